"""The joint form's least squares (model_form._Joint) against numpy's, including its kept
factorisation of the leading blocks and rank-deficient blocks."""
import numpy as np

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
