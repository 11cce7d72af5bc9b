"""Cost of the Janus judge: one run's turntable judged (36 frames rendered from the scene at 128 px,
cropped, read by the eye, the outline read, the head), and a label sheet's six views, each the
median of repeats, with the machine's phase (a matrix-multiply GFLOP/s before and after) beside
the absolute times. The target (the judge issue): a run's turntable in at most 2 s on the 2-core
CPU machine, measured with the machine otherwise idle.

    python -m gdbench.bench.bm_judge --out bench_results/judge.csv
"""

from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import numpy as np

from gdbench.bench.common import environment, write_csv, write_json

TARGET_RUN_S = 2.0


def _median_time(fn, repeats: int) -> float:
    fn()  # warm-up: the judge's weights, the renderer's kernels
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times)


def main(argv=None) -> int:
    from gdbench.bench.roofline import peak_gflops
    from gdbench.metrics.failures3d import failure_scene
    from gdbench.metrics.judge.judge import load_judge, turntable_frames

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/judge.csv"))
    ap.add_argument("--caption", default="a yellow duck")
    ap.add_argument("--repeats", type=int, default=7)
    args = ap.parse_args(argv)
    before = peak_gflops()
    judge = load_judge()
    scene = failure_scene(args.caption, "turned-90")  # a whole result, turned: a run's scene stands in
    frames = turntable_frames(scene)
    six = frames[::6]
    rows = [
        {"case": "run turntable (render + judge)", "seconds": _median_time(lambda: judge.scene(scene, args.caption),
                                                                            args.repeats)},
        {"case": "36 frames rendered", "seconds": _median_time(lambda: turntable_frames(scene), args.repeats)},
        {"case": "36 frames judged", "seconds": _median_time(
            lambda: judge.views(frames, np.arange(36) * 10.0, args.caption), args.repeats)},
        {"case": "six sheet views judged", "seconds": _median_time(
            lambda: judge.views(six, np.arange(6) * 60.0, args.caption), args.repeats)},
    ]  # fmt: skip
    after = peak_gflops()
    env = environment() | {"gflops_before": before, "gflops_after": after, "gaussians": len(scene),
                           "judge": judge.version}  # fmt: skip
    for r in rows:
        r |= {"gflops_before": round(before, 1), "gflops_after": round(after, 1), "commit": env["commit"]}
    write_csv(rows, args.out)
    run_s = rows[0]["seconds"]
    summary = {"rows": rows, "environment": env, "target_run_s": TARGET_RUN_S, "met": run_s <= TARGET_RUN_S}
    write_json(summary, args.out.with_suffix(".json"))
    for r in rows:
        print(f"{r['case']:32s} {r['seconds']:.3f} s")
    print(f"machine phase: {before:.0f} -> {after:.0f} GFLOP/s (matrix multiply); target run <= {TARGET_RUN_S} s: "
          f"{'met' if summary['met'] else 'not met'}")  # fmt: skip
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
