"""How many steps of screen-space statistics a densification needs, and how much one grows
(docs/training.md, "Short runs"): the measurements behind ``DensifyConfig.min_every`` and
``DensifyConfig.max_growth``.

    python scripts/study_densify_window.py window --out docs/results/densify_window
    python scripts/study_densify_window.py events --out docs/results/densify_window
    python scripts/study_densify_window.py plot docs/results/short_runs/before.csv \
        docs/results/short_runs/after.csv --out docs/figures/short_runs.png

``window``: the duck (gd, the default config of a 2000-step run) trained to step S with its
schedule, then on for 200 steps with densification held off while each step's statistic (the
norm of the screen-space gradient of every Gaussian's mean, and whether it was seen) is kept.
For a window of k steps the Gaussians whose mean statistic over the window exceeds the
threshold are the ones a densification would grow; each window is compared with the 200-step
reading (the share that grows, and the Jaccard overlap of the two sets), over every
non-overlapping window of k steps in the 200. ``events``: every densification of whole runs of
several lengths, with the Gaussians before it and the clones and splits it adds.

Each row records the commit (``core.provenance.code_commit``) and the time.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

from gdbench.core.provenance import code_commit, utc_now

WINDOWS = (1, 2, 3, 5, 7, 10, 15, 20, 25, 30, 40, 50, 75, 100, 200)
HOLD = 200


def _context(steps: int, seed: int, views: int, out: Path, **overrides):
    from gdbench.train.config import preset
    from gdbench.train.trainer import init_state, make_context

    cfg = preset(
        "gd", prompt="a yellow duck", steps=steps, seed=seed, views_per_step=views, out=out, progress=False, **overrides
    )
    ctx = make_context(cfg)
    return ctx, init_state(ctx)


class _Recorder:
    """A densification strategy that never densifies and keeps each step's statistic."""

    def __init__(self, inner):
        self.inner = inner
        self.norms: list = []
        self.seen: list = []

    def collects(self, step: int) -> bool:
        return True

    def accumulate(self, state, means2d, visible, width, height):
        new = self.inner.accumulate(self.inner.init_state(means2d.shape[1]), means2d, visible, width, height)
        self.norms.append(new.grad2d)
        self.seen.append(new.count)
        return state

    def step(self, params, optimizer, state, step, *, generator):
        return state, {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}


def window(args) -> None:
    import dataclasses

    import torch

    from gdbench.train.trainer import train_step

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        for start in args.at:
            for views in args.views:
                ctx, state = _context(2000, seed, views, out / "scratch")
                while state.step < start:
                    train_step(state, ctx)
                rec = _Recorder(ctx.strategy)
                ctx = dataclasses.replace(ctx, strategy=rec)
                for _ in range(HOLD):
                    train_step(state, ctx)
                norms, seen = torch.stack(rec.norms), torch.stack(rec.seen)  # [HOLD, N]
                thr = ctx.cfg.densify.grad_threshold

                def hot(lo: int, hi: int, norms=norms, seen=seen, thr=thr) -> tuple:
                    c = seen[lo:hi].sum(0)
                    avg = norms[lo:hi].sum(0) / c.clamp_min(1)
                    return avg > thr, c > 0

                ref, _ = hot(0, HOLD)
                for k in WINDOWS:
                    for lo in range(0, HOLD - k + 1, k):
                        h, s = hot(lo, lo + k)
                        inter, union = int((h & ref).sum()), int((h | ref).sum())
                        rows.append(
                            {
                                "seed": seed,
                                "at_step": start,
                                "views": views,
                                "window": k,
                                "offset": lo,
                                "gaussians": int(norms.shape[1]),
                                "seen": int(s.sum()),
                                "grow": int(h.sum()),
                                "grow_share": round(int(h.sum()) / norms.shape[1], 5),
                                "ref_grow": int(ref.sum()),
                                "jaccard": round(inter / union, 4) if union else 1.0,
                            }
                        )
                print(f"window: seed {seed}, step {start}, {views} views: {norms.shape[1]} Gaussians", flush=True)
    _write(out / "window.csv", rows)
    _summary(rows, out / "window_summary.csv")


def _summary(rows: list[dict], path: Path) -> None:
    from collections import defaultdict
    from statistics import mean

    by = defaultdict(list)
    for r in rows:
        by[(r["views"], r["window"])].append(r)
    out = []
    for (views, k), rs in sorted(by.items()):
        share = mean(r["grow_share"] for r in rs)
        ref = mean(r["ref_grow"] / r["gaussians"] for r in rs)
        out.append(
            {
                "views": views,
                "window": k,
                "windows": len(rs),
                "grow_share": round(share, 4),
                "ref_share": round(ref, 4),
                "ratio": round(share / ref, 3) if ref else float("nan"),
                "jaccard": round(mean(r["jaccard"] for r in rs), 3),
            }
        )
        print(" ".join(f"{k_}={v}" for k_, v in out[-1].items()), flush=True)
    _write(path, out)


