"""The paper's claims as paired comparisons a statistician would sign (the tests themselves:
``experiments/stats.py``).

Each claim says preset ``a`` scores lower than preset ``b`` on a metric where lower is better.
Over the (prompt, seed) pairs that both presets ran in one setting, the paired differences
d = metric(a) - metric(b) give:

- the mean difference with a **BCa** 95% interval (``scipy.stats.bootstrap``, 10,000 resamples
  of the pairs, a fixed seed; the percentile interval where BCa is undefined, e.g. all
  differences equal);
- a **Wilcoxon signed-rank** two-sided p-value (zero differences dropped: ``zero_method
  "wilcox"``; exact, ties at mid-ranks, up to 16 non-zero differences, scipy's normal
  approximation beyond), and the same p-value **Holm**-adjusted
  across the claims of the table that a test decides (``evaluate``'s rows; a row not measured,
  not testable because neither arm fails or both always fail, or with too few pairs, is no
  hypothesis tested and stays out of the family; a row whose failures are rarer than the
  margin stays in it, since its test can still decide);
- an **equivalence** test of the mean against the claim's margin m (``MARGINS``: the smallest
  effect that would matter, with its reason): two one-sided paired t-tests of mean(d) > -m and
  mean(d) < m (TOST), p = the larger of the two. Not signed-rank tests: those test a location
  shift, and on rates that are 0 in most pairs they passed pairs whose mean difference was
  outside the margin (0.072 against +-0.05 in the decisive sweep's first read);
- the **pairs needed** for 80% power at a two-sided 5% level, from the observed mean and
  standard deviation of d (normal approximation, divided by the Wilcoxon test's asymptotic
  relative efficiency 3/pi);
- the mean difference **per prompt** (``by_prompt``), so that one prompt cannot carry a pooled
  verdict unseen;
- the same claim **across prompts** (``across_prompts``): the per-prompt mean differences as G
  observations, their mean with a t interval, a two-sided t p-value Holm-adjusted over the same
  family, and ``verdict_prompts`` in the same words. The pairs' verdict is about the prompts that
  ran (seeds are the random unit; pairs of one prompt are independent given it); this one is
  about prompts beyond them, where the pairs of one prompt are correlated and G, not the pair
  count, is the sample size (6 prompts: an effect must be large and shared to pass Holm).

The verdict words, checked in this order:

- **not measured**: no pair has the metric in both arms (not scored, or nothing to score);
- **not testable here (neither preset fails)**: the metric is 0 in every pair: the mechanism
  had nothing to fix in this setting, which is no evidence either way;
- **not testable here (both always fail)**: the metric sits at its failure value in every pair
  of both arms (COLMAP registers nothing in either, so its failure rate is 1.0 throughout): the
  metric cannot see a difference, which is no evidence either way;
- **too few pairs (n < 6)**: fewer than ``MIN_PAIRS`` pairs: below six, even pairs that all
  agree are not significant (the exact two-sided signed-rank p is 2^(1-n) >= 0.0625);
- **holds** / **does not hold**: the Holm-adjusted p-value is below 0.05 (with at least six
  non-tied pairs) and the BCa interval of the mean difference lies below 0 (the claim holds) or
  above 0 (the opposite holds); a significant rank test whose mean interval covers 0 (a skewed
  sample: the median moves one way, the mean not) decides nothing and goes on to the words below;
- **not testable here (baseline fails < m)**: not significant, and both arms' means are surely
  under the margin m (their one-sided 95% t upper bounds over the pairs): every metric here is
  a failure measure of at least 0, so no reduction could reach m and the equivalence test says
  nothing about the mechanism (a setting where the failure is too rare to test the claim). A
  treated arm that fails more than m is not hidden here: the equivalence test can then fail,
  and the row reads undecided or does not hold;
- **no effect beyond +-m**: the equivalence test's p is below 0.05 and the BCa 95% interval
  lies within +-m (so a reader checks it in the table): a null result with the power to say so
  (a tie in every pair counts here: the presets do the same);
- **too few non-tied pairs (k < 6)**: the pairs are enough but fewer than six differ, so the
  signed-rank test cannot reach 5%;
- **undecided**: none of the above: more pairs are needed (see the power column).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from gdbench.core.io import num
from gdbench.experiments.stats import (
    ALPHA,
    bca_ci,
    equivalence_p,
    holm,
    pairs_for_power,
    sign_flip_p,
    signed_rank_p,
    upper_bound,
)


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
    Claim(
        "structured noise reduces Janus failures (the front everywhere or a second face)",
        "gd",
        "gd-no-sn",
        "janus_rate",
        1.0,
    ),
    Claim("persistent noise, not the noise's texture, cuts Janus failures", "gd", "gd-redraw-step", "janus_rate", 1.0),
    Claim(
        "3D correspondence between views, not persistence alone, cuts Janus failures",
        "gd",
        "gd-pose-locked",
        "janus_rate",
        1.0,
    ),
    Claim("structured noise reduces the results the judge calls Janus", "gd", "gd-no-sn", "judge_janus", 1.0),
    Claim("persistent noise cuts the results the judge calls Janus", "gd", "gd-redraw-step", "judge_janus", 1.0),
    Claim("3D correspondence cuts the results the judge calls Janus", "gd", "gd-pose-locked", "judge_janus", 1.0),
    Claim("structured noise reduces instance inconsistency", "gd", "gd-no-sn", "instance_inconsistency"),
    Claim("structured noise reduces instance inconsistency", "gd-no-vgs", "sjc-gs", "instance_inconsistency"),
    Claim("variational Gaussians reduce floaters", "gd", "gd-no-vgs", "floaters"),
    Claim("variational Gaussians reduce floaters", "gd-no-sn", "sjc-gs", "floaters"),
    Claim("gd is more consistent than SJC on COLMAP (failure rate)", "gd", "sjc-gs", "colmap_failure_rate", 1.0),
    Claim("gd is more consistent than SDS on COLMAP (failure rate)", "gd", "sds-gs", "colmap_failure_rate", 1.0),
    Claim("structured noise makes results more COLMAP-consistent", "gd", "gd-no-sn", "colmap_failure_rate", 1.0),
    Claim("variational Gaussians make results more COLMAP-consistent", "gd", "gd-no-vgs", "colmap_failure_rate", 1.0),
)
"""The paper's claims (section 4) in the ablation's terms. COLMAP's are read on its failure rate
(adjacent views unregistered or off the true relative rotation by more than 5 degrees), which
every cell has: Var(theta) is defined only over registered views, so cells that register fewer
than three drop out of it and the pairs left are a selection; it stays in the summary (mean and
median) with no verdict of its own. gd against SJC differs in two factors (structured noise and
variational Gaussians); the last two claims read each factor on its own, where the sweep ran
COLMAP for gd-no-sn and gd-no-vgs."""


MIN_PAIRS = 6
"""Fewest pairs (and non-tied pairs) a difference is read from (module docstring)."""

MARGINS = {
    "multi_face_rate": (0.05, "one view in twenty of the turntable"),
    "janus_rate": (0.05, "one view in twenty of the turntable"),
    "janus_failure_rate": (0.05, "one view in twenty of the turntable"),
    "label_janus": (0.05, "one result in twenty labelled Janus by eye"),
    "label_failure": (0.05, "one result in twenty labelled not fine by eye"),
    "judge_janus": (0.05, "one result in twenty judged Janus"),
    "judge_failure": (0.05, "one result in twenty judged not fine"),
    "instance_inconsistency": (0.05, "one view in twenty of the turntable"),
    "colmap_failure_rate": (0.05, "one view in twenty of COLMAP's circle"),
    "floaters": (0.01, "a tenth of the 40-floater 3D fixtures' 0.08-0.15 (every other fixture 0.000)"),
}
"""Equivalence margin of each metric: the smallest difference that would matter, and why."""


def untested(baseline: np.ndarray, treated: np.ndarray, fails_at: float | None) -> str | None:
    """Why a claim's pairs admit no test (its verdict words), or None: such a row is left out of
    the Holm family, which holds only the claims a test decides."""
    if baseline.size == 0:
        return "not measured"
    if np.all(baseline == 0) and np.all(treated == 0):
        return "not testable here (neither preset fails)"
    if fails_at is not None and np.all(baseline == fails_at) and np.all(treated == fails_at):
        return "not testable here (both always fail)"
    if baseline.size < MIN_PAIRS:
        return f"too few pairs (n < {MIN_PAIRS})"
    return None


def verdict(row: dict, *, baseline: np.ndarray, treated: np.ndarray, fails_at: float | None) -> str:
    """The verdict words of one claim's row (module docstring: the words and their order)."""
    why = untested(baseline, treated, fails_at)
    if why is not None:
        return why
    significant = row["p_holm"] < ALPHA and row["nonzero_pairs"] >= MIN_PAIRS  # (exact p: k < 6 cannot)
    if significant and (row["ci_high"] < 0 or row["ci_low"] > 0):
        return "holds" if row["ci_high"] < 0 else "does not hold"
    # (significant ranks with a mean interval over 0: the mean may still be bounded by the margin)
    if upper_bound(baseline) < row["margin"] and upper_bound(treated) < row["margin"]:  # no reduction could reach it
        return f"not testable here (baseline fails < {row['margin']:g})"
    if row["p_equivalence"] < ALPHA and -row["margin"] < row["ci_low"] <= row["ci_high"] < row["margin"]:
        return f"no effect beyond +-{row['margin']:g}"
    if row["nonzero_pairs"] < MIN_PAIRS:
        return f"too few non-tied pairs (k < {MIN_PAIRS})"
    return "undecided"


