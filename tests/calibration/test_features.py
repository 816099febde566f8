"""Feature families, presets and causal temperature derivatives."""
import numpy as np
import pandas as pd
import pytest

from deltatwin.calibration.blackbox.features import (
    FeatureSet,
    Monomials,
    Product,
    causal_derivatives,
    force_ladder,
    force_preset,
    geometric,
    temperature_variables,
    temperatures,
    thermal_ladder,
    thermal_preset,
)
from deltatwin.calibration.errors import (
    CalibrationInputError,
    MissingColumnsError,
    MissingMetadataWarning,
)

SENSORS9 = [f"s{i}" for i in range(9)]


def test_geometric_family_has_19_monomials_of_order_1_to_3():
    names = [t.name for t in geometric().terms()]
    assert len(names) == 19 and len(set(names)) == 19
    assert names[:3] == ["q1", "q2", "q3"]
    assert "q1*q2*q3" in names and "q3^3" in names and "q1^2*q2" in names
    assert len(Monomials(("X", "Y", "Z"), (2,)).terms()) == 6


def test_presets_have_the_papers_sizes_and_order():
    th = thermal_preset(SENSORS9)
    assert len(th) == 217
    assert [f.name for f in th.families] == ["geometric", "temperatures",
                                             "geometric x temperature", "temperature rates",
                                             "temperature accelerations"]
    assert [len(f) for f in th.families] == [19, 9, 171, 9, 9]
    assert "q1^2*q3*T_s4" in th.names and "d2T_s8" in th.names
    fo = force_preset()
    assert len(fo) == 79
    assert fo.names[19:22] == ["F", "F^2", "F^3"] and "X*Y*Z*F^3" in fo.names
    assert [len(fs) for _, fs in thermal_ladder(SENSORS9)] == [19, 28, 199, 217]
    assert [len(fs) for _, fs in force_ladder()] == [19, 79]


def test_feature_set_round_trips_and_detects_edits():
    th = thermal_preset(["a", "b"])
    d = th.to_dict()
    back = FeatureSet.from_dict(d)
    assert back.names == th.names and back.signature == th.signature
    d["families"][1]["variables"] = ["T_a", "T_c"]
    with pytest.raises(CalibrationInputError, match="signature"):
        FeatureSet.from_dict(d)
    with pytest.raises(CalibrationInputError, match="duplicate"):
        FeatureSet([geometric(), geometric()])


def test_matrix_evaluates_monomials_and_names_missing_variables():
    fs = FeatureSet([geometric(), Product(geometric(), temperatures(["a"]))])
    rng = np.random.default_rng(0)
    v = {"q1": rng.normal(size=5), "q2": rng.normal(size=5), "q3": rng.normal(size=5),
         "T_a": rng.normal(size=5)}
    M = fs.matrix(v)
    j = fs.names.index("q1^2*q3*T_a")
    assert np.allclose(M[:, j], v["q1"] ** 2 * v["q3"] * v["T_a"], rtol=1e-15)
    with pytest.raises(MissingColumnsError, match="T_a"):
        fs.matrix({k: v[k] for k in ("q1", "q2", "q3")})


def _uneven_times(rng, n=600):
    return np.cumsum(rng.uniform(4.0, 16.0, n))


def test_causal_derivatives_exact_on_a_quadratic_with_uneven_sampling():
    t = _uneven_times(np.random.default_rng(1))
    T = 21.5 + 3e-4 * t - 2e-8 * t**2
    d1, d2, n_used = causal_derivatives(t, T, window_s=600.0)
    full = n_used >= 3
    assert np.allclose(d1[full], 3e-4 - 4e-8 * t[full], rtol=0, atol=1e-13)
    assert np.allclose(d2[full], -4e-8, rtol=0, atol=1e-15)
    assert d1[0] == 0.0 and d2[0] == 0.0                  # nothing before the first sample
    assert d1[1] == pytest.approx((T[1] - T[0]) / (t[1] - t[0]))


def test_causal_derivatives_track_a_slow_sinusoid_within_the_local_fit_bias():
    t = _uneven_times(np.random.default_rng(2), 2000)
    w = 2 * np.pi / 14400.0                               # a 4 h room cycle
    A = 0.8
    T = 22 + A * np.sin(w * t)
    d1, d2, n_used = causal_derivatives(t, T, window_s=600.0)
    m = t > 600.0
    # end-point bias of a local quadratic ~ T''' W^2 / 10-ish: a few % here
    assert np.max(np.abs(d1[m] - A * w * np.cos(w * t[m]))) < 0.02 * A * w
    assert np.max(np.abs(d2[m] + A * w**2 * np.sin(w * t[m]))) < 0.2 * A * w**2