class _Logger:
    """A densification strategy that densifies as ``inner`` does and logs every densification."""

    def __init__(self, inner, rows: list, **key):
        self.inner, self.rows, self.key = inner, rows, key

    def __getattr__(self, name):
        return getattr(self.inner, name)

    def step(self, params, optimizer, st, step, *, generator):
        n = int(params["means"].shape[0])
        st, info = self.inner.step(params, optimizer, st, step, generator=generator)
        if self.inner.schedule.grows(step):
            grown = info["cloned"] + info["split"]
            self.rows.append(
                self.key
                | {"step": step, "before": n, "cloned": info["cloned"], "split": info["split"]}
                | {"pruned": info["pruned"], "after": int(params["means"].shape[0]), "growth": round(grown / n, 4)}
            )
        return st, info


def events(args) -> None:
    import dataclasses

    from gdbench.train.trainer import train_step

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows = []
    for seed in args.seeds:
        for steps in args.steps:
            ctx, state = _context(steps, seed, 1, out / "scratch")
            inner = ctx.strategy

            ctx = dataclasses.replace(ctx, strategy=_Logger(inner, rows, seed=seed, steps=steps))
            while state.step < steps:
                train_step(state, ctx)
            grown = [r for r in rows if r["seed"] == seed and r["steps"] == steps]
            top = max((r["growth"] for r in grown), default=0.0)
            print(f"events: seed {seed}, {steps} steps: {len(grown)} events, largest growth {top:.3f}", flush=True)
    _write(out / "events.csv", rows)


def plot(args) -> None:
    """GT PSNR, Gaussians and the run's wall time against --steps (log axis) from
    ``study_schedule.py`` tables, before and after: each seed a dot, the mean a line."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    panels = [("psnr", "GT PSNR (dB)"), ("gaussians", "Gaussians"), ("train_s", "run + scoring, s (wall)")]
    for path, colour in zip((args.before, args.after), ("tab:blue", "tab:orange")):
        with open(path) as f:
            rows = [r for r in csv.DictReader(f) if r["views"] == "1" and r["overrides"] == "{}"]
        steps = sorted({int(r["steps"]) for r in rows})
        label = f"{Path(path).stem} ({rows[0]['commit']})"
        for ax, (key, title) in zip(axes, panels):
            pts = [(int(r["steps"]), float(r[key])) for r in rows]
            ax.scatter(*zip(*pts), s=10, color=colour, alpha=0.5)
            means = [sum(v for s_, v in pts if s_ == s) / sum(1 for s_, _ in pts if s_ == s) for s in steps]
            ax.plot(steps, means, color=colour, label=label)
            ax.set_xscale("log")
            ax.set_xlabel("--steps")
            ax.set_title(title)
            ax.grid(alpha=0.3)
    axes[0].legend(fontsize=8)
    fig.suptitle("The duck (gd), seeds 0-2, before and after the densification floor and cap", fontsize=10)
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"-> {args.out}")


def _write(path: Path, rows: list[dict]) -> None:
    stamp = {"commit": code_commit(), "utc": utc_now()}
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, [*rows[0], *stamp])
        w.writeheader()
        for r in rows:
            w.writerow(r | stamp)
    print(f"-> {path}")


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    w = sub.add_parser("window", help="hot-set agreement against the statistic's window")
    w.add_argument("--out", required=True)
    w.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    w.add_argument("--at", nargs="+", type=int, default=[400, 1000])
    w.add_argument("--views", nargs="+", type=int, default=[1, 4])
    w.set_defaults(fn=window)
    e = sub.add_parser("events", help="every densification of whole runs")
    e.add_argument("--out", required=True)
    e.add_argument("--seeds", nargs="+", type=int, default=[0, 1, 2])
    e.add_argument("--steps", nargs="+", type=int, default=[100, 300, 1000, 2000, 5000])
    e.set_defaults(fn=events)
    q = sub.add_parser("plot", help="PSNR, Gaussians and time against --steps, before and after")
    q.add_argument("before")
    q.add_argument("after")
    q.add_argument("--out", required=True)
    q.set_defaults(fn=plot)
    args = p.parse_args(argv)
    args.fn(args)


if __name__ == "__main__":
    main()
