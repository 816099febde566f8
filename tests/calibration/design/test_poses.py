"""Greedy D-optimal pose selection: its running log det is the selection's, it picks the
extremes for a straight line, and it beats random subsets of the same size; the campaign
studies (fractions against random subsets, load levels, order) on small force campaigns."""
import numpy as np
import pytest

from deltatwin.calibration.design.budget import without_random_errors
from deltatwin.calibration.design.poses import (
    fraction_study,
    fraction_summary,
    greedy_selection,
    load_level_study,
    log_det_information,
    mean_prediction_variance,
    order_study,
)
from deltatwin.twin.scenario import Scenario


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


@pytest.fixture(scope="module")
def force_campaign():
    """The force paper's grids at a tenth of their points, and the same campaign read without
    random errors."""
    sc = Scenario.load("quiet/magnetic-force")
    df, meta = sc.simulate(0.1)
    return df, meta, without_random_errors(sc).simulate(0.1)[0], sc.settings.noise_floor_m


def test_noise_free_copy_differs_by_the_reading_noise(force_campaign):
    df, _, clean, sigma = force_campaign
    diff = np.concatenate([(df[c] - clean[c]).to_numpy() for c in ("x_nm", "y_nm", "z_nm")])
    # 4 readings per point: the point's reading has sigma / 2 (a constant per axis: the zero's)
    assert np.std(diff) == pytest.approx(sigma * 1e9 / 2, rel=0.15)
    assert np.array_equal(df.q1_rad, clean.q1_rad) and np.array_equal(df.F_N, clean.F_N)


def test_fraction_study_ranks_the_optimal_subsets_against_random_ones(force_campaign):
    df, meta, clean, sigma = force_campaign
    study = fraction_study(df, meta, ["magnetic_force"], [1 / 3], sigma,
                           np.random.default_rng(3), n_random=1, clean=clean)
    assert list(study.selection) == ["all", "D_optimal", "I_optimal", "random"]
    rand = study[study.selection == "random"]
    d = study[study.selection == "D_optimal"].iloc[0]
    i = study[study.selection == "I_optimal"].iloc[0]
    assert d.log_det > rand.log_det.max()
    assert i.mean_prediction_variance < rand.mean_prediction_variance.min()
    assert np.isfinite(study.truth_err90_nm).all()
    summary = fraction_summary(study, "truth_err90_nm")
    assert list(summary.selection) == ["D_optimal", "I_optimal"]
    assert summary.random_worse_share.between(0, 1).all() and (summary.random_draws == 1).all()


@pytest.mark.slow
def test_load_levels_ranked_by_information(force_campaign):
    df, meta, clean, sigma = force_campaign
    t = load_level_study(df, meta, ["magnetic_force"], 4, sigma, clean=clean)
    assert len(t) == 5 + 1                          # C(5, 4) subsets and the campaign's own
    assert t.levels_N.iloc[0] == [0.0, 0.5, 1.0, 1.5, 2.0]    # a superset informs the most
    assert list(t.log_det) == sorted(t.log_det, reverse=True)
    # the force's signature grows with the load: the subset without 2 N informs the least
    assert 2.0 not in t.levels_N.iloc[-1]
    with pytest.raises(ValueError, match="n_levels"):
        load_level_study(df, meta, ["magnetic_force"], 6, sigma)


def test_order_study_compares_both_orders_on_one_campaign():
    t = order_study("paper-force", {"drift": ["loop_drift"]}, 0.05, [1], 7e-9)
    assert list(t.order) == ["papers", "interleaved"] and (t.status == "ok").all()
    assert np.isfinite(t[["val_err90_nm", "truth_err90_nm",
                          "validation_prediction_variance"]].to_numpy()).all()
    with pytest.raises(ValueError, match="force campaign"):
        order_study("quiet/gravity-sag", {"m": ["gravity_sag"]}, 0.02, [1], 5e-9)
