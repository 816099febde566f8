"""The joint form's least squares (model_form._Joint) against numpy's, including its kept
factorisation of the leading blocks and rank-deficient blocks."""
import numpy as np
import pytest

from deltatwin.calibration.diagnosis.model_form import _Joint


def _joint(r):
    joint = object.__new__(_Joint)        # only the residual: least_squares needs nothing else
    joint.r = r
    return joint


def _numpy(blocks, r):
    X = np.hstack(blocks)
    norm = np.linalg.norm(X, axis=0)
    norm[norm == 0] = 1.0
    coef, _, rank, _ = np.linalg.lstsq(X / norm, r, rcond=None)
    return coef / norm, rank


def test_least_squares_is_numpys_with_and_without_the_kept_factorisation():
    rng = np.random.default_rng(21)
    n = 500
    r = rng.normal(size=n)
    x = rng.normal(size=n)
    blocks = [rng.normal(size=(n, 2)) * [1e-9, 3.0],                 # columns of mixed size
              np.column_stack([x, x ** 2]),
              np.column_stack([2 * x, rng.normal(size=n)]),           # x again: rank deficient
              np.zeros((n, 1)),                                       # a column without values
              rng.normal(size=(n, 3))]
    joint = _joint(r)
    for lead in ([], [0], [0, 1], [0, 1, 2], [0, 1, 2, 3]):
        for last in range(len(blocks)):
            if last in lead:
                continue
            trial = [blocks[j] for j in lead + [last]]
            coef, rank = joint.least_squares(trial)
            want, want_rank = _numpy(trial, r)
            assert rank == want_rank, (lead, last)
            np.testing.assert_allclose(coef, want, rtol=1e-9, atol=1e-12 * np.abs(want).max())
            # the residual it leaves is the least-squares one
            np.testing.assert_allclose(np.hstack(trial) @ coef, np.hstack(trial) @ want,
                                       rtol=0, atol=1e-12)
    # the leading blocks' factorisation was kept between the calls that share them
    assert len(joint._lead[0]) == 4 and joint._lead[0][3] is blocks[3]


def _stepped_joint(rng):
    """A _Joint of two reading axes' calibration readings (axis 2 in two sessions, axis 0 in
    one) whose model spans a drift in time (t and t^2 in each session, their means out), the
    residual a 40 nm step on axis 2 at 1300 s with the drift's part taken out (what a fitted
    model leaves: its drift has followed the step), plus 1 nm noise."""
    n = 240
    t = np.sort(rng.uniform(0.0, 3600.0, 2 * n))
    rows2 = rng.permutation(2 * n)[:n]                   # axis 2's readings in any order
    rows0 = np.setdiff1d(np.arange(2 * n), rows2)
    session = (np.arange(2 * n) % 2).astype(int)
    groups, place = [], 0
    for k, rows in ((2, rows2), (0, rows0)):
        for s in ((0, 1) if k == 2 else (None,)):
            cal_g = rows[session[rows] == s] if s is not None else rows
            groups.append((k, cal_g, slice(place, place + cal_g.size), None, None))
            place += cal_g.size
    all_rows = np.concatenate([g[1] for g in groups])
    demean = np.zeros((place, place))
    for g in groups:
        idx = np.arange(place)[g[2]]
        demean[np.ix_(idx, idx)] = np.eye(idx.size) - 1.0 / idx.size
    tt = t[all_rows] / 3600.0
    drift = np.column_stack([(tt ** p) * np.isin(all_rows, rows2) for p in (1, 2)]
                            + [(tt ** p) * np.isin(all_rows, rows0) for p in (1, 2)])
    Qm = np.linalg.qr(demean @ drift)[0]
    step = 40e-9 * (t[all_rows] > 1300.0) * np.isin(all_rows, rows2)
    r = demean @ (step + 1e-9 * rng.normal(size=place))
    r -= Qm @ (Qm.T @ r)
    joint = object.__new__(_Joint)
    joint.r, joint.Qm, joint.groups, joint.n_cal = r, Qm, groups, place
    return joint, t, demean