SIZE_RATIO_LIMIT = 2.0
"""Paired arms whose mean Gaussian counts differ by more than this factor are flagged: the size of
the model, not only what the claim ablates, then differs between them (docs/training.md)."""


def _sizes(rows: list[dict], c: Claim, keys: list) -> dict:
    """Mean final Gaussian count and GT PSNR of each arm over the pairs (what else differs between
    the arms, printed beside the claim), the counts' ratio (larger / smaller) and whether it
    exceeds ``SIZE_RATIO_LIMIT``."""

    def mean(preset: str, metric: str) -> float:
        n = {(r["prompt"], r["seed"]): num(r.get(metric)) for r in rows if r["preset"] == preset}
        vals = [float(n[k]) for k in keys if k in n and n[k] == n[k]]
        return float(np.mean(vals)) if vals else math.nan

    ga, gb = mean(c.a, "gaussians"), mean(c.b, "gaussians")
    ratio = max(ga, gb) / min(ga, gb) if ga > 0 and gb > 0 else math.nan
    return {
        "gaussians_a": ga,
        "gaussians_b": gb,
        "size_ratio": ratio,
        "size_confounded": bool(ratio > SIZE_RATIO_LIMIT),
        "gt_psnr_a": mean(c.a, "gt_psnr"),
        "gt_psnr_b": mean(c.b, "gt_psnr"),
    }


