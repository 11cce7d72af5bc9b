"""What watching a run costs it: ``generate --view`` (``app.live_view.LiveView``) against the same
run unwatched, as an in-process A/B. The duck (gd, the default config) is trained for ``warmup``
steps, then in alternating blocks of ``block`` steps with and without the live view (the same
run, so both see the same scene sizes and the machine's phase moves both alike). The figure is
the mean step (the sends are spikes: the mean, not the median, is what the run pays), watched
over unwatched, per ``--view-every``; target: at most 1.05 at the default (100 steps). No
browser is connected (a browser's socket writes are not measured). Writes CSV and JSON with the
machine's phase.

    python scripts/bench_live_view.py --out bench_results/live_view.csv
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

TARGET_RATIO = 1.05


def measure(every: int, *, warmup: int = 100, block: int = 50, pairs: int = 16, out: Path) -> dict:
    from gdbench.app.live_view import LiveView
    from gdbench.train.config import preset
    from gdbench.train.trainer import init_state, make_context, train_step

    cfg = preset("gd", prompt="a yellow duck", steps=2000, out=out / "scratch", progress=False)
    ctx = make_context(cfg)
    state = init_state(ctx)
    for _ in range(warmup):
        train_step(state, ctx)
    live = LiveView(every=every, port=8093, verbose=False)
    live(state)  # the server starts outside the timed blocks
    times = {"watched": [], "unwatched": []}
    try:
        for _ in range(pairs):
            for arm in ("unwatched", "watched"):
                for _ in range(block):
                    t0 = time.perf_counter()
                    train_step(state, ctx)
                    if arm == "watched":
                        live(state)
                    times[arm].append(time.perf_counter() - t0)
    finally:
        live.close()
    mean = {k: statistics.fmean(v) for k, v in times.items()}
    return {
        "view_every": every,
        "steps_per_arm": len(times["watched"]),
        "mean_unwatched_ms": 1e3 * mean["unwatched"],
        "mean_watched_ms": 1e3 * mean["watched"],
        "median_unwatched_ms": 1e3 * statistics.median(times["unwatched"]),
        "median_watched_ms": 1e3 * statistics.median(times["watched"]),
        "ratio": mean["watched"] / mean["unwatched"],
        "sends": live.updates,
        "gaussians": int(state.params["means"].shape[0]),
        "target_ratio": TARGET_RATIO if every == 100 else float("nan"),
    }


def main(argv: list[str] | None = None) -> None:
    from gdbench.bench.common import environment
    from gdbench.bench.roofline import peak_gflops
    from gdbench.core.io import write_csv, write_json

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="bench_results/live_view.csv")
    p.add_argument("--every", nargs="+", type=int, default=[100, 10])
    args = p.parse_args(argv)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    before = peak_gflops()
    rows = [measure(e, out=out.parent) for e in args.every]
    after = peak_gflops()
    env = environment() | {"gflops_before": before, "gflops_after": after}
    for r in rows:
        r |= {"commit": env["commit"], "gflops_before": before, "gflops_after": after}
        print(
            f"view every {r['view_every']:4d} steps: mean step {r['mean_watched_ms']:.2f} ms watched, "
            f"{r['mean_unwatched_ms']:.2f} unwatched: x{r['ratio']:.3f} "
            f"({r['sends']} sends, {r['gaussians']} Gaussians)"
        )
    print(f"machine phase: float32 matmul {before:.0f} GFLOP/s before, {after:.0f} after")
    write_csv(rows, out)
    write_json({"environment": env, "rows": rows}, out.with_suffix(".json"))
    print(f"-> {out}")


if __name__ == "__main__":
    main()
