"""Statistics with the prompt as the unit (the v3 experiment, docs/decisive_v3.md): variance
components and power across prompts, the share of an effect a control keeps, and the forest plot.

A claim's observations are the per-prompt means of its paired differences d (one per seed). With
S seeds a prompt's mean has variance ``between + within / S``: ``between`` is how much the effect
itself differs between prompts, ``within`` the seed-to-seed spread of one prompt's pairs. A pilot
with few seeds estimates both (one-way random-effects ANOVA), and ``power`` says how many seeds G
prompts need for a paired t test across prompts at a Holm-conservative level (``alpha / k`` for a
family of k claims: the level its first step uses, so the power is a lower bound).
"""

from __future__ import annotations

import math

import numpy as np

from gdbench.experiments.claims import per_prompt


def components(keys: list[tuple], d: np.ndarray) -> dict:
    """Variance components of the paired differences ``d`` of the (prompt, seed) pairs ``keys``:
    ``within`` (pooled over the prompts with at least two pairs), ``between`` (the variance of the
    prompts' means less what ``within`` explains of it, at least 0), the mean and the counts."""
    per = [np.asarray(v, dtype=np.float64) for v in per_prompt(keys, d).values()]
    if not per:
        return {"prompts": 0, "pairs": 0, "mean": math.nan, "within": math.nan, "between": math.nan}
    multi = [v for v in per if v.size > 1]
    dof = sum(v.size - 1 for v in multi)
    within = sum(float(((v - v.mean()) ** 2).sum()) for v in multi) / dof if dof else math.nan
    means = np.array([v.mean() for v in per])
    n_h = len(per) / sum(1.0 / v.size for v in per)  # harmonic mean of pairs per prompt
    var_means = float(means.var(ddof=1)) if len(per) > 1 else math.nan
    between = max(0.0, var_means - within / n_h) if within == within and var_means == var_means else math.nan
    return {"prompts": len(per), "pairs": int(sum(v.size for v in per)), "mean": float(np.mean(means)),
            "within": within, "between": between}  # fmt: skip


def t_interval(x: np.ndarray, level: float = 0.95) -> tuple[float, float, float]:
    """Mean of ``x`` and its two-sided t interval ((mean, NaN, NaN) below two values)."""
    from scipy import stats

    x = np.asarray(x, dtype=np.float64)
    if x.size < 2:
        return (float(x.mean()) if x.size else math.nan), math.nan, math.nan
    m, se = float(x.mean()), float(x.std(ddof=1)) / math.sqrt(x.size)
    h = float(stats.t.ppf(0.5 + level / 2, x.size - 1)) * se
    return m, m - h, m + h


def power(effect: float, between: float, within: float, prompts: int, seeds: int, alpha: float) -> float:
    """Power of the two-sided paired t test over ``prompts`` per-prompt means (each of ``seeds``
    pairs) at level ``alpha`` against a true mean difference ``effect`` (noncentral t)."""
    from scipy import stats

    if prompts < 2 or seeds < 1 or not (effect == effect and between == between and within == within):
        return math.nan
    sd = math.sqrt(between + within / seeds)
    if sd == 0:
        return 1.0 if effect != 0 else alpha
    df, nc = prompts - 1, abs(effect) / (sd / math.sqrt(prompts))
    crit = stats.t.ppf(1 - alpha / 2, df)
    upper, lower = float(stats.nct.sf(crit, df, nc)), float(stats.nct.cdf(-crit, df, nc))
    return upper + (lower if lower == lower else 0.0)  # scipy's far lower tail can be NaN: it is ~0 there


def seeds_for_power(effect: float, between: float, within: float, prompts: int, alpha: float,
                    target: float = 0.8, most: int = 10) -> int | None:  # fmt: skip
    """Fewest seeds per prompt (1 to ``most``) whose ``power`` reaches ``target``; None if none does
    (the between-prompt spread alone can cap the power below it, whatever the seeds)."""
    for s in range(1, most + 1):
        if power(effect, between, within, prompts, s, alpha) >= target:
            return s
    return None


def detectable(between: float, within: float, prompts: int, seeds: int, alpha: float, target: float = 0.8) -> float:
    """The smallest effect ``power`` detects with probability ``target`` (bisection; NaN where
    the spread is unknown, or where no effect up to 100 standard errors reaches the target)."""
    if not (between == between and within == within) or prompts < 2 or seeds < 1:
        return math.nan
    lo, hi = 0.0, 100.0 * math.sqrt((between + within / seeds) / prompts) + 1e-12
    if not power(hi, between, within, prompts, seeds, alpha) >= target:
        return math.nan
    for _ in range(60):
        mid = (lo + hi) / 2
        lo, hi = (mid, hi) if power(mid, between, within, prompts, seeds, alpha) < target else (lo, mid)
    return hi


