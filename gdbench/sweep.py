"""``gdbench sweep``: train and score every (prompt, preset, seed) cell; write the analogue of
the paper's Tables 1 and 2 (COLMAP variance, registration rate, GT PSNR, iterations, training
time) as CSV and Markdown.

Resumable: each cell lives in ``out/cells/<prompt>/<preset>/seed<k>``; a finished cell (its
``cell.json`` present) is skipped, and an interrupted one resumes from its training
checkpoint. Executors are pluggable: ``local`` (a process pool, default one worker, since one
training already uses both cores here) or ``ray`` (``--address`` of a cluster, or a local
instance when empty).
"""

from __future__ import annotations

import json
import math
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal


@dataclass(frozen=True)
class CellSpec:
    prompt: str
    preset: str
    seed: int
    steps: int
    out: str
    colmap: bool = True
    colmap_views: int = 100
    overrides: dict = field(default_factory=dict)

    @property
    def dir(self) -> Path:
        return Path(self.out) / "cells" / cell_name(self.prompt) / self.preset / f"seed{self.seed}"


def cell_name(prompt: str) -> str:
    """A prompt as a folder name: lower-case letters, digits and '_' only, so no prompt can
    reach outside the sweep's folder ('../../a duck' -> 'a_duck')."""
    import re

    name = re.sub(r"[^a-z0-9]+", "_", prompt.lower()).strip("_")
    if not name:
        raise ValueError(f"prompts: {prompt!r} has no letters or digits to name its cells by")
    return name


def validate_grid(prompts: list[str], presets: list[str], seeds: list[int], specs: list[CellSpec]) -> None:
    """Everything a sweep could fail on, checked before the first cell trains: presets, repeated
    entries, cell folders two prompts would share, prompts no asset matches (or that contradict
    it), and each cell's config."""
    from .assets.library import ASSETS, COLOURS
    from .priors.text import CaptionMatcher, contradiction, normalise
    from .train.config import PRESETS

    bad = [p for p in presets if p not in PRESETS]
    if bad:
        raise ValueError(f"presets: unknown {bad}; expected names from {sorted(PRESETS)}")
    if not prompts or not presets or not seeds:
        raise ValueError("prompts, presets, seeds: expected at least one of each")
    for name, items in (("presets", presets), ("seeds", seeds)):
        if len(set(items)) != len(items):
            raise ValueError(f"{name}: {sorted({x for x in items if items.count(x) > 1})} listed more than once")
    names: dict[str, str] = {}
    for pr in prompts:
        n = cell_name(pr)
        if n in names:
            raise ValueError(
                f"prompts: {names[n]!r} and {pr!r} would share the cell folder {n!r}; list each prompt once"
            )
        names[n] = pr
    matcher = CaptionMatcher(sorted(ASSETS))
    for pr in prompts:
        caption, sim = matcher.match_scored(pr)
        why = contradiction(pr, caption, COLOURS.get(caption, frozenset()) | set(normalise(caption).split()))
        if why is not None:
            raise ValueError(f"prompts: {pr!r} matched {caption!r} (cosine {sim:.2f}): {why}")
    for spec in specs:
        cell_config(spec)  # a bad override raises here, naming the setting


def cell_config(spec: CellSpec):
    """The TrainConfig of a cell."""
    from .train.config import preset

    return preset(
        spec.preset,
        prompt=spec.prompt,
        steps=spec.steps,
        seed=spec.seed,
        out=spec.dir,
        progress=False,
        **spec.overrides,
    )


def run_cell(spec: CellSpec) -> dict:
    """Train (or resume) and score one cell; writes and returns its row."""
    from .io import write_json
    from .metrics.run_scores import score_run
    from .train.checkpoint import CheckpointError
    from .train.run import train

    t0 = time.perf_counter()
    try:
        r = train(cell_config(spec))
    except CheckpointError as e:
        raise CheckpointError(
            f"{str(e).split(';')[0]}; delete {spec.dir} to retrain this cell, or sweep into another --out"
        ) from None
    train_s = sum(h["seconds"] for h in r.state.history)
    scores = score_run(spec.dir, colmap=spec.colmap, views=spec.colmap_views)
    col = scores.get("colmap", {})
    row = {
        "prompt": spec.prompt,
        "preset": spec.preset,
        "seed": spec.seed,
        "iterations": r.state.step,
        "train_time_s": train_s,
        "gaussians": scores["gaussians"],
        "gt_psnr": scores.get("gt", {}).get("psnr", float("nan")),
        "gt_ssim": scores.get("gt", {}).get("ssim", float("nan")),
        "registration_rate": col.get("registration_rate", float("nan")),
        "var_theta_deg2": col.get("var_theta_deg2", float("nan")),
        "translation_dir_err_deg": col.get("translation_dir_err_deg", float("nan")),
        "cell_s": time.perf_counter() - t0,
    }
    write_json({"spec": asdict(spec), "row": row}, spec.dir / "cell.json")
    return row