REVERSAL_SHARE = 0.8
"""A prompt goes against a claim's pooled reading when at least this share of its pairs (8 of 10
seeds) differ with one sign: the sign opposite to the pooled mean difference where the pooled
reading decided (holds, does not hold), either sign where it did not (a pooled 'undecided' then
hides a one-way prompt)."""
REVERSAL_MIN_PAIRS = 5
"""Fewest pairs of one prompt a reversal is read from."""


def reversals(keys: list[tuple], d: np.ndarray, *, decided: bool = True) -> str:
    """The prompts that go against the pooled reading (``REVERSAL_SHARE``), e.g. 'a penguin +0.43
    (9 of 10 pairs)'; '' when none. ``decided``: whether the pooled reading decided (then only the
    sign opposite to the pooled mean counts)."""
    if not len(d):
        return ""
    pooled = np.sign(d.mean())
    out = []
    for prompt, v in per_prompt(keys, d).items():
        v = np.asarray(v)
        for sign in (1.0, -1.0):
            if (decided and sign == pooled) or len(v) < REVERSAL_MIN_PAIRS:
                continue
            k = int((np.sign(v) == sign).sum())
            if k >= math.ceil(REVERSAL_SHARE * len(v)):
                out.append(f"{prompt} {v.mean():+.2g} ({k} of {len(v)} pairs)")
    return "; ".join(out)