def share_kept(rows: list[dict], control: str, metric: str, *, treated: str = "gd", baseline: str = "gd-no-sn",
               n: int = 10_000, seed: int = 0) -> dict:  # fmt: skip
    """How much of ``treated``'s effect against ``baseline`` the ``control`` keeps:
    (baseline - control) / (baseline - treated), the ratio of the mean differences over the
    prompts, each prompt's differences averaged over the seeds where all three arms have the
    metric (so every arm is read at the same seeds), with a percentile 95% interval from ``n``
    resamples of the prompts (``seed``). 1: the control does all the treatment does; 0: nothing.
    NaN where the treatment's effect is 0; an unbounded interval (NaN ends, ``flipped`` > 0) where
    resamples give the treatment's effect 0 or the other sign, since the ratio then has no bound."""
    vals: dict[str, dict] = {treated: {}, baseline: {}, control: {}}
    for r in rows:
        v = r.get(metric)
        if r["preset"] in vals and v is not None and v == v:
            vals[r["preset"]][(r["prompt"], r["seed"])] = float(v)
    keys = set(vals[treated]) & set(vals[baseline]) & set(vals[control])
    per: dict[str, list[tuple[float, float]]] = {}
    for k in sorted(keys):
        b = vals[baseline][k]
        per.setdefault(k[0], []).append((b - vals[treated][k], b - vals[control][k]))
    nan = {"prompts": len(per), "share": math.nan, "low": math.nan, "high": math.nan, "flipped": 0}
    if len(per) < 2:
        return nan
    effect = np.array([np.mean([e for e, _ in v]) for v in per.values()])
    kept = np.array([np.mean([c for _, c in v]) for v in per.values()])
    out = nan | {"effect": float(effect.mean()), "kept": float(kept.mean())}
    if effect.mean() == 0:
        return out
    idx = np.random.default_rng(seed).integers(0, len(per), (n, len(per)))
    num, den = kept[idx].mean(axis=1), effect[idx].mean(axis=1)
    flipped = int((np.sign(den) != np.sign(effect.mean())).sum())
    out |= {"share": float(kept.mean() / effect.mean()), "flipped": flipped}
    if flipped == 0:
        lo, hi = np.percentile(num / den, [2.5, 97.5])
        out |= {"low": float(lo), "high": float(hi)}
    return out


def forest(keys: list[tuple], d: np.ndarray, *, title: str, margin: float, path, pooled: dict | None = None):
    """The forest plot of one claim: every prompt a row (sorted by its mean difference), its mean
    over the seeds with a 95% t interval over them (none with one seed), and the across-prompts
    mean with its interval at the bottom (``pooled``: ``prompt_mean_diff``, ``prompt_ci_low``,
    ``prompt_ci_high``); 0 and the margin drawn, the prompts beyond it blue (a < b) or red (a > b),
    those within it grey."""

    from gdbench.core.plotting import pyplot, save

    per = sorted(per_prompt(keys, d).items(), key=lambda kv: np.mean(kv[1]))
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.4, 1.2 + 0.22 * (len(per) + 2)))
    for i, (_prompt, v) in enumerate(per):
        m, lo, hi = t_interval(v)
        if hi > lo:
            ax.plot([lo, hi], [i, i], color="0.45", lw=1.2)
        side = "C0" if m < -margin else "C3" if m > margin else "0.35"  # margin NaN: every prompt grey
        ax.plot([m], [i], "o", color=side, ms=4)
    labels = [f"{p} ({len(v)})" for p, v in per]
    if pooled is not None and pooled.get("prompt_mean_diff") == pooled.get("prompt_mean_diff"):
        y = len(per) + 0.8
        m, lo, hi = pooled["prompt_mean_diff"], pooled["prompt_ci_low"], pooled["prompt_ci_high"]
        ax.plot([lo, hi], [y, y], color="k", lw=2.5)
        ax.plot([m], [y], "D", color="k", ms=6)
        labels.append(f"across {len(per)} prompts")
        ticks = [*range(len(per)), y]
    else:
        ticks = list(range(len(per)))
    ax.set_yticks(ticks, labels, fontsize=7)
    ax.axvline(0, color="k", lw=0.8)
    if margin == margin:
        for x in (-margin, margin):
            ax.axvline(x, color="0.6", lw=0.8, ls=":")
    ax.invert_yaxis()
    ax.set_xlabel("a - b (per prompt: mean over seeds, 95% t interval)", fontsize=8)
    ax.set_title(title, fontsize=8)
    ax.grid(True, axis="x", alpha=0.3)
    return save(fig, path, dpi=100)