def _done(spec: CellSpec) -> dict | None:
    p = spec.dir / "cell.json"
    if not p.is_file():
        return None
    blob = json.loads(p.read_text())
    return blob["row"] if blob.get("spec") == json.loads(json.dumps(asdict(spec))) else None


def _median(xs: list[float]) -> float:
    xs = [x for x in xs if x == x]  # drop NaN
    return statistics.median(xs) if xs else math.nan


def _fmt(x: float) -> str:
    return "n/a" if x != x else f"{x:.3g}"


def _mean_std(xs: list[float]) -> str:
    xs = [x for x in xs if x == x]  # drop NaN
    if not xs:
        return "n/a"
    if len(xs) == 1:
        return f"{xs[0]:.4g}"
    return f"{statistics.mean(xs):.4g} ± {statistics.stdev(xs):.2g}"


PAPER_ORDER = (("gd", "gd-no-vgs"), ("gd-no-vgs", "gd-no-sn"), ("gd", "sjc-gs"))
"""The paper's claims on pose variance: each pair (a, b) says Var(a) < Var(b)."""


def paper_ordering(rows: list[dict], metric: str = "var_theta_deg2") -> list[dict]:
    """For each claimed pair (a, b): mean and median of ``metric`` over the cells of a and b, and
    the paired count over (prompt, seed) where a < b. ``holds`` needs both the means and the
    majority of pairs to agree; a pair is undecided when either preset has no finite value.
    Claims about presets absent from ``rows`` are left out."""
    out = []
    ran = {r["preset"] for r in rows}
    for a, b in PAPER_ORDER:
        if not {a, b} <= ran:  # a claim about presets this sweep did not train
            continue
        va = {(r["prompt"], r["seed"]): r[metric] for r in rows if r["preset"] == a and r[metric] == r[metric]}
        vb = {(r["prompt"], r["seed"]): r[metric] for r in rows if r["preset"] == b and r[metric] == r[metric]}
        common = sorted(set(va) & set(vb))
        wins = sum(va[k] < vb[k] for k in common)
        ma = statistics.mean(va.values()) if va else math.nan
        mb = statistics.mean(vb.values()) if vb else math.nan
        holds = None if not (va and vb) else bool(ma < mb and wins * 2 > len(common))
        out.append(
            {
                "claim": f"{a} < {b}",
                "metric": metric,
                "mean_a": ma,
                "mean_b": mb,
                "median_a": _median(list(va.values())),
                "median_b": _median(list(vb.values())),
                "paired_wins": wins,
                "pairs": len(common),
                "holds": holds,
            }
        )
    return out


def tables(rows: list[dict], out: Path) -> dict[str, Path]:
    """Per-cell CSV and the per-preset summary (mean ± std over prompts and seeds) as CSV/Markdown."""
    from .bench.common import write_csv

    out.mkdir(parents=True, exist_ok=True)
    paths = {"cells_csv": write_csv(rows, out / "cells.csv")}
    presets = list(dict.fromkeys(r["preset"] for r in rows))
    summary = []
    for p in presets:
        sel = [r for r in rows if r["preset"] == p]
        summary.append(
            {
                "preset": p,
                "cells": len(sel),
                "var_theta_deg2": _mean_std([r["var_theta_deg2"] for r in sel]),
                "registration_rate": _mean_std([r["registration_rate"] for r in sel]),
                "gt_psnr": _mean_std([r["gt_psnr"] for r in sel]),
                "iterations": _mean_std([r["iterations"] for r in sel]),
                "train_time_s": _mean_std([r["train_time_s"] for r in sel]),
                "median_var_theta_deg2": _median([r["var_theta_deg2"] for r in sel]),
            }
        )
    paths["summary_csv"] = write_csv(summary, out / "summary.csv")
    head = [
        "preset",
        "cells",
        "Var(theta) deg^2 (COLMAP)",
        "median Var",
        "registration",
        "GT PSNR dB",
        "iterations",
        "train time s",
    ]
    md = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for s in summary:
        md.append(
            f"| {s['preset']} | {s['cells']} | {s['var_theta_deg2']} | {_fmt(s['median_var_theta_deg2'])} | "
            f"{s['registration_rate']} | {s['gt_psnr']} | {s['iterations']} | {s['train_time_s']} |"
        )
    order = paper_ordering(rows)
    paths["ordering_csv"] = write_csv(order, out / "ordering.csv")
    md += ["", "| paper's claim (Var(theta)) | mean a | mean b | a < b in pairs | holds |", "|---|---|---|---|---|"]
    if not order:
        md[-2:] = ["The paper's ordering claims need two of its presets in the sweep; none is decidable here."]
    for o in order:
        verdict = {True: "yes", False: "no", None: "undecided"}[o["holds"]]
        md.append(
            f"| {o['claim']} | {_fmt(o['mean_a'])} | {_fmt(o['mean_b'])} | "
            f"{o['paired_wins']}/{o['pairs']} | {verdict} |"
        )
    (out / "summary.md").write_text("\n".join(md) + "\n")
    paths["summary_md"] = out / "summary.md"
    paths["plot"] = plot(rows, out / "ablation.png")
    return paths


