"""The sweep's tables and figure, written when a sweep ends and every few minutes while it runs:

- ``cells.csv``: one row per (group, setting, prompt, preset, seed) cell;
- ``summary.csv``: per (group, setting, preset), numbers only: each metric's mean, standard deviation
  and number of cells it was measured on (``<metric>_mean``, ``_std``, ``_n``; empty where
  missing), and the median of the heavy-tailed COLMAP variance;
- ``summary.md``: the same as mean ± std, "(k of n)" where a metric was measured on only k of n
  cells, and the commits that trained and scored the cells;
- ``verdict.csv`` (and in ``summary.md``): each of the paper's claims in each setting, as the
  paired difference with a 95% bootstrap interval (``metrics/claims.py``);
- ``ablation.png``: every cell's metrics per preset and setting (``gdbench sweep --figures``).
"""

from __future__ import annotations

import math
import statistics
from pathlib import Path

from gdbench.experiments.claims import REVERSAL_SHARE, label, where

COLUMNS = (
    ("gt_psnr", "GT PSNR dB", False),
    ("judge_janus", "judged Janus", False),
    ("judge_failure", "judged not fine", False),
    ("janus_rate", "Janus rate", False),
    ("front_everywhere_rate", "front everywhere", False),
    ("multi_face_rate", "second face", False),
    ("blob_rate", "blob", False),
    ("instance_inconsistency", "instance inconsistency", False),
    ("floaters", "floaters", False),
    ("turned", "turned > 45 deg", False),
    ("var_theta_deg2", "Var(theta) deg^2", True),
    ("colmap_failure_rate", "COLMAP failure rate", False),
    ("registration_rate", "registration", False),
    ("gaussians", "Gaussians", False),
    ("train_time_s", "train time s", False),
)
"""Summarised metrics: (row key, heading, heavy-tailed: report the median too)."""


def _finite(xs: list) -> list[float]:
    return [float(x) for x in xs if isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)]


def _median(xs: list[float]) -> float:
    xs = _finite(xs)
    return statistics.median(xs) if xs else math.nan


def _fmt(x: float) -> str:
    return "n/a" if x != x else f"{x:.3g}"


def _count(x: float) -> str:
    return "n/a" if x != x else f"{x:.0f}"


def _mean_std(xs: list) -> tuple[float, float, int]:
    """Mean, sample standard deviation (NaN for fewer than two values) and count of the finite
    values of ``xs``."""
    xs = _finite(xs)
    mean = statistics.mean(xs) if xs else math.nan
    std = statistics.stdev(xs) if len(xs) > 1 else math.nan
    return mean, std, len(xs)


def _pretty(mean: float, std: float, n: int, cells: int) -> str:
    if n == 0:
        return "n/a"
    text = f"{mean:.4g}" if std != std else f"{mean:.4g} ± {std:.2g}"
    return text if n == cells else f"{text} ({n} of {cells})"


def summarise(rows: list[dict]) -> list[dict]:
    """Per (group, setting, preset): numbers only, for a dataframe: ``<metric>_mean``, ``_std``
    and ``_n`` (the cells the metric could be measured on; NaN, written empty, where none), and
    the median of the heavy-tailed ones."""
    out = []
    for (group, setting), preset in dict.fromkeys((where(r), r["preset"]) for r in rows):
        sel = [r for r in rows if where(r) == (group, setting) and r["preset"] == preset]
        s = {"group": group, "setting": setting, "preset": preset, "cells": len(sel)}
        for key, _, tailed in COLUMNS + (("iterations", "iterations", False),):
            vals = [r.get(key) for r in sel]
            s[f"{key}_mean"], s[f"{key}_std"], s[f"{key}_n"] = _mean_std(vals)
            if tailed:
                s[f"{key}_median"] = _median(vals)
        out.append(s)
    return out


def commits(rows: list[dict]) -> str:
    """Which code trained and scored the cells, e.g. 'trained at 69486f7c3a34 (30 cells);
    scored at 69486f7c3a34 (30)'."""
    parts = []
    for what, key in (("trained", "train_commit"), ("scored", "score_commit")):
        counts: dict[str, int] = {}
        for r in rows:
            c = r.get(key) or "unknown"
            counts[c] = counts.get(c, 0) + 1
        parts.append(f"{what} at " + ", ".join(f"{c} ({n} cells)" for c, n in counts.items()))
    versions = {r.get("versions") for r in rows if r.get("versions")}
    if len(versions) > 1:
        parts.append(f"MIXED package versions ({len(versions)} sets; cells.csv's versions column)")
    return "; ".join(parts)