def user_claims(given, presets: list[str]) -> tuple[Claim, ...]:
    """A sweep's own claims (``Claim``s or mappings with text, a, b, metric and optionally
    fails_at), each between two different presets of the sweep, on a metric with a margin
    (``MARGINS``) or the outcome ('janus', 'failure': rater labels where the sweep is given them,
    else the judge; ``outcome.read_outcome``); anything else is a ValueError naming the claim."""
    out = []
    for i, c in enumerate(given or ()):
        where = f"claims[{i}]"
        if isinstance(c, dict):
            unknown = set(c) - {"text", "a", "b", "metric", "fails_at"}
            if unknown or not {"text", "a", "b", "metric"} <= set(c):
                raise ValueError(f"{where}: expected text, a, b, metric (and fails_at), got keys {sorted(c)}")
            c = Claim(str(c["text"]), str(c["a"]), str(c["b"]), str(c["metric"]), c.get("fails_at"))
        if not isinstance(c, Claim):
            raise ValueError(f"{where}: expected a mapping or a Claim, got {type(c).__name__}")
        bad = [p for p in (c.a, c.b) if p not in presets]
        if bad or c.a == c.b:
            raise ValueError(f"{where} ({c.text!r}): a and b must be two different presets of the sweep {presets}")
        known = sorted(MARGINS) + ["janus", "failure"]  # the outcome: labels where given, else the judge
        if c.metric not in known:
            raise ValueError(f"{where} ({c.text!r}): metric: expected one of {known}, got {c.metric!r}")
        if c.fails_at is not None and not isinstance(c.fails_at, (int, float)):
            raise ValueError(f"{where} ({c.text!r}): fails_at: expected a number or none, got {c.fails_at!r}")
        out.append(c)
    return tuple(out)


JANUS_METRICS = ("janus_rate", "multi_face_rate", "front_everywhere_rate", "janus_failure_rate", "judge_janus")
JANUS_SETTING_METRICS = (
    "janus_rate",
    "janus_failure_rate",
    "label_janus",
    "label_failure",
    "judge_janus",
    "judge_failure",
)
"""Metrics whose claims are read in the janus setting only (``_applies``); ``label_*``: the share of
blind raters who labelled a result Janus (front everywhere or a second face) or not fine."""
"""Metrics of the Janus classes: defined only for assets with a front (``assets.library.FRONTS``)."""


def left_out(metric: str, ran: set, kept: list) -> str:
    """The prompts that ran in both arms but give no pair of ``metric``, with why: '' when none
    (e.g. "janus_rate: a hamburger (the asset declares no front)")."""
    from gdbench.assets.library import FRONTS

    prompts = sorted({p for p, _ in ran} - {p for p, _ in kept})
    if not prompts:
        return ""
    frontless = metric in JANUS_METRICS and all(FRONTS.get(p, "") is None for p in prompts)
    return f"{metric}: {', '.join(prompts)} ({'the asset declares no front' if frontless else 'not measured'})"


def _applies(claim: Claim, rows: list[dict], setting: str) -> bool:
    """Instance consistency is only defined where the bank holds several variants; the Janus
    failure (a second face or none) only where view prompting is off (the janus setting), since
    with a view window a featureless result is a blur, not a pose ambiguity."""
    if claim.metric in JANUS_SETTING_METRICS:
        return setting == "janus"
    if claim.metric != "instance_inconsistency":
        return True
    return setting == "instance" or any(int(r.get("variants", 1) or 1) > 1 for r in rows)


def where(row: dict) -> tuple[str, str]:
    """(group, setting) of a sweep row: the cells a claim pairs within (group '' when the sweep
    had none; setting 'easy' when a row has none)."""
    return row.get("group") or "", row.get("setting") or "easy"


def label(row: dict) -> str:
    """Where a row belongs, as tables print it: its setting, after its group when it has one."""
    group, setting = where(row)
    return f"{group} / {setting}" if group else setting


