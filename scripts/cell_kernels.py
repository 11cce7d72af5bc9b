"""A scored cell's time inside the renderer's C++ kernels (issue 32; docs/log/2026-11-26_cell_cost.md, "The
step's floor"): the bm_cell cell (1000 gd steps on "a yellow duck", scored without COLMAP) run in
this process ``--rounds`` times, each from an empty zoom-level cache, with each training step's
time inside the kernels (``bench.bm_train.kernels_per_step``). Writes one CSV row per round and
kernel, with the commit and the machine's matrix product before and after.

    .venv/bin/python scripts/cell_kernels.py --out docs/results/cell_kernels.csv
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def main(argv: list[str] | None = None) -> int:
    from gdbench.bench.bm_train import kernels_per_step
    from gdbench.bench.common import environment, write_csv, write_json
    from gdbench.bench.roofline import peak_gflops
    from gdbench.experiments.sweep import CellSpec, run_cell
    from gdbench.priors.empirical import clear_level_cache

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/cell_kernels.csv"))
    ap.add_argument("--rounds", type=int, default=2, help="cells to run, one after the other (default 2)")
    ap.add_argument("--steps", type=int, default=1000, help="training steps of the cell (default 1000)")
    args = ap.parse_args(argv)
    if args.rounds < 1 or args.steps < 1:
        ap.error("--rounds and --steps: expected at least 1")
    rows = []
    before = peak_gflops()
    for r in range(args.rounds):
        work = Path(tempfile.mkdtemp(prefix="cell_kernels_"))
        try:
            clear_level_cache()
            spec = CellSpec("a yellow duck", "gd", 0, args.steps, str(work), colmap=False)
            with kernels_per_step() as (per, inside):
                t0 = time.perf_counter()
                row = run_cell(spec)
                cell_s = time.perf_counter() - t0
        finally:
            shutil.rmtree(work, ignore_errors=True)
        if per is None:
            raise SystemExit("cell_kernels: the C++ extension is not available")
        base = {"round": r + 1, "cell_s": cell_s, "train_steps_s": row["train_time_s"], "kernels_s": sum(inside),
                "median_step_in_kernels_s": statistics.median(inside)}  # fmt: skip
        print(f"round {r + 1}: cell {cell_s:.2f} s, steps {row['train_time_s']:.2f} s, of which in the kernels "
              f"{sum(inside):.2f} s (median {1e3 * statistics.median(inside):.2f} ms a step)")  # fmt: skip
        for name, (seconds, calls) in sorted(per.items(), key=lambda kv: -kv[1][0]):
            if calls:
                rows.append(base | {"kernel": name, "kernel_s": seconds, "calls": calls})
    after = peak_gflops()
    print(f"machine: float32 matrix product {before:.0f} GFLOP/s before, {after:.0f} after")
    for r in rows:
        r |= {"gflops_before": before, "gflops_after": after}
    write_csv(rows, args.out)
    write_json({"environment": environment(), "rows": rows}, args.out.with_name(args.out.stem + "_summary.json"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