def markdown(summary: list[dict], verdicts: list[dict], rows: list[dict] | None = None) -> str:
    head = ["setting", "preset", "cells"]
    for _key, name, tailed in COLUMNS:
        head += [name] + ([f"median {name}"] if tailed else [])
    made_by = {v.get("tables_commit") for v in verdicts} - {None}
    md = (
        [f"Cells {commits(rows)}" + (f"; tables by {', '.join(sorted(made_by))}." if made_by else "."), ""]
        if rows
        else []
    )
    md += ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in summary:
        cells = [label(s), s["preset"], str(s["cells"])]
        for key, _, tailed in COLUMNS:
            cells.append(_pretty(s[f"{key}_mean"], s[f"{key}_std"], s[f"{key}_n"], s["cells"]))
            if tailed:
                cells.append(_fmt(s[f"{key}_median"]))
        md.append("| " + " | ".join(cells) + " |")
    md += ["", "(k of n): the metric could be measured on k of the n cells; n/a: on none.", ""]
    md += ["| setting | claim | a vs b | metric | pairs | mean a | mean b | a - b [95% BCa CI] | a better | "
           "p (Holm) | equivalence p (margin) | pairs for 80% power | verdict on these prompts | prompts | "
           "across prompts: a - b [95% t CI] | p (Holm) | verdict across prompts | Gaussians a / b | "
           "GT PSNR a / b (dB) |"]  # fmt: skip
    md.append("|---" * 19 + "|")
    unmeasured = [v for v in verdicts if v["verdict"] == "not measured" and not float(v["pairs"] or 0)]
    verdicts = [v for v in verdicts if v not in unmeasured]  # a claim no cell could measure: one line below
    if not verdicts:
        md[-2:] = ["No claim is decidable here: each needs both of its presets in one setting."]
    for v in verdicts:
        ci = f"{_fmt(v['mean_diff'])} [{_fmt(v['ci_low'])}, {_fmt(v['ci_high'])}]"
        p = f"{_fmt(v['p_value'])} ({_fmt(v['p_holm'])})"
        eq = f"{_fmt(v['p_equivalence'])} (+-{_fmt(v['margin'])})"
        md.append(
            f"| {label(v)} | {v['claim']} | {v['a']} vs {v['b']} | {v['metric']} | {v['pairs']} | "
            f"{_fmt(v['mean_a'])} | {_fmt(v['mean_b'])} | {ci} | {v['a_better_pairs']}/{v['pairs']} | {p} | {eq} | "
            f"{_fmt(v['pairs_for_80pct_power'])} | {v['verdict']} | {v['prompts']} | "
            f"{_fmt(v['prompt_mean_diff'])} [{_fmt(v['prompt_ci_low'])}, {_fmt(v['prompt_ci_high'])}] | "
            f"{_fmt(v['p_prompts'])} ({_fmt(v['p_prompts_holm'])}) | {v['verdict_prompts']} | "
            f"{_count(v['gaussians_a'])} / {_count(v['gaussians_b'])}{_size_note(v)} | "
            f"{_fmt(v.get('gt_psnr_a', math.nan))} / {_fmt(v.get('gt_psnr_b', math.nan))} |"
        )
    if verdicts:
        md += ["", "Per prompt, the mean difference a - b (pairs), and the prompts that go against the pooled "
               f"reading (one sign in at least {REVERSAL_SHARE:.0%} of their pairs: the sign opposite to the pooled "
               "mean where the verdict holds or does not hold, either sign where it is not decided):", "",
               "| setting | a vs b | metric | per prompt | against the pooled reading |",
               "|---|---|---|---|---|"]  # fmt: skip
        for v in verdicts:
            md.append(f"| {label(v)} | {v['a']} vs {v['b']} | {v['metric']} | {v['by_prompt'] or 'n/a'} | "
                      f"{v.get('reversals') or 'none'} |")  # fmt: skip
        left = sorted({v["left_out"] for v in verdicts if v.get("left_out")})
        if left:
            md += ["", *[f"Left out of the claims on {line}." for line in left]]
    if unmeasured:
        md += ["", "Not measured (no cell has the metric in both arms): "
               + "; ".join(f"{label(v)}, {v['a']} vs {v['b']}, {v['metric']}" for v in unmeasured) + "."]  # fmt: skip
    return "\n".join(md) + "\n"


def _size_note(v: dict) -> str:
    return f" (sizes differ {v['size_ratio']:.1f}x: growth confounds the pair)" if v["size_confounded"] else ""


