"""Greedy D-optimal pose selection: its running log det is the selection's, it picks the
extremes for a straight line, and it beats random subsets of the same size."""
import numpy as np
import pytest

from deltatwin.calibration.design.poses import (
    greedy_selection,
    log_det_information,
    mean_prediction_variance,
)


def test_straight_line_picks_the_ends():
    x = np.linspace(-1.0, 1.0, 21)
    blocks = np.stack([np.ones_like(x), x], axis=1)[:, None, :] * 100.0   # (21, 1, 2)
    order, _ = greedy_selection(blocks, 2)
    assert sorted(order.tolist()) == [0, 20]


def test_running_log_det_is_the_selections_and_beats_random():
    rng = np.random.default_rng(5)
    blocks = rng.normal(size=(300, 3, 12)) * rng.uniform(0.1, 3.0, size=(1, 1, 12))
    order, logdet = greedy_selection(blocks, 40)
    assert len(set(order.tolist())) == 40
    for k in (1, 10, 40):
        assert logdet[k - 1] == pytest.approx(log_det_information(blocks[order[:k]]), rel=1e-9)
    random_best = max(log_det_information(blocks[rng.choice(300, 40, replace=False)])
                      for _ in range(200))
    assert logdet[-1] > random_best


def test_too_many_points_refused():
    with pytest.raises(ValueError, match="n_select"):
        greedy_selection(np.ones((3, 1, 2)), 4)


def test_i_optimal_running_value_is_the_selections_prediction_variance():
    rng = np.random.default_rng(6)
    blocks = rng.normal(size=(200, 3, 8))
    region = rng.normal(size=(50, 3, 8))
    order, value = greedy_selection(blocks, 25, "I", region)
    for k in (1, 25):
        assert value[k - 1] == pytest.approx(mean_prediction_variance(blocks[order[:k]], region),
                                             rel=1e-9)
    random_best = min(mean_prediction_variance(blocks[rng.choice(200, 25, replace=False)], region)
                      for _ in range(200))
    assert value[-1] < random_best