def plot(rows: list[dict], path: Path) -> Path:
    """Per preset, every cell's Var(theta), registration rate and GT PSNR (colour = prompt)."""
    from .plotting import pyplot, save

    plt = pyplot()

    presets = list(dict.fromkeys(r["preset"] for r in rows))
    prompts = list(dict.fromkeys(r["prompt"] for r in rows))
    panels = (
        ("var_theta_deg2", "Var(theta) deg$^2$ (COLMAP, lower is better)", True),
        ("registration_rate", "COLMAP registration rate", False),
        ("gt_psnr", "PSNR against the asset (dB)", False),
    )
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.8))
    for ax, (key, label, log) in zip(axes, panels):
        for j, pr in enumerate(prompts):
            xs, ys = [], []
            for i, p in enumerate(presets):
                for r in rows:
                    if r["preset"] == p and r["prompt"] == pr and r[key] == r[key]:
                        xs.append(i + 0.1 * (j - (len(prompts) - 1) / 2))
                        ys.append(r[key])
            ax.scatter(xs, ys, s=18, color=f"C{j}", label=pr)
        means = [_median([r[key] for r in rows if r["preset"] == p]) for p in presets]
        ax.scatter(range(len(presets)), means, marker="_", s=400, color="k", label="median")
        ax.set_xticks(range(len(presets)), presets, rotation=20)
        ax.set_title(label, fontsize=9)
        if not any(r[key] == r[key] for r in rows):  # e.g. a sweep run with colmap=False
            ax.text(0.5, 0.5, "not measured", transform=ax.transAxes, ha="center", color="0.5")
        elif log and any(r[key] > 0 for r in rows if r[key] == r[key]):
            ax.set_yscale("log")
        ax.grid(True, axis="y", alpha=0.3)
    axes[0].legend(fontsize=7)
    return save(fig, path, dpi=110)


def sweep(
    prompts: list[str],
    presets: list[str],
    seeds: list[int],
    *,
    steps: int = 2000,
    out: str | Path = "runs/sweep",
    executor: Literal["local", "ray"] = "local",
    address: str = "",
    workers: int = 1,
    colmap: bool = True,
    colmap_views: int = 100,
    overrides: dict | None = None,
    progress: bool = True,
) -> list[dict]:
    out = Path(out)
    # seeds outermost: a sweep cut short still has every (prompt, preset) for its first seeds
    specs = [
        CellSpec(pr, p, s, steps, str(out), colmap, colmap_views, dict(overrides or {}))
        for s in seeds
        for pr in prompts
        for p in presets
    ]
    validate_grid(prompts, presets, seeds, specs)
    rows: dict[int, dict] = {}
    todo = []
    for i, spec in enumerate(specs):
        done = _done(spec)
        if done is not None:
            rows[i] = done
        else:
            todo.append(i)
    if progress:
        print(f"sweep: {len(specs)} cells, {len(rows)} already finished, {len(todo)} to run ({executor})")
    for i, row in _execute([specs[i] for i in todo], executor, address, workers):
        rows[todo[i]] = row
        tables([rows[k] for k in sorted(rows)], out)
        if progress:
            print(
                f"  done {row['prompt']!r} {row['preset']} seed {row['seed']}: Var {row['var_theta_deg2']:.3g}, "
                f"reg {row['registration_rate']:.2f}, PSNR {row['gt_psnr']:.2f} ({row['cell_s']:.0f} s)"
            )
    ordered = [rows[k] for k in sorted(rows)]
    tables(ordered, out)
    return ordered


def _execute(specs: list[CellSpec], executor: str, address: str, workers: int):
    """Yield (index, row) as cells finish."""
    if executor == "local":
        if workers <= 1:
            for i, s in enumerate(specs):
                yield i, run_cell(s)
            return
        from concurrent.futures import ProcessPoolExecutor, as_completed

        with ProcessPoolExecutor(max_workers=workers) as pool:
            futs = {pool.submit(run_cell, s): i for i, s in enumerate(specs)}
            for f in as_completed(futs):
                yield futs[f], f.result()
        return
    if executor == "ray":
        try:
            import ray
        except ImportError as e:
            raise ImportError("executor='ray' needs Ray: pip install 'ray[default]'") from e
        started = not ray.is_initialized()
        if started:
            ray.init(
                address=address or None,
                include_dashboard=False,
                num_cpus=None if address else max(workers, 1),
                log_to_driver=False,
            )
        try:
            remote = ray.remote(run_cell)
            refs = {remote.remote(s): i for i, s in enumerate(specs)}
            pending = list(refs)
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                yield refs[ready[0]], ray.get(ready[0])
        finally:
            if started:
                ray.shutdown()
        return
    raise ValueError(f"executor: expected 'local' or 'ray', got {executor!r}")