def test_the_step_scan_fits_the_step_with_the_models_drift_readjusted():
    """``_Joint.best_step`` is the brute-force argmax of the step's gain with the model's
    directions re-adjusted (each candidate moment's indicator projected explicitly, each
    session's mean out), and finds the step the model's drift has followed."""
    joint, t, demean = _stepped_joint(np.random.default_rng(12))
    tau = joint.best_step(t)
    taus = np.unique(t)
    taus = 0.5 * (taus[:-1] + taus[1:])
    brute = []
    for cand in taus:
        total = 0.0
        for k in (2, 0):
            h = np.zeros(joint.n_cal)
            for g in joint.groups:
                if g[0] == k:
                    h[g[2]] = t[g[1]] > cand
            h = demean @ h
            P = h - joint.Qm @ (joint.Qm.T @ h)
            total += (joint.r @ h) ** 2 / (P @ P) if P @ P > 1e-6 * (h @ h) else 0.0
        brute.append(total)
    assert tau == taus[int(np.argmax(brute))]
    assert abs(tau - 1300.0) < 30.0
    # a session without calibration readings on the axis changes nothing (it has no mean)
    joint.groups = joint.groups + [(2, np.zeros(0, int), slice(joint.n_cal, joint.n_cal),
                                    None, None)]
    assert joint.best_step(t) == tau
    # no step the model does not span: no moment (the residual's own scan stands)
    joint.r = np.zeros_like(joint.r)
    assert joint.best_step(t) is None


def test_model_span_keeps_the_rank_rule_of_each_routine_it_stands_for():
    """model_form.ModelSpan (one SVD of the model's directions for the diagnosis) gives what
    _orthonormal, np.linalg.pinv and np.linalg.lstsq give, each with its own rank rule: singular
    values a decade either side of 1e-10, 1e-15 and eps max(n, k) of the largest."""
    from deltatwin.calibration.diagnosis.model_form import ModelSpan, _orthonormal

    rng = np.random.default_rng(31)
    n = 400
    eps_n = np.finfo(float).eps * n
    s = np.array([1.0, 0.3, 1e-9, 1e-11, 10 * eps_n, 0.1 * eps_n, 1e-17])
    U = np.linalg.qr(rng.normal(size=(n, s.size)))[0]
    V = np.linalg.qr(rng.normal(size=(s.size, s.size)))[0]
    Jm = (U * s) @ V.T
    r = rng.normal(size=n)
    span = ModelSpan(Jm)
    Q, Q_svd = span.orthonormal(), _orthonormal(Jm)
    assert Q.shape == Q_svd.shape == (n, 3)
    np.testing.assert_allclose(Q @ Q.T, Q_svd @ Q_svd.T, atol=1e-12)
    want = np.linalg.pinv(Jm)
    got = span.pinv()
    assert np.linalg.matrix_rank(got @ Jm, tol=0.5) == 6      # 1e-15 of the largest keeps six
    np.testing.assert_allclose(got, want, rtol=0, atol=1e-12 * np.abs(want).max())
    want = np.linalg.lstsq(Jm, r, rcond=None)
    got = span.lstsq(r)
    assert want[2] == 5                                        # eps max(n, k): five
    along = V.T @ got                     # the solution along each singular direction
    assert abs(along[4]) > 1e11 and abs(along[5]) < 1e-4 * abs(along[4])   # five, not six
    assert abs((V.T @ span.pinv() @ r)[5]) > 1e13                           # pinv's six
    # equal to LAPACK's to its own round-off along a 1e-12 direction (condition 1e12)
    assert np.linalg.norm(got - want[0]) < 1e-3 * np.linalg.norm(want[0])
    assert span.U.shape == (n, s.size)         # the model's span, as QR's Q: every column


