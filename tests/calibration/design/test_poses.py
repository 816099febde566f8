"""Greedy D-optimal pose selection: its running log det is the selection's, it picks the
extremes for a straight line, and it beats random subsets of the same size."""
import numpy as np
import pytest

from deltatwin.calibration.design.poses import greedy_d_optimal, log_det_information


def test_straight_line_picks_the_ends():
    x = np.linspace(-1.0, 1.0, 21)
    blocks = np.stack([np.ones_like(x), x], axis=1)[:, None, :] * 100.0   # (21, 1, 2)
    order, _ = greedy_d_optimal(blocks, 2)
    assert sorted(order.tolist()) == [0, 20]


def test_running_log_det_is_the_selections_and_beats_random():
    rng = np.random.default_rng(5)
    blocks = rng.normal(size=(300, 3, 12)) * rng.uniform(0.1, 3.0, size=(1, 1, 12))
    order, logdet = greedy_d_optimal(blocks, 40)
    assert len(set(order.tolist())) == 40
    for k in (1, 10, 40):
        assert logdet[k - 1] == pytest.approx(log_det_information(blocks[order[:k]]), rel=1e-9)
    random_best = max(log_det_information(blocks[rng.choice(300, 40, replace=False)])
                      for _ in range(200))
    assert logdet[-1] > random_best


def test_too_many_points_refused():
    with pytest.raises(ValueError, match="n_select"):
        greedy_d_optimal(np.ones((3, 1, 2)), 4)
