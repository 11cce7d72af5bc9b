"""The paper's claims as paired comparisons with bootstrap confidence intervals.

Each claim says preset ``a`` scores lower than preset ``b`` on a metric where lower is better.
Over the (prompt, seed) pairs that both presets ran in one setting, the paired differences
d = metric(a) - metric(b) are resampled (percentile bootstrap, 10,000 resamples of the pairs,
a fixed seed); the verdict reads the 95% interval of their mean. The words, checked in order:

- **not measured**: no pair has the metric in both arms (not scored, or nothing to score);
- **too few pairs (n < 6)**: fewer than ``MIN_PAIRS`` pairs. Below six, even pairs that all
  agree are not significant (a two-sided sign test gives p = 2^(1-n) >= 0.0625), while the
  percentile bootstrap of a few same-signed numbers never spans 0 and would say "holds";
- **not testable here (neither preset fails)**: the metric is 0 in every pair: the mechanism
  had nothing to fix in this setting, which is no evidence either way;
- **not testable here (both always fail)**: the metric sits at its failure value in every pair
  of both arms (COLMAP registers nothing in either, so its failure rate is 1.0 throughout): the
  metric cannot see a difference, which is no evidence either way;
- **does not hold (no difference)**: every difference is 0 while the baseline does fail;
- **holds**: the interval lies below 0;
- **does not hold**: the interval lies above 0 (the opposite holds);
- **undecided (CI spans zero)**: the interval spans 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..io import num


@dataclass(frozen=True)
class Claim:
    text: str
    a: str
    b: str
    metric: str
    """A row key; lower is better."""
    fails_at: float | None = None
    """The metric's value in a cell where the failure always happens (a rate's 1.0), or None
    where it has no such value."""


CLAIMS = (
    Claim("structured noise reduces multi-face failures", "gd", "gd-no-sn", "multi_face_rate", 1.0),
    Claim("structured noise reduces multi-face failures", "gd-no-vgs", "sjc-gs", "multi_face_rate", 1.0),
    Claim("structured noise reduces instance inconsistency", "gd", "gd-no-sn", "instance_inconsistency"),
    Claim("structured noise reduces instance inconsistency", "gd-no-vgs", "sjc-gs", "instance_inconsistency"),
    Claim("variational Gaussians reduce floaters", "gd", "gd-no-vgs", "floaters"),
    Claim("variational Gaussians reduce floaters", "gd-no-sn", "sjc-gs", "floaters"),
    Claim("gd is more consistent than SJC on COLMAP (variance)", "gd", "sjc-gs", "var_theta_deg2"),
    Claim("gd is more consistent than SJC on COLMAP (failure rate)", "gd", "sjc-gs", "colmap_failure_rate", 1.0),
    Claim("gd is more consistent than SDS on COLMAP (variance)", "gd", "sds-gs", "var_theta_deg2"),
    Claim("gd is more consistent than SDS on COLMAP (failure rate)", "gd", "sds-gs", "colmap_failure_rate", 1.0),
)
"""The paper's claims (section 4) in the ablation's terms."""


def bootstrap_mean_ci(d: np.ndarray, *, level: float = 0.95, n: int = 10_000, seed: int = 0) -> tuple[float, float]:
    """Percentile bootstrap interval of the mean of ``d`` (resampling its entries)."""
    d = np.asarray(d, dtype=np.float64)
    if d.size == 0:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    means = d[rng.integers(0, d.size, size=(n, d.size))].mean(1)
    lo, hi = np.quantile(means, [(1 - level) / 2, (1 + level) / 2])
    return float(lo), float(hi)


MIN_PAIRS = 6
"""Fewest pairs a verdict is read from (module docstring: a sign test's reach)."""


def verdict(
    lo: float,
    hi: float,
    diffs: np.ndarray,
    baseline: np.ndarray | None = None,
    treated: np.ndarray | None = None,
    fails_at: float | None = None,
) -> str:
    """The verdict of one claim from the interval of the mean paired difference (a - b), the
    differences themselves, both arms' values (``treated``: a's, ``baseline``: b's) and the
    metric's always-fails value (module docstring: the words and their order)."""
    if diffs.size == 0 or math.isnan(lo):
        return "not measured"
    if diffs.size < MIN_PAIRS:
        return f"too few pairs (n < {MIN_PAIRS})"
    if baseline is not None and np.all(np.asarray(baseline) == 0) and np.all(diffs == 0):
        return "not testable here (neither preset fails)"
    if (
        fails_at is not None
        and baseline is not None
        and treated is not None
        and np.all(np.asarray(baseline) == fails_at)
        and np.all(np.asarray(treated) == fails_at)
    ):
        return "not testable here (both always fail)"
    if np.all(diffs == 0):
        return "does not hold (no difference)"
    if hi < 0:
        return "holds"
    if lo > 0:
        return "does not hold"
    return "undecided (CI spans zero)"


SIZE_RATIO_LIMIT = 2.0
"""Paired arms whose mean Gaussian counts differ by more than this factor are flagged: the size of
the model, not only what the claim ablates, then differs between them (docs/training.md)."""


def _sizes(rows: list[dict], c: Claim, keys: list) -> dict:
    """Mean final Gaussian count of each arm over the pairs, their ratio (larger / smaller) and
    whether it exceeds ``SIZE_RATIO_LIMIT``."""

    def mean(preset: str) -> float:
        n = {(r["prompt"], r["seed"]): num(r.get("gaussians")) for r in rows if r["preset"] == preset}
        vals = [float(n[k]) for k in keys if k in n and n[k] == n[k]]
        return float(np.mean(vals)) if vals else math.nan

    ga, gb = mean(c.a), mean(c.b)
    ratio = max(ga, gb) / min(ga, gb) if ga > 0 and gb > 0 else math.nan
    return {
        "gaussians_a": ga,
        "gaussians_b": gb,
        "size_ratio": ratio,
        "size_confounded": bool(ratio > SIZE_RATIO_LIMIT),
    }


def _applies(claim: Claim, rows: list[dict], setting: str) -> bool:
    """Instance consistency is only defined where the bank holds several variants."""
    if claim.metric != "instance_inconsistency":
        return True
    return setting == "instance" or any(int(r.get("variants", 1) or 1) > 1 for r in rows)


def evaluate(rows: list[dict], claims=CLAIMS) -> list[dict]:
    """One result per (setting, claim) whose two presets ran in that setting (instance claims
    only where the prior held several variants)."""
    out = []
    settings = list(dict.fromkeys(r.get("setting", "easy") for r in rows))
    for setting in settings:
        sel = [r for r in rows if r.get("setting", "easy") == setting]
        ran = {r["preset"] for r in sel}
        for c in claims:
            if not {c.a, c.b} <= ran or not _applies(c, sel, setting):
                continue
            va = {(r["prompt"], r["seed"]): num(r.get(c.metric)) for r in sel if r["preset"] == c.a}
            vb = {(r["prompt"], r["seed"]): num(r.get(c.metric)) for r in sel if r["preset"] == c.b}
            keys = sorted(k for k in set(va) & set(vb) if va[k] == va[k] and vb[k] == vb[k])
            d = np.array([va[k] - vb[k] for k in keys], dtype=np.float64)
            lo, hi = bootstrap_mean_ci(d)
            size = _sizes(sel, c, keys)
            out.append(
                {
                    "setting": setting,
                    "claim": c.text,
                    "a": c.a,
                    "b": c.b,
                    "metric": c.metric,
                    "pairs": len(keys),
                    "mean_a": float(np.mean([va[k] for k in keys])) if keys else math.nan,
                    "mean_b": float(np.mean([vb[k] for k in keys])) if keys else math.nan,
                    "mean_diff": float(d.mean()) if keys else math.nan,
                    "ci_low": lo,
                    "ci_high": hi,
                    "a_better_pairs": int((d < 0).sum()),
                    "verdict": verdict(
                        lo, hi, d, np.array([vb[k] for k in keys]), np.array([va[k] for k in keys]), c.fails_at
                    ),
                    **size,
                }
            )
    return out