def test_causal_derivatives_use_no_future_sample():
    rng = np.random.default_rng(3)
    t = _uneven_times(rng, 300)
    T = 22 + np.cumsum(rng.normal(0, 1e-3, 300))
    d1, d2, _ = causal_derivatives(t, T)
    T2 = T.copy()
    T2[200:] += 5.0                                       # change the future of sample 199
    e1, e2, _ = causal_derivatives(t, T2)
    assert np.array_equal(d1[:200], e1[:200]) and np.array_equal(d2[:200], e2[:200])
    assert not np.allclose(d1[200:], e1[200:])


def test_causal_derivatives_reject_bad_input():
    with pytest.raises(CalibrationInputError, match="non-decreasing"):
        causal_derivatives([0.0, 2.0, 1.0], [1.0, 2.0, 3.0])
    with pytest.raises(CalibrationInputError, match="finite"):
        causal_derivatives([0.0, 1.0], [1.0, np.nan])


def test_temperature_variables_per_session_in_time_order_and_SI():
    rng = np.random.default_rng(4)
    t_a = _uneven_times(rng, 100)
    t_b = t_a[-1] + 5000 + _uneven_times(rng, 100)
    t = np.concatenate([t_a, t_b])
    T = np.concatenate([20.0 + 1e-3 * t_a, 30.0 - 2e-3 * (t_b - t_b[0])])
    df = pd.DataFrame({"t_s": t, "session": ["xy"] * 100 + ["z"] * 100, "T_a_C": T})
    df = df.sample(frac=1.0, random_state=1).reset_index(drop=True)      # shuffled rows
    v = temperature_variables(df, ["a"], {"T_a", "dT_a", "d2T_a"}, 293.15, 600.0)
    sess = df["session"].to_numpy()
    T_in = df["T_a_C"].to_numpy()
    assert np.allclose(v["T_a"], T_in + 273.15 - 293.15)
    tt = df["t_s"].to_numpy()
    first_z = tt == t_b[0]
    assert v["dT_a"][first_z] == 0.0                      # the z session starts afresh
    late = np.isin(tt, np.concatenate([t_a[5:], t_b[5:]]))
    expect = np.where(sess == "xy", 1e-3, -2e-3)
    assert np.allclose(v["dT_a"][late], expect[late], atol=1e-12)
    with pytest.raises(MissingColumnsError, match="T_b_C"):
        temperature_variables(df, ["b"], {"T_b"}, 293.15, 600.0)
    with pytest.warns(MissingMetadataWarning, match="session"):
        temperature_variables(df.drop(columns="session"), ["a"], {"dT_a"}, 293.15, 600.0)


def test_causal_fit_of_many_streams_equals_a_window_by_window_least_squares():
    """One call for several columns against each sample's own least-squares polynomial over
    its trailing window (numpy lstsq), uneven times with repeats and a window start."""
    from deltatwin.calibration.streams import causal_fit
    rng = np.random.default_rng(11)
    t = np.sort(np.concatenate([rng.uniform(0.0, 3000.0, 300), [5.0, 5.0, 5.0]]))
    v = np.stack([20.0 + 1e-3 * rng.normal(size=t.size), np.sin(t / 500.0),
                  1e-4 * t + rng.normal(size=t.size)], axis=1)
    for degree in (1, 2):
        level, d1, d2, count = causal_fit(t, v, 600.0, degree)
        for i in range(0, t.size, 7):
            window = np.flatnonzero((t >= t[i] - 600.0) & (np.arange(t.size) <= i))  # causal
            assert count[i] == window.size
            dg = min(degree, np.unique(t[window]).size - 1)
            if dg == 0:
                assert np.array_equal(level[i], v[i]) and not d1[i].any() and not d2[i].any()
                continue
            tau = (t[window] - t[i]) / 600.0
            coef = np.linalg.lstsq(np.vander(tau, dg + 1, increasing=True),
                                   v[window] - v[i], rcond=None)[0]
            assert np.allclose(level[i], v[i] + coef[0], rtol=0, atol=1e-12 * np.abs(v).max())
            assert np.allclose(d1[i], coef[1] / 600.0, rtol=1e-9, atol=1e-15)
            if dg == 2:
                assert np.allclose(d2[i], 2 * coef[2] / 600.0 ** 2, rtol=1e-9, atol=1e-18)