def test_one_column_is_normalised_as_the_svd_would():
    """_orthonormal of one column is the column at unit norm (the SVD's vector up to its sign);
    a zero column has no basis, and one whose squares underflow goes to the SVD."""
    from deltatwin.calibration.diagnosis.model_form import _orthonormal

    x = np.random.default_rng(5).normal(size=(300, 1))
    u = np.linalg.svd(x, full_matrices=False)[0]
    got = _orthonormal(x)
    np.testing.assert_allclose(np.abs(got), np.abs(u), atol=1e-15)
    assert _orthonormal(np.zeros((300, 1))).shape == (300, 0)
    tiny = _orthonormal(x * 1e-170)
    assert tiny.shape == (300, 1)
    np.testing.assert_allclose(np.abs(tiny), np.abs(u), atol=1e-14)


def _screened_frame(rng, n=600, n_val=300):
    """A JointFrame on a synthetic _Joint (no model directions, three reading axes): the
    calibration residual r, the validation residual b, and blocks (P, D) of columns."""
    from deltatwin.calibration.diagnosis.model_form import JointFrame

    joint = object.__new__(_Joint)
    joint.r, joint.b = rng.normal(size=n), rng.normal(size=n_val)
    joint.axis_of = np.repeat(np.arange(3), n_val // 3)
    joint.Qm, joint.n_groups = np.zeros((n, 0)), 3
    frame = object.__new__(JointFrame)
    frame.joint, frame.axes, frame.n_axes = joint, [0, 1, 2], 3
    x, y = rng.normal(size=n), rng.normal(size=n_val)
    blocks = [(np.column_stack([x, x ** 2]) * [1.0, 1e-6], np.column_stack([y, y ** 2]) * [1.0, 1e-6]),
              (np.column_stack([2 * x + 1e-5 * rng.normal(size=n), rng.normal(size=n)]),
               rng.normal(size=(n_val, 2))),                     # nearly x again
              (np.column_stack([3 * x, x ** 2]), rng.normal(size=(n_val, 2))),   # x, x^2 again
              (np.zeros((n, 1)), np.zeros((n_val, 1)))]           # a column without values
    # blocks that explain part of r (and of b: their validation columns follow it)
    for scale in (0.3, 0.1, 0.1, 0.02):
        P, D, beta = rng.normal(size=(n, 3)), rng.normal(size=(n_val, 3)), rng.normal(size=3)
        joint.r, joint.b = joint.r + scale * P @ beta, joint.b + scale * D @ beta
        blocks.append((P, D))
    return frame, blocks


def test_estimates_are_the_fits_within_their_bounds_and_unsure_where_dependent():
    """_Joint.estimates (a forward selection's screen) against the exact fit of every lead and
    trial: within its bounds (and far inside them) where it estimates, None for a block (or a
    lead) nearly dependent or without values."""
    frame, blocks = _screened_frame(np.random.default_rng(8))
    for lead in ([], [0], [4], [4, 5], [0, 1]):
        trials = [i for i in range(len(blocks)) if i not in lead]
        ests = frame.estimates([blocks[j] for j in lead], [blocks[i] for i in trials])
        for i, est in zip(trials, ests):
            if lead == [0, 1]:                  # the lead itself nearly dependent
                assert est is None
                continue
            if i == 3 or (i in (1, 2) and 0 in lead):
                # a zero column; x nearly and exactly again (block 0's x^2 at 1e-6 is fine)
                assert est is None, (lead, i)
                continue
            exact = frame.fit([blocks[j] for j in lead + [i]])
            assert est is not None, (lead, i)
            assert est["rank"] == exact["rank"] and est["dof"] == exact["dof"]
            assert abs(est["rss"] - exact["rss_cal"]) < 1e-3 * est["rss_tol"]
            assert abs(est["rss"] - exact["rss_cal"]) < 1e-11 * exact["rss_cal"]
            assert abs(est["val_power"] - exact["val_power"]) < 1e-3 * est["val_tol"]


def test_the_screened_forward_step_is_the_exhaustive_one():
    """attribution._best_addition (estimates rule out, a few are fitted) chooses what fitting
    every trial chooses (the largest validation gain among the terms that qualify, the first of
    equal ones), with the same p value and fit, fitting a few of them."""
    from deltatwin.calibration.diagnosis.attribution import Term, _best_addition, _joins

    frame, blocks = _screened_frame(np.random.default_rng(9))
    blocks.append(blocks[5])                 # an equal twin of block 5: the first one wins
    terms = [Term(f"v{i}", "power 1", np.zeros((1, 1)), scanned=int(i == 6))
             for i in range(len(blocks))]
    fitted = []
    fit = frame.fit
    frame.fit = lambda bl: (fitted.append(len(bl)), fit(bl))[1]
    for chosen in ([], [4], [4, 6], [0, 4, 6]):
        current = fit([blocks[j] for j in chosen])
        trials = [i for i in range(len(blocks)) if i not in chosen]
        # the selection's thresholds; a p value too strict; every term qualifying (the unsure
        # ones too: fitted first, not the best); no term qualifying
        for limit, min_gain in ((1e-3, 0.02 * current["val_power"]), (1e-30, 0.0),
                                (1.0, -np.inf), (1e-3, 1e9)):
            want = None
            for i in trials:        # the exhaustive selection: every trial fitted
                after = fit([blocks[j] for j in chosen + [i]])
                joins = _joins(terms[i], after, current, 3, limit, min_gain)
                if joins is not None and (want is None or joins[0] > want[1]):
                    want = (i, *joins, after)
            fitted.clear()
            got = _best_addition(frame, terms, blocks, chosen, trials, current, limit, min_gain)
            if want is None:
                assert got is None
                continue
            assert got[:3] == want[:3] and got[3] == want[3], (chosen, limit)
            # the unsure trials (1, 2, 3 and their like) are fitted, a few others
            assert len(fitted) <= 6, (chosen, fitted)


def test_rss_each_is_the_fit_of_each_column_alone():
    """attribution.Residual.rss_each (the ramp's moment scanned in one pass) is the calibration
    sum of squares ``Residual.fit`` leaves after each column alone: two axes, sessions with
    their own zeros, a validation period, a column of zeros and one zero on the calibration
    rows after the session means."""
    from deltatwin.calibration.diagnosis.attribution import Residual

    rng = np.random.default_rng(17)
    n = 400
    t = np.sort(rng.uniform(0.0, 7200.0, n))
    session = np.where(t < 3000.0, "a", "b")
    cal = t < 5000.0
    res = np.column_stack([1e-8 * np.maximum(t - 2500.0, 0.0) / 3600 + 1e-9 * rng.normal(size=n),
                           np.full(n, np.nan), 3e-9 * np.sin(t / 500.0)])
    res[::7, 2] = np.nan                               # axis 2 not read on every row
    target = Residual(res, cal, ~cal, session, t)
    taus = np.quantile(t[cal], np.linspace(0.05, 0.95, 19))
    X = np.column_stack([np.maximum(t[:, None] - taus, 0.0), np.zeros(n),
                         (session == "a").astype(float)])
    got = target.rss_each(X)
    want = np.array([target.fit(X[:, [j]])[1]["rss_cal"] for j in range(X.shape[1])])
    np.testing.assert_allclose(got, want, rtol=1e-12)
    assert np.argmin(got) == np.argmin(want)
    assert got[-2] == pytest.approx(target.fit(X[:, :0])[1]["rss_cal"], rel=1e-14)   # nothing fitted


def test_the_screened_forward_selection_is_the_exhaustive_one(monkeypatch):
    """model_form._forward with its trials screened by _Joint.gains chooses the blocks that
    trying every block chooses (gains all unsure: every trial made), with variables of several
    blocks (the alike ones tried in the strongest's place) and physical alternatives, making
    fewer trials."""
    from deltatwin.calibration.diagnosis import model_form

    rng = np.random.default_rng(23)
    frame, pairs = _screened_frame(rng, n=900, n_val=450)
    joint = frame.joint
    n, n_val = joint.r.size, joint.b.size
    x = rng.normal(size=n)
    # a variable's powers on three "axes" (blocks of its own), one the residual follows
    for k in (1, 2, 3):
        P = np.column_stack([x ** k, rng.normal(size=n)])
        pairs.append((P, rng.normal(size=(n_val, 2))))
    joint.r = joint.r + 0.2 * pairs[-2][0] @ [1.0, 0.3]
    joint.b = joint.b + 0.2 * pairs[-2][1] @ [1.0, 0.3]
    blocks = [(P, D, int(i % 3 == 0)) for i, (P, D) in enumerate(pairs)]
    variable_of = ["a", "a", "a", "z", "b", "c", "d", "e", "x", "x", "x"]
    physical = {8: [4, 9], 10: [5]}
    made, chosen = [], []
    orthonormal = model_form._orthonormal
    monkeypatch.setattr(model_form, "_orthonormal", lambda X: (made.append(1), orthonormal(X))[1])
    for alpha, min_share in ((1e-3, 0.02), (1.0, 0.0), (1e-3, 0.5)):
        args = (joint, blocks, alpha, min_share, lambda chosen, i: len(chosen) < 5,
                frozenset({7}), physical, variable_of)
        made.clear()
        got = model_form._forward(*args)
        n_screened = len(made)
        monkeypatch.setattr(joint, "gains", lambda basis, Ps: [None] * len(Ps))
        made.clear()
        want = model_form._forward(*args)
        monkeypatch.undo()
        monkeypatch.setattr(model_form, "_orthonormal",
                            lambda X: (made.append(1), orthonormal(X))[1])
        assert got == want, (alpha, min_share)
        assert n_screened < len(made), (alpha, min_share)
        chosen.append(got)
    assert len(chosen[0]) >= 2 and len(chosen[1]) > len(chosen[0]) and not chosen[2]


def test_the_screened_forward_selection_makes_the_trials_its_choice_depends_on():
    """_forward's strongest block fails on validation; a weaker block of the same variable
    (not significantly weaker on the calibration rows) would join in its place, and before it
    its physical form (not significantly weaker than it) does: the screen makes those trials
    though their gains are below the strongest's."""
    from deltatwin.calibration.diagnosis import model_form

    rng = np.random.default_rng(29)
    frame, _ = _screened_frame(rng, n=3000, n_val=1500)
    joint = frame.joint
    n, n_val = joint.r.size, joint.b.size
    u, v = rng.normal(size=n), rng.normal(size=n_val)
    joint.r = rng.normal(size=n) + 0.3 * u
    joint.b = rng.normal(size=n_val) + 0.3 * v
    col = lambda x: x[:, None]
    blocks = [(col(u + 0.02 * rng.normal(size=n)), col(rng.normal(size=n_val)), 0),   # x: fails
              (col(u + 0.15 * rng.normal(size=n)), col(v), 0),                         # x
              (col(u + 0.20 * rng.normal(size=n)), col(v + 0.01 * rng.normal(size=n_val)), 0),
              (col(rng.normal(size=n)), col(rng.normal(size=n_val)), 0)]
    args = (joint, blocks, 1e-3, 0.02, lambda chosen, i: len(chosen) < 1, frozenset(),
            {1: [2]}, ["x", "x", "load", "y"])
    want = [2]                      # the physical form of the weaker block of x
    assert model_form._forward(*args) == want
    gains = joint.gains(np.zeros((n, 0)), [P for P, _, _ in blocks])
    assert all(g is not None for g in gains) and gains[0][0] > gains[1][0] + 10 * gains[1][1]
    assert gains[1][0] > gains[2][0] + 10 * gains[2][1]
