"""The statistics the claims are read with (``claims.py`` holds the claims and their verdict
words): the BCa bootstrap interval of a mean, the exact Wilcoxon signed-rank and sign-flip tests,
the TOST equivalence test, Holm's adjustment, the pairs needed for power and a one-sided upper
bound. Each is checked against an independent oracle in tests/test_claims.py and
tests/test_across.py (enumeration, scipy, simulation)."""

from __future__ import annotations

import math
import warnings

import numpy as np

ALPHA = 0.05


def bca_ci(d: np.ndarray, *, level: float = 0.95, n: int = 10_000, seed: int = 0) -> tuple[float, float]:
    """BCa bootstrap interval of the mean of ``d`` (percentile where BCa is undefined: a
    constant sample, or a jackknife without spread); (NaN, NaN) for no data."""
    from scipy import stats

    d = np.asarray(d, dtype=np.float64)
    if d.size == 0:
        return math.nan, math.nan
    if d.size == 1 or np.all(d == d[0]):
        return float(d[0]), float(d[0])
    for method in ("BCa", "percentile"):
        with warnings.catch_warnings(), np.errstate(all="ignore"):  # BCa warns where it is undefined
            warnings.simplefilter("ignore")
            ci = stats.bootstrap(
                (d,), np.mean, confidence_level=level, n_resamples=n, method=method, rng=np.random.default_rng(seed)
            ).confidence_interval
        lo, hi = float(ci.low), float(ci.high)
        if math.isfinite(lo) and math.isfinite(hi):
            return lo, hi
    return math.nan, math.nan


ROUND = 12
"""Decimals the differences are rounded to before ranking: float noise (0.3 - 0.2 against 0.1)
would otherwise break ties and give near-zero differences a rank."""

EXACT_UP_TO = 16
"""Non-zero differences up to which the signed-rank p is exact (every sign pattern enumerated, ties
at their mid-ranks): scipy falls back to the normal approximation wherever zeros or ties occur,
which gave five agreeing pairs p = 0.043 (exact: 0.0625)."""


def signed_rank_p(d: np.ndarray, alternative: str = "two-sided") -> float:
    """Wilcoxon signed-rank p-value of ``d`` (zeros dropped; exact up to ``EXACT_UP_TO`` non-zero
    differences, scipy's otherwise); 1 when nothing differs."""
    from scipy import stats

    d = np.round(np.asarray(d, dtype=np.float64), ROUND)  # 0.3 - 0.2 and 0.1 tie
    d = d[d != 0]
    if d.size == 0:
        return 1.0
    if d.size > EXACT_UP_TO:
        return float(stats.wilcoxon(d, zero_method="wilcox", alternative=alternative).pvalue)
    ranks = stats.rankdata(np.abs(d))
    signs = (np.arange(2**d.size)[:, None] >> np.arange(d.size)) & 1  # every sign pattern
    w = signs @ ranks  # W+ of each pattern (the observed one among them)
    obs, centre, eps = float(ranks[d > 0].sum()), float(ranks.sum()) / 2, 1e-9
    if alternative == "greater":
        return float(np.mean(w >= obs - eps))
    if alternative == "less":
        return float(np.mean(w <= obs + eps))
    return float(np.mean(np.abs(w - centre) >= abs(obs - centre) - eps))


def equivalence_p(d: np.ndarray, margin: float) -> float:
    """TOST with two one-sided paired t-tests: H0 |mean effect| >= margin; small p says the mean
    effect lies within +-margin. Differences without spread: 0 inside the margin, 1 outside;
    NaN under two pairs."""
    from scipy import stats

    d = np.asarray(d, dtype=np.float64)
    if d.size < 2:
        return math.nan
    mean, se = float(d.mean()), float(d.std(ddof=1)) / math.sqrt(d.size)
    if np.all(d == d[0]):  # no spread (the std of equal floats can be 1e-17, not 0)
        return 0.0 if abs(mean) < margin else 1.0
    t = stats.t(d.size - 1)
    return float(max(t.sf((mean + margin) / se), t.cdf((mean - margin) / se)))