def by_pair(rows: list[dict], preset: str, metric: str) -> dict[tuple, float]:
    """``metric`` of each ``preset`` cell of ``rows`` by its (prompt, seed) pair (NaN where missing)."""
    return {(r["prompt"], r["seed"]): num(r.get(metric)) for r in rows if r["preset"] == preset}


def paired(va: dict, vb: dict) -> tuple[list, np.ndarray, np.ndarray]:
    """The keys both ``va`` and ``vb`` hold with finite values (sorted) and the two arrays of values."""
    keys = sorted(k for k in set(va) & set(vb) if va[k] == va[k] and vb[k] == vb[k])
    return keys, np.array([va[k] for k in keys], dtype=np.float64), np.array([vb[k] for k in keys], dtype=np.float64)


def evaluate(rows: list[dict], claims=CLAIMS, prompt_test: str = "t") -> list[dict]:
    """One result per (group, setting, claim) whose two presets ran there (instance claims only
    where the prior held several variants); p-values Holm-adjusted across the claims a test
    decides in the whole table (rows not measured, not testable or with too few pairs have no
    adjusted p). ``prompt_test``: the test across prompts Holm adjusts ("t" or "signflip":
    ``across_prompts``)."""
    out, arms = [], []
    for group, setting in dict.fromkeys(where(r) for r in rows):
        sel = [r for r in rows if where(r) == (group, setting)]
        ran = {r["preset"] for r in sel}
        for c in claims:
            if not {c.a, c.b} <= ran or not _applies(c, sel, setting):
                continue
            va, vb = (by_pair(sel, preset, c.metric) for preset in (c.a, c.b))
            keys, a, b = paired(va, vb)
            d = a - b
            lo, hi = bca_ci(d)
            margin, why = MARGINS.get(c.metric, (math.nan, "no margin stated"))
            out.append(
                {
                    "group": group,
                    "setting": setting,
                    "claim": c.text,
                    "a": c.a,
                    "b": c.b,
                    "metric": c.metric,
                    "pairs": len(keys),
                    "nonzero_pairs": int((d != 0).sum()),
                    "mean_a": float(a.mean()) if keys else math.nan,
                    "mean_b": float(b.mean()) if keys else math.nan,
                    "mean_diff": float(d.mean()) if keys else math.nan,
                    "ci_low": lo,
                    "ci_high": hi,
                    "a_better_pairs": int((d < 0).sum()),
                    "p_value": signed_rank_p(d) if keys else math.nan,
                    "p_holm": math.nan,
                    "margin": margin,
                    "margin_reason": why,
                    "p_equivalence": equivalence_p(d, margin) if keys and margin == margin else math.nan,
                    "pairs_for_80pct_power": pairs_for_power(d, floor=MIN_PAIRS),
                    **across_prompts(keys, d, margin, prompt_test),
                    "by_prompt": by_prompt(keys, d),
                    "reversals": "",  # after the verdict (below)
                    "left_out": left_out(c.metric, set(va) & set(vb), keys),
                    **_sizes(sel, c, keys),
                }
            )
            arms.append((b, a, c.fails_at, keys, d))
    family = [r["p_value"] if untested(b, a, f) is None else math.nan for r, (b, a, f, *_) in zip(out, arms)]
    for row, p in zip(out, holm(family)):
        row["p_holm"] = p
    family = [r["p_prompts"] if f == f and r["prompts"] >= MIN_PROMPTS else math.nan for r, f in zip(out, family)]
    for row, p in zip(out, holm(family)):
        row["p_prompts_holm"] = p
    for row, (b, a, fails_at, keys, d) in zip(out, arms):
        row["verdict"] = verdict(row, baseline=b, treated=a, fails_at=fails_at)
        row["reversals"] = reversals(keys, d, decided=row["verdict"] in ("holds", "does not hold"))
        row["verdict_prompts"] = verdict_prompts(row)
    return out


MIN_PROMPTS = 3
"""Fewest prompts a difference across prompts is read from."""


