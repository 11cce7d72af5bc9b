"""The training-schedule study of docs/training.md: GT PSNR and Gaussian count against the run's
length and against views per step, one run per point, scored against the asset.

    python scripts/study_schedule.py run --out runs/study_after --steps 100:2000:100 \
        --steps 399 401 799 801 1199 1201 1599 1601 --views 1
    python scripts/study_schedule.py run --out runs/study_after --steps 2000 --views 1 2 4
    python scripts/study_schedule.py plot runs/study_before/study.csv runs/study_after/study.csv \
        --labels before after --out docs/figures/schedule_study.png

Resumable: a point already in ``study.csv`` (same steps, views and overrides) is skipped, and a
run interrupted mid-training resumes from its checkpoint. Every row records the commit of the
code it ran (``git describe --always --dirty``), the machine's time and the run's wall time.
It uses only ``train`` and ``score_against_asset``, so it runs unchanged against older commits
(run it from a clone frozen at that commit).
"""

from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

FIELDS = [
    "steps", "views", "seed", "overrides", "gaussians", "psnr", "ssim", "mean_opacity",
    "duplicates", "train_s", "ms_per_step", "commit", "utc",
]  # fmt: skip


def _commit() -> str:
    import gdbench

    root = Path(gdbench.__file__).resolve().parents[1]
    try:
        return subprocess.check_output(["git", "describe", "--always", "--dirty"], cwd=root, text=True).strip()
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _median(xs: list[float]) -> float:
    """The median of ``xs`` (nan when empty): a step's time, robust to the first steps' warm-up."""
    xs = sorted(xs)
    return xs[len(xs) // 2] if xs else float("nan")


def _steps(items: list[str]) -> list[int]:
    out: list[int] = []
    for it in items:
        if ":" in it:
            a, b, c = (int(x) for x in it.split(":"))
            out += list(range(a, b + 1, c))
        else:
            out.append(int(it))
    return sorted(set(out))


def _parse_overrides(items: list[str]) -> dict:
    out = {}
    for it in items:
        k, _, v = it.partition("=")
        out[k] = json.loads(v)
    return out


def run(args) -> None:
    import torch

    from gdbench.metrics.gt import score_against_asset
    from gdbench.train.config import preset
    from gdbench.train.run import train

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    table = out / "study.csv"
    done = set()
    if table.is_file():
        with open(table) as f:
            done = {(int(r["steps"]), int(r["views"]), int(r["seed"]), r["overrides"]) for r in csv.DictReader(f)}
    overrides = _parse_overrides(args.set)
    okey = json.dumps(overrides, sort_keys=True)
    commit = _commit()
    todo = [
        (s, v, seed)
        for seed in args.seeds
        for v in args.views
        for s in _steps(args.steps)
        if (s, v, seed, okey) not in done
    ]
    print(f"study: {len(todo)} runs to do ({len(done)} done) -> {table} (commit {commit})", flush=True)
    for s, v, seed in todo:
        t0 = time.perf_counter()
        tag = "".join(f"_{k.split('.')[-1]}{val}" for k, val in sorted(overrides.items()))
        folder = out / "runs" / f"s{s}_v{v}_seed{seed}{tag}"
        cfg = preset(
            args.preset,
            prompt=args.prompt,
            steps=s,
            seed=seed,
            views_per_step=v,
            out=folder,
            progress=False,
            **overrides,
        )
        r = train(cfg, write_outputs=True, overwrite=False)
        scene = r.state.scene()
        bg = tuple(cfg.background)
        sc = score_against_asset(scene, r.caption, background=bg)
        key = torch.cat([scene.means, scene.log_scales, scene.opacity_logits[:, None]], 1)
        dup = len(key) - len(torch.unique(key, dim=0))
        row = {
            "steps": s,
            "views": v,
            "seed": seed,
            "overrides": okey,
            "gaussians": len(scene),
            "psnr": round(sc.psnr, 3),
            "ssim": round(sc.ssim, 4),
            "mean_opacity": round(float(torch.sigmoid(scene.opacity_logits).mean()), 4),
            "duplicates": dup,
            "train_s": round(time.perf_counter() - t0, 1),
            "ms_per_step": round(1e3 * _median([h["seconds"] for h in r.state.history if "seconds" in h]), 1),
            "commit": commit,
            "utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        }
        new = not table.is_file()
        with open(table, "a", newline="") as f:
            w = csv.DictWriter(f, FIELDS)
            if new:
                w.writeheader()
            w.writerow(row)
        print(" ".join(f"{k}={row[k]}" for k in FIELDS if k != "overrides"), flush=True)


def _by(rows: list[dict], key: str, value: str, **where) -> dict[int, list[float]]:
    """{rows[key]: [rows[value], ...]} over the rows matching ``where`` (one entry per seed)."""
    out: dict[int, list[float]] = {}
    for r in rows:
        if all(str(r[k]) == str(v) for k, v in where.items()):
            out.setdefault(int(r[key]), []).append(float(r[value]))
    return dict(sorted(out.items()))


def plot(args) -> None:
    """PSNR and Gaussians against --steps (mean over seeds, band from the lowest to the highest
    seed), and Gaussians against views per step at the longest run, one line per table."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(16, 4.2))
    labels = args.labels or [Path(t).parent.name for t in args.tables]
    for i, (path, label) in enumerate(zip(args.tables, labels)):
        with open(path) as f:
            rows = [r for r in csv.DictReader(f) if r["overrides"] == "{}"]
        if args.seeds is not None:  # the same seeds at every point, so that the means compare
            rows = [r for r in rows if int(r["seed"]) in args.seeds]
        commit = rows[0]["commit"] if rows else "?"
        for ax, value in ((axes[0], "psnr"), (axes[1], "gaussians")):
            d = _by(rows, "steps", value, views=1)
            if not d:
                continue
            x = list(d)
            mean = [sum(v) / len(v) for v in d.values()]
            lo, hi = min(len(v) for v in d.values()), max(len(v) for v in d.values())
            seeds = f"{lo}" if lo == hi else f"{lo}-{hi}"
            ax.plot(x, mean, "o-", ms=3, color=f"C{i}", label=f"{label} ({commit}), mean of {seeds} seeds")
            ax.fill_between(x, [min(v) for v in d.values()], [max(v) for v in d.values()], color=f"C{i}", alpha=0.15)
        longest = max((int(r["steps"]) for r in rows), default=0)
        d = _by(rows, "views", "gaussians", steps=longest)
        if d:
            axes[2].plot(list(d), [sum(v) / len(v) for v in d.values()], "o-", color=f"C{i}",
                         label=f"{label}, {longest} steps")  # fmt: skip
            for v, ns in d.items():
                axes[2].scatter([v] * len(ns), ns, s=8, color=f"C{i}", alpha=0.5)
    for x in (400, 800, 1200, 1600):
        for ax in axes[:2]:
            ax.axvline(x, color="0.85", lw=0.8, zorder=0)
    axes[0].set(xlabel="--steps", ylabel="GT PSNR (dB)", title="PSNR against the run's length (1 view per step)")
    axes[1].set(xlabel="--steps", ylabel="Gaussians", title="Gaussians against the run's length")
    axes[2].set(xlabel="--views-per-step", ylabel="Gaussians", title="Gaussians against views per step")
    axes[2].set_xticks([1, 2, 4])
    axes[2].set_ylim(bottom=0)
    for ax in axes:
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(args.out, dpi=100)
    print(f"wrote {args.out}")


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="train and score the points not yet in OUT/study.csv")
    r.add_argument("--out", required=True)
    r.add_argument("--steps", nargs="+", default=["2000"], help="step counts, or ranges a:b:c (inclusive)")
    r.add_argument("--views", nargs="+", type=int, default=[1])
    r.add_argument("--prompt", default="a yellow duck")
    r.add_argument("--preset", default="gd")
    r.add_argument("--seeds", nargs="+", type=int, default=[0])
    r.add_argument("--set", nargs="*", default=[], help="config overrides key=JSON ('densify.start=150')")
    p = sub.add_parser("plot", help="the study's figure from one or more study.csv")
    p.add_argument("tables", nargs="+")
    p.add_argument("--labels", nargs="*")
    p.add_argument("--seeds", nargs="+", type=int, default=None, help="plot only these seeds (default: all)")
    p.add_argument("--out", required=True)
    args = ap.parse_args(argv)
    {"run": run, "plot": plot}[args.cmd](args)


if __name__ == "__main__":
    sys.exit(main())