def holm(p: list[float]) -> list[float]:
    """Holm's step-down adjustment of the p-values ``p`` (NaN entries are left out and stay NaN)."""
    idx = [i for i, x in enumerate(p) if x == x]
    order = sorted(idx, key=lambda i: p[i])
    m, out, running = len(order), [math.nan] * len(p), 0.0
    for rank, i in enumerate(order):
        running = max(running, min(1.0, (m - rank) * p[i]))
        out[i] = running
    return out


def pairs_for_power(d: np.ndarray, power: float = 0.8, alpha: float = ALPHA, floor: int = 6) -> float:
    """Pairs a two-sided level-``alpha`` signed-rank test needs for ``power`` against the
    observed mean effect, from its mean and standard deviation (normal approximation over the
    Wilcoxon test's efficiency 3/pi); inf where the observed mean is 0, NaN under 2 pairs, ``floor``
    (the fewest pairs a difference is read from) where the differences do not vary."""
    from scipy import stats

    d = np.asarray(d, dtype=np.float64)
    if d.size < 2:
        return math.nan
    mean, sd = float(d.mean()), float(d.std(ddof=1))
    if mean == 0:
        return math.inf
    z = stats.norm.ppf(1 - alpha / 2) + stats.norm.ppf(power)
    return float(math.ceil((z * sd / abs(mean)) ** 2 / (3 / math.pi))) if np.any(d != d[0]) else float(floor)


def upper_bound(x: np.ndarray, level: float = 0.95) -> float:
    """One-sided upper confidence bound of the mean of ``x`` (t, over the pairs); the mean itself
    for fewer than two values or no spread."""
    from scipy import stats

    x = np.asarray(x, dtype=np.float64)
    if x.size < 2 or not np.any(x != x[0]):
        return float(x.mean()) if x.size else math.nan
    return float(x.mean() + stats.t(x.size - 1).ppf(level) * x.std(ddof=1) / math.sqrt(x.size))


SIGN_FLIP_EXACT_UP_TO = 44
"""Observations up to which ``sign_flip_p`` enumerates every sign pattern (two halves of at most
2^22 sums each); beyond, 2^20 random patterns."""


def sign_flip_p(x: np.ndarray, *, seed: int = 0) -> float:
    """Two-sided sign-flip (permutation) p-value of mean(x) = 0: the share of the 2^G patterns of
    signs on |x| whose sum is at least as far from 0 as the observed one (which is among them).
    Exact, by meeting in the middle (the sums of each half's patterns, one half sorted and searched)
    up to ``SIGN_FLIP_EXACT_UP_TO`` values; beyond, a Monte Carlo estimate ((k + 1) / (n + 1))
    from 2^20 patterns drawn with ``seed``. Sums within 1e-9 of the observed count as ties."""
    x = np.asarray(x, dtype=np.float64)
    if x.size == 0 or not np.all(np.isfinite(x)):
        return math.nan
    obs = abs(float(x.sum()))
    tol = 1e-9 * max(1.0, float(np.abs(x).sum()))
    if obs <= tol:
        return 1.0
    a = np.abs(x)
    if a.size > SIGN_FLIP_EXACT_UP_TO:
        rng, n, k, chunk = np.random.default_rng(seed), 2**20, 0, 2**14
        for _ in range(n // chunk):  # in chunks: a 2^20 x G sign matrix at once would take GBs
            signs = rng.integers(0, 2, (chunk, a.size), dtype=np.int8) * 2 - 1
            k += int((np.abs(signs @ a) >= obs - tol).sum())
        return float((k + 1) / (n + 1))

    def sums(v: np.ndarray) -> np.ndarray:
        out = np.zeros(1)
        for value in v:
            out = np.concatenate([out + value, out - value])
        return out

    half = a.size // 2
    left, right = np.sort(sums(a[:half])), sums(a[half:])
    # pairs with left + right >= obs - tol, and pairs with left + right <= -(obs - tol): disjoint
    above = left.size - np.searchsorted(left, obs - tol - right, side="left")
    below = np.searchsorted(left, tol - obs - right, side="right")
    return float((above.sum() + below.sum()) / 2.0**a.size)