def across_prompts(keys: list[tuple], d: np.ndarray, margin: float, test: str = "t") -> dict:
    """The claim with the prompt as the unit: the mean of the per-prompt mean differences, its
    t interval, the two-sided t p-value over the G prompts (G - 1 degrees of freedom,
    ``p_prompts_t``), the exact sign-flip p (``p_prompts_signflip``, ``sign_flip_p``) and the
    t-TOST p against the margin; ``p_prompts`` (the one Holm adjusts) is the ``test``'s ("t" or
    "signflip"). Pairs of one prompt share its asset and caption, so across prompts they are not
    independent; this is the reading for prompts beyond the ones run."""
    from scipy import stats

    if test not in ("t", "signflip"):
        raise ValueError(f"test: expected 't' or 'signflip', got {test!r}")
    pm = np.array([np.mean(v) for v in per_prompt(keys, d).values()], dtype=np.float64)
    nan = {"prompts": len(pm), "prompt_mean_diff": math.nan, "prompt_ci_low": math.nan, "prompt_ci_high": math.nan,
           "p_prompts": math.nan, "p_prompts_holm": math.nan, "p_prompts_t": math.nan,
           "p_prompts_signflip": math.nan, "p_prompts_equivalence": math.nan}  # fmt: skip
    if len(pm) < 2:
        return nan | ({"prompt_mean_diff": float(pm.mean())} if len(pm) else {})
    mean, se = float(pm.mean()), float(pm.std(ddof=1)) / math.sqrt(len(pm))
    t = stats.t(len(pm) - 1)
    flip = sign_flip_p(pm)
    if np.all(pm == pm[0]):  # every prompt moved alike: the exact sign-flip p (no t: its se is 0)
        p, lo, hi = flip, mean, mean
    else:
        p = float(2 * t.sf(abs(mean) / se))
        lo, hi = mean - t.ppf(0.975) * se, mean + t.ppf(0.975) * se
    return nan | {"prompt_mean_diff": mean, "prompt_ci_low": float(lo), "prompt_ci_high": float(hi),
                  "p_prompts": p if test == "t" else flip, "p_prompts_signflip": flip,
                  "p_prompts_t": math.nan if np.all(pm == pm[0]) else p,
                  "p_prompts_equivalence": equivalence_p(pm, margin) if margin == margin else math.nan}  # fmt: skip


def verdict_prompts(row: dict) -> str:
    """The verdict words with the prompt as the unit (``across_prompts``; Holm over the same
    family): the pairs' words where they admit no test, the failure is too rare or fewer than six
    pairs differ; otherwise holds / does not hold (the adjusted p under 5% and the t interval on
    one side of 0), no effect beyond +-m (t-TOST and the interval
    inside the margin), too few prompts, or undecided."""
    words = row["verdict"]
    if words.startswith(("not measured", "not testable", "too few pairs")) or row["nonzero_pairs"] < MIN_PAIRS:
        return words  # (k < 6 non-tied pairs: a t test over their prompt means would be far too liberal)
    if row["prompts"] < MIN_PROMPTS:
        return f"too few prompts (G < {MIN_PROMPTS})"
    if row["p_prompts_holm"] < ALPHA and (row["prompt_ci_high"] < 0 or row["prompt_ci_low"] > 0):
        return "holds" if row["prompt_mean_diff"] < 0 else "does not hold"
    m = row["margin"]
    if row["p_prompts_equivalence"] < ALPHA and -m < row["prompt_ci_low"] <= row["prompt_ci_high"] < m:
        return f"no effect beyond +-{m:g}"
    return "undecided"


def per_prompt(keys: list[tuple], d: np.ndarray) -> dict[str, list[float]]:
    """The differences ``d`` of the (prompt, seed) pairs ``keys``, grouped by prompt (first-seen order)."""
    per: dict[str, list[float]] = {}
    for (prompt, _seed), x in zip(keys, d):
        per.setdefault(prompt, []).append(float(x))
    return per


def by_prompt(keys: list[tuple], d: np.ndarray) -> str:
    """The mean difference per prompt with its pair count, e.g. 'a corgi -0.05 (3); a duck 0 (3)'."""
    return "; ".join(f"{p} {np.mean(v):+.3g} ({len(v)})" for p, v in per_prompt(keys, d).items())