def tables(
    rows: list[dict], out: Path, figures: bool = True, claims=None, prompt_test: str = "t", labels=None
) -> dict[str, Path]:
    """cells.csv, summary.csv, verdict.csv, summary.md and, with ``figures``, ablation.png;
    ``claims`` (default: every claim, ``claims.CLAIMS``) and ``prompt_test`` as ``claims.evaluate``;
    ``claims`` may also be a dict of families (name -> claims), each Holm-adjusted on its own and
    named in the verdict's ``family`` column. With ``labels`` (rater label files by run id) the
    claims on the Janus outcome read the labels, else the judge (``outcome.read_outcome``), and
    summary.md says which."""
    from gdbench.core.io import write_csv
    from gdbench.experiments.claims import CLAIMS, evaluate
    from gdbench.experiments.outcome import attach_labels, outcome_note, read_outcome

    out.mkdir(parents=True, exist_ok=True)
    if labels:
        rows = attach_labels(rows, list(labels))
        if not any("label_janus" in r for r in rows):  # files for another sweep: no verdict reads nothing
            files = [str(f) for f in labels]
            raise ValueError(f"labels: none of the cells' run ids is labelled in every file of {files}")
    paths = {"cells_csv": write_csv(rows, out / "cells.csv")}
    summary = summarise(rows)
    paths["summary_csv"] = write_csv(summary, out / "summary.csv")
    from gdbench.core.provenance import code_commit

    tables_commit = code_commit()  # the statistics' code: the cells say which code made them
    families = claims if isinstance(claims, dict) else {"": claims or CLAIMS}
    verdicts = [
        v | ({"family": name} if name else {}) | {"tables_commit": tables_commit}
        for name, family in families.items()
        for v in evaluate(rows, read_outcome(family, bool(labels)), prompt_test)
    ]
    paths["verdict_csv"] = write_csv(verdicts, out / "verdict.csv")
    (out / "summary.md").write_text(outcome_note(rows, labels) + "\n\n" + markdown(summary, verdicts, rows))
    paths["summary_md"] = out / "summary.md"
    if figures:
        paths["plot"] = plot(rows, out / "ablation.png")
    else:  # one drawn by an earlier --figures pass would show other cells
        (out / "ablation.png").unlink(missing_ok=True)
    return paths


def plot(rows: list[dict], path: Path) -> Path:
    """Per group and setting (rows of panels) and metric (columns), every cell per preset (colour
    and marker = prompt: ten colours, a new marker for every ten prompts)."""
    from gdbench.core.plotting import pyplot, save

    plt = pyplot()
    settings = list(dict.fromkeys(where(r) for r in rows))
    prompts = list(dict.fromkeys(r["prompt"] for r in rows))
    panels = [c for c in COLUMNS if c[0] not in ("train_time_s", "gaussians")]
    spread = min(0.08, 0.6 / max(len(prompts) - 1, 1))  # a preset's prompts side by side within +-0.3
    ncol = 1 + len(prompts) // 16  # the legend's columns, 1.8 inches each beside the panels
    width = 2.6 * len(panels) + 1.8 * ncol
    fig, axes = plt.subplots(len(settings), len(panels), figsize=(width, 2.6 * len(settings)), squeeze=False)
    for si, setting in enumerate(settings):
        sel = [r for r in rows if where(r) == setting]
        presets = list(dict.fromkeys(r["preset"] for r in sel))
        for ax, (key, name, log) in zip(axes[si], panels):
            for j, pr in enumerate(prompts):
                pts = [
                    (i + spread * (j - (len(prompts) - 1) / 2), float(r[key]))
                    for i, p in enumerate(presets)
                    for r in sel
                    if r["preset"] == p and r["prompt"] == pr and _finite([r.get(key)])
                ]
                if pts:
                    ax.scatter(
                        *zip(*pts),
                        s=10,
                        color=f"C{j % 10}",
                        marker="os^Dv<>p"[j // 10 % 8],
                        label=pr if si == 0 else None,
                    )
            meds = [_median([r.get(key) for r in sel if r["preset"] == p]) for p in presets]
            ax.scatter(range(len(presets)), meds, marker="_", s=300, color="k")
            ax.set_xticks(range(len(presets)), presets, rotation=35, fontsize=7)
            ax.set_title(f"{label({'group': setting[0], 'setting': setting[1]})}: {name}", fontsize=8)
            vals = _finite([r.get(key) for r in sel])
            if not vals:
                ax.text(0.5, 0.5, "not measured", transform=ax.transAxes, ha="center", color="0.5")
            elif log and any(v > 0 for v in vals):
                ax.set_yscale("log")
            ax.grid(True, axis="y", alpha=0.3)
    handles, names = axes[0][0].get_legend_handles_labels()
    if handles:  # the prompts' colours beside the panels, not over the first one
        fig.tight_layout(rect=(0, 0, 1 - 1.8 * ncol / width, 1))
        fig.legend(handles, names, loc="center right", fontsize=6, ncol=ncol, frameon=False)
    return save(fig, path, dpi=100)
