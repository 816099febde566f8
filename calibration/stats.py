"""The statistical rule the calibration decides by: one place for the nested-model test, the
information criterion, the rows' serial correlation and the validation rows' evidence.

A physics model's residual is not independent noise: a thermometer's error through a lever and
a model's slow misfit stay correlated over tens of readings, and the validation rows of a
papers'-order campaign come after the calibration rows, warmer, so most of their residual is a
per-(session, axis) drift offset that every model shares. The rule accounts for both:

- **Calibration rows: the nested F test.** A bigger model (``k`` more directions) against a
  smaller one, both fitted on the calibration rows: ``F = ((rss0 - rss1) / k) / (rss1 / df2)``
  divided by the serial-correlation factor of what the bigger model explains
  (``serial_inflation``), against F(k, df2).
- **The information criterion.** ``bic_change``: n ln(rss1 / rss0) + k ln n (Schwarz 1978);
  negative when the bigger model is preferred.
- **Validation rows: an offset-immune block test.** ``validation_p`` regresses the smaller
  model's validation residual on the change the bigger one makes, with every (session, axis)
  group's mean removed from both (a constant offset, whatever its size, is no evidence), and
  judges the slope by a cluster-robust t statistic over contiguous time blocks of each
  session, every axis of a block in it (Bester, Conley & Hansen 2011, J. Econometrics 165:
  with a fixed number G of large blocks, the cluster-covariance t statistic follows Student's
  t with G - 1 degrees of freedom). It
  counts independent blocks, not correlated readings: it holds its level as long as a block
  is longer than the residual's correlation time (tests/calibration/test_stats.py).
- **Combining the two.** The calibration and validation rows are disjoint readings, so their
  p-values are combined by Fisher's method (chi-square with 4 degrees of freedom).

- **Relevance.** A claim must matter to the model's error, not only be detectable: a claim by
  the calibration test explains at least ``min_explained`` of the validation residual's power
  or closes ``gap_closed`` of the gap between the model's validation error and its achievable
  floor, and is not made for a model within ``at_floor`` of that floor (what is left there is
  the floor's own error); a claim by the combined test must close ``gap_closed`` of the gap.

``DecisionRule`` holds the rule's few named parameters (the module's constants are their
defaults); the diagnosis, its ladder and detection power (calibration/design/power.py) use it,
and tests/calibration/test_stats.py measures its false-claim rate on null data where the truth
is known.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy import special

ALPHA = 1e-3                 # the false-claim rate the rule is run at
VALIDATION_BLOCKS = 8        # contiguous time blocks per session of validation rows, at most
BLOCK_CORRELATIONS = 10      # a block is at least this many of the score's correlation lengths
MIN_EXPLAINED = 0.1          # a calibration claim explains this share of the validation power
GAP_CLOSED = 0.5             # ... or closes this share of the gap to the achievable floor
AT_FLOOR = 1.1               # a model within this factor of the achievable floor is at it
# a candidate whose signature lies this much in the model's span is absorbed (reported so)
ABSORBED = 0.9
# a candidate explaining less than this share of what generic functions of the laboratory
# variables explain, and nothing beyond them, is a correlate of the missing term, not it
GENERIC_SHARE = 0.5


def f_test_p(rss0: float, rss1: float, df1: int, df2: int, inflation: float = 1.0) -> float:
    """p-value of the nested F test: ``rss0`` (m^2) of the smaller model, ``rss1`` of the
    bigger one with ``df1`` more directions, ``df2`` residual degrees of freedom;
    ``inflation``: the variance of the explained part over that of independent rows
    (``serial_inflation``, >= 1): the statistic is divided by it and the residual's degrees of
    freedom are the effective number of independent rows, ``df2 / inflation``. 1 when the
    bigger model explains nothing."""
    df1 = max(int(df1), 1)
    if not (rss1 > 0 and rss0 > rss1 and df2 > 0):
        return 1.0
    inflation = max(inflation, 1.0)
    F = ((rss0 - rss1) / df1) / (rss1 / df2) / inflation
    # scipy.stats.f.sf, without scipy.stats
    return float(special.fdtrc(df1, max(df2 / inflation, 1.0), F))


def bic_change(n, rss0, rss1, k):
    """Change of the Bayesian information criterion from the smaller model (``rss0``) to the
    bigger one (``rss1``, ``k`` more parameters) on ``n`` readings; numpy arrays broadcast."""
    n = np.maximum(n, 1)
    return n * np.log(np.maximum(rss1, 1e-300) / np.maximum(rss0, 1e-300)) + k * np.log(n)


def f_at_zero_bic(n: int, k: int, df2: int) -> float:
    """The F statistic above which ``bic_change`` is negative (``k`` >= 1 directions added to a
    model of ``df2`` residual degrees of freedom on ``n`` readings)."""
    k = max(int(k), 1)
    return (n ** (k / n) - 1.0) * df2 / k


def fisher_p(*p_values: float) -> float:
    """Fisher's combination of independent p-values: the chi-square tail of -2 sum ln p with
    2 x (their number) degrees of freedom."""
    stat = -2.0 * sum(math.log(max(p, 1e-300)) for p in p_values)
    return float(special.chdtrc(2 * len(p_values), stat))


def serial_inflation(group_sizes, explained: np.ndarray, left: np.ndarray) -> float:
    """How much serial correlation inflates the variance of what a bigger model explains on
    the calibration readings (``explained``: the smaller model's residual minus the bigger
    one's; ``left``: the bigger one's residual; readings grouped by (session, axis) in the
    sizes ``group_sizes``, each group in time order) against independent rows: Bartlett's
    factor for the variance of a cross-product, 1 + 2 sum_l rho_e(l) rho_x(l) over lags
    l >= 1 (the two series' autocorrelations pooled over the groups), summed up to the first
    lag whose product is not positive. A change that varies pose to pose (rho_x near 0) is
    barely penalised; one that follows the temperatures as slowly as the residual does, much.
    1 when no group has two readings."""
    sizes = [int(s) for s in group_sizes]
    lags = max(sizes, default=0) // 2
    acov = np.zeros((2, lags + 1))
    cuts = np.cumsum(sizes)[:-1]
    for part_e, part_x in zip(np.split(left, cuts), np.split(explained, cuts)):
        m = min(lags, part_e.size - 1)
        for k, x in enumerate((part_e, part_x)):
            if m >= 0:
                f = np.fft.rfft(x, 2 * x.size)
                acov[k, :m + 1] += np.fft.irfft(f * np.conj(f), 2 * x.size)[:m + 1]
    if acov[0, 0] <= 0 or acov[1, 0] <= 0:
        return 1.0
    product = (acov[0, 1:] / acov[0, 0]) * (acov[1, 1:] / acov[1, 0])
    stop = np.flatnonzero(product <= 0)
    return 1.0 + 2.0 * float(np.sum(product[:stop[0] if stop.size else product.size]))


def time_blocks(rows: np.ndarray, session: np.ndarray | None = None,
                t_s: np.ndarray | None = None, blocks: int = VALIDATION_BLOCKS,
                min_rows: float = 1.0) -> np.ndarray:
    """(N,) block index of each of ``rows`` (N,) (-1 elsewhere): each session's rows in time
    order cut into contiguous blocks of nearly equal counts, ``blocks`` of them or fewer so
    that each holds at least ``min_rows`` rows (a short session: one block), numbered across
    sessions. A block holds every axis read in its time span: the axes' residuals share the
    laboratory's slow temperatures, so they are not independent of one another."""
    n = rows.shape[0]
    session = np.zeros(n, int) if session is None else np.unique(session, return_inverse=True)[1]
    t = np.arange(n, dtype=float) if t_s is None else np.asarray(t_s, dtype=float)
    out, first = np.full(n, -1), 0
    for s in np.unique(session[rows]):
        idx = np.flatnonzero(rows & (session == s))
        idx = idx[np.argsort(t[idx], kind="stable")]
        count = int(np.clip(idx.size // max(min_rows, 1.0), 1, blocks))
        out[idx] = first + np.arange(idx.size) * count // idx.size
        first += count
    return out


def validation_p(before: np.ndarray, after: np.ndarray, group: np.ndarray, rows: np.ndarray,
                 session: np.ndarray | None = None, t_s: np.ndarray | None = None,
                 blocks: int = VALIDATION_BLOCKS) -> float:
    """One-sided p-value that a change explains the residual on the validation ``rows`` (N,):
    the residual ``before`` (N,3) regressed on the change ``before - after`` through the
    origin, each (session, axis) ``group``'s (N,3) mean removed from both (offset-immune), the
    slope's variance cluster-robust over contiguous time blocks per session (``time_blocks``;
    at most ``blocks``, each at least BLOCK_CORRELATIONS times the score's correlation length,
    ``serial_inflation`` of the change and what it leaves), Student's t with (number of
    blocks - 1) degrees of freedom (module docstring). 1 when the change is constant on every
    group or fewer than two blocks hold readings."""
    t = np.arange(rows.shape[0], dtype=float) if t_s is None else np.asarray(t_s, dtype=float)
    ok = (group >= 0) & rows[:, None] & np.isfinite(before) & np.isfinite(after)
    parts = []                                  # (row index, b, c) per group, in time order
    for g in np.unique(group[ok]):
        r, k = np.nonzero(ok & (group == g))        # a group is one axis of one session
        order = np.argsort(t[r], kind="stable")
        r, k = r[order], k[order]
        b, c = before[r, k], before[r, k] - after[r, k]
        parts.append((r, b - b.mean(), c - c.mean(), float(c @ c)))
    if not parts:
        return 1.0
    row = np.concatenate([p[0] for p in parts])
    b, c = np.concatenate([p[1] for p in parts]), np.concatenate([p[2] for p in parts])
    cc = float(c @ c)
    if cc <= 1e-24 * sum(p[3] for p in parts):     # constant on every group, to round-off
        return 1.0
    slope = float(b @ c) / cc
    e = b - slope * c
    correlation = serial_inflation([p[0].size for p in parts], c, e)
    block = time_blocks(rows, session, t, blocks, BLOCK_CORRELATIONS * correlation)[row]
    ids = np.unique(block, return_inverse=True)[1]
    n_blocks = int(ids.max()) + 1
    if n_blocks < 2:
        return 1.0
    scores = np.bincount(ids, weights=c * e, minlength=n_blocks)
    var = n_blocks / (n_blocks - 1) * float(scores @ scores) / cc ** 2
    if var <= 0:
        return 0.0 if slope > 0 else 1.0
    return float(special.stdtr(n_blocks - 1, -slope / math.sqrt(var)))


def correlation_rows(x: np.ndarray) -> float:
    """The integrated correlation time (rows) of the series ``x``: 1 + 2 sum of its
    autocorrelations over the first run of positive lags (Geyer's initial positive sequence,
    one lag at a time)."""
    x = np.asarray(x, dtype=float) - np.mean(x)
    if x.size < 3 or not np.any(x):
        return 1.0
    f = np.fft.rfft(x, 2 * x.size)
    acov = np.fft.irfft(f * np.conj(f), 2 * x.size)[:x.size // 2]
    rho = acov[1:] / acov[0]
    stop = np.flatnonzero(rho <= 0)
    return 1.0 + 2.0 * float(np.sum(rho[:stop[0] if stop.size else rho.size]))


def sandwich_covariance(J: np.ndarray, r: np.ndarray, row: np.ndarray,
                        t_s: np.ndarray, information: np.ndarray | None = None) -> np.ndarray:
    """(k, k) covariance of least-squares coefficients whose residuals are serially
    correlated: (J^T J)^-1 S (J^T J)^-1 (the sandwich), S the long-run covariance of the
    scores summed per data row (``row`` (n,) of each reading of ``J`` (n, k) and ``r`` (n,);
    the readings of one row share its moment and its temperatures), rows in the time order of
    ``t_s`` (N,), by overlapping batch means (Meketon & Schmeiser 1984: the Bartlett-kernel
    estimator of Newey and West to O(L / n), in O(n k^2) from cumulative sums). The batches
    are twice the scores' integrated correlation time (``correlation_rows``), at least Newey
    and West's 4 (rows / 100)^(2/9), at most a quarter of the rows. ``information`` (k, k):
    the estimating equations' derivative when it is not J^T J (a corrected score: the fit's
    J^T J less the thermometers' share), the bread its inverse."""
    k = J.shape[1]
    if k == 0 or r.size == 0:
        return np.zeros((k, k))
    used, inverse = np.unique(row, return_inverse=True)
    inverse_JTJ = np.linalg.pinv(J.T @ J)
    bread = inverse_JTJ if information is None else np.linalg.pinv(information)
    # a row's own share of the fit (its leverage h: the readings' diagonal of J (J^T J)^-1 J^T
    # summed over the row) is taken out of its residual by the fit; its score over
    # sqrt(1 - h) restores it (MacKinnon & White 1985, HC2), unbiased for independent rows
    leverage = np.zeros(used.size)
    np.add.at(leverage, inverse, np.einsum("ij,jk,ik->i", J, inverse_JTJ, J))
    scores = np.zeros((used.size, k))
    np.add.at(scores, inverse, J * r[:, None])
    scores /= np.sqrt(np.clip(1.0 - leverage, 0.05, 1.0))[:, None]
    scores = scores[np.argsort(t_s[used], kind="stable")]
    n = scores.shape[0]
    tau = max(correlation_rows(scores[:, j]) for j in range(k))
    batch = int(min(max(n // 4, 1), max(np.floor(4 * (n / 100.0) ** (2 / 9)), np.ceil(2 * tau))))
    return bread @ overlapping_batch_means(scores, batch) @ bread


def overlapping_batch_means(scores: np.ndarray, batch: int) -> np.ndarray:
    """(k, k) long-run covariance of the sum of the rows of ``scores`` (n, k), in time order:
    n / (batch (n - batch + 1)) sum over every window of ``batch`` consecutive rows of its
    sum's outer product (Meketon & Schmeiser 1984); the plain sum of outer products when
    ``batch`` is 1."""
    n = scores.shape[0]
    batch = int(min(max(batch, 1), n))
    cum = np.vstack([np.zeros((1, scores.shape[1])), np.cumsum(scores, axis=0)])
    sums = cum[batch:] - cum[:-batch]                                # (n - batch + 1, k)
    return sums.T @ sums * (n / (batch * (n - batch + 1)))


def exponential_kernel_sums(t: np.ndarray, w: np.ndarray, time_s: float) -> np.ndarray:
    """m_i = sum_j w_j exp(-|t_i - t_j| / time_s) for every i (``w``: (n,) or (n, k), each
    column alike), in O(n) (a forward and a backward recursion over the sorted times);
    ``time_s`` 0: white (equal times only)."""
    order = np.argsort(t, kind="stable")
    ts, ws = t[order], w[order]
    gap = np.diff(ts)
    decay = np.exp(-gap / time_s) if time_s > 0 else (gap == 0).astype(float)
    decay = decay.reshape(-1, *([1] * (ws.ndim - 1)))
    forward, backward = ws.copy(), ws.copy()
    for k in range(1, ts.size):
        forward[k] += decay[k - 1] * forward[k - 1]
    for k in range(ts.size - 2, -1, -1):
        backward[k] += decay[k] * backward[k + 1]
    out = np.empty_like(ws)
    out[order] = forward + backward - ws
    return out



@dataclass(frozen=True)
class Verdict:
    """A bigger model against a smaller one: ``p_value`` (calibration rows' F test),
    ``delta_bic``, ``p_validation`` (the offset-immune block test), ``p_combined`` (Fisher's
    of the two), the relevance figures ``explained_fraction`` and ``gap_closed``, and
    ``routes``: the rule's routes to a claim that hold ("calibration", "validation"; empty:
    not significant)."""
    p_value: float
    delta_bic: float
    p_validation: float
    p_combined: float
    explained_fraction: float
    gap_closed: float
    routes: tuple

    @property
    def significant(self) -> bool:
        return bool(self.routes)


@dataclass(frozen=True)
class DecisionRule:
    """The rule (module docstring): a bigger model is shown by the data when its calibration F
    test gives p < ``alpha``, the BIC falls and the claim is relevant (explains
    ``min_explained`` of the validation residual's power or closes ``gap_closed`` of the gap
    to the achievable floor, the model not within ``at_floor`` of it), or when the
    calibration and validation tests combined (Fisher) give p < ``alpha`` and it closes
    ``gap_closed`` of the gap. ``validation_blocks``: time blocks per session of validation
    readings. ``absorbed`` and ``generic_share``: the diagnosis' reading of a candidate
    (calibration/diagnosis/diagnose.py): absorbed by the model where that share of its
    signature lies in the model's span; a correlate of the missing term where it explains less
    than ``generic_share`` of what generic functions of the laboratory variables explain and
    nothing beyond them."""
    alpha: float = ALPHA
    validation_blocks: int = VALIDATION_BLOCKS
    min_explained: float = MIN_EXPLAINED
    gap_closed: float = GAP_CLOSED
    at_floor: float = AT_FLOOR
    absorbed: float = ABSORBED
    generic_share: float = GENERIC_SHARE

    def __post_init__(self):
        if not 0 < self.alpha < 1:
            raise ValueError(f"DecisionRule: alpha = {self.alpha}: must be between 0 and 1")
        if self.validation_blocks < 2:
            raise ValueError(f"DecisionRule: validation_blocks = {self.validation_blocks}: "
                             "at least 2")
        for name in ("min_explained", "gap_closed", "absorbed", "generic_share"):
            if not 0 <= getattr(self, name) <= 1:
                raise ValueError(f"DecisionRule: {name} = {getattr(self, name)}: a share, "
                                 "between 0 and 1")
        if not self.at_floor >= 1:
            raise ValueError(f"DecisionRule: at_floor = {self.at_floor}: a factor, at least 1")

    def f_critical(self, df1: int, df2: int) -> float:
        """The F statistic the calibration test needs (at ``alpha``)."""
        return float(special.fdtri(max(df1, 1), df2, 1.0 - self.alpha))

    def is_at_floor(self, err90_nm: float, floor_nm: float | None) -> bool | None:
        """Whether a validation error 90 % ``err90_nm`` is within ``at_floor`` of the floor
        ``floor_nm`` (None without a floor)."""
        return bool(err90_nm <= self.at_floor * floor_nm) if floor_nm else None

    def routes(self, p_value: float, delta_bic: float, p_combined: float, explained: float,
               gap_closed: float, at_floor: bool) -> tuple:
        """The routes to a claim that hold (class docstring), given the tests' figures and
        the relevance figures: ``explained`` (share of the validation power), ``gap_closed``
        (share of the gap to the floor; 0 without a floor) and ``at_floor`` (the smaller
        model within ``at_floor`` of the floor)."""
        relevant = (explained >= self.min_explained or gap_closed >= self.gap_closed)
        out = []
        if p_value < self.alpha and delta_bic < 0 and relevant and not at_floor:
            out.append("calibration")
        if gap_closed >= self.gap_closed and p_combined < self.alpha:
            out.append("validation")
        return tuple(out)

    def decide(self, rss0: float, rss1: float, k: int, n: int, df2: int, before: np.ndarray,
               after: np.ndarray, group: np.ndarray, val: np.ndarray,
               inflation: float = 1.0, session: np.ndarray | None = None,
               t_s: np.ndarray | None = None, *, explained: float,
               gap_closed: float = 0.0, at_floor: bool = False) -> Verdict:
        """The verdict on ``k`` added directions: calibration sums of squares ``rss0`` /
        ``rss1`` (m^2) over ``n`` readings with ``df2`` residual degrees of freedom and the
        serial ``inflation``; the validation residuals ``before`` / ``after`` (N,3) with their
        (session, axis) ``group`` (N,3) on the rows ``val`` (N,), with the rows' ``session``
        and times ``t_s`` (s) (N,) that cut them into blocks; the relevance figures as
        ``routes`` takes them (``explained`` always: a claim's relevance is part of the rule;
        ``gap_closed`` 0 and ``at_floor`` False where no floor is known)."""
        p_cal = f_test_p(rss0, rss1, k, df2, inflation)
        d_bic = float(bic_change(n, rss0, rss1, k)) if n else 0.0
        p_val = validation_p(before, after, group, val, session, t_s, self.validation_blocks)
        p_comb = fisher_p(p_cal, p_val)
        return Verdict(p_cal, d_bic, p_val, p_comb, float(explained), float(gap_closed),
                       self.routes(p_cal, d_bic, p_comb, explained, gap_closed, at_floor))
