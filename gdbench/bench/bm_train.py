"""Training-side figures: the empirical denoiser's time (target: at most 5 ms for a 64x64x3
image against a 360-image bank) and the default generation's wall time (target: at most
10 minutes on the 2-core machine), written to CSV/JSON.

    python -m gdbench.bench.bm_train --out bench_results/train.csv [--skip-run]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from .common import environment, timeit, write_csv, write_json

TARGET_DENOISE_S = 0.005
TARGET_RUN_S = 600.0


def denoise_time(view_mode: str = "window") -> dict:
    from ..priors.empirical import EmpiricalPrior

    prior = EmpiricalPrior(view_mode=view_mode)
    cond = prior.encode("a yellow duck")
    g = torch.Generator().manual_seed(0)
    x = torch.rand(1, 64, 64, 3, generator=g) * 2 - 1
    t = timeit(lambda: prior.denoise(x, torch.tensor([1.0]), cond, azimuth=torch.tensor([30.0])), budget_s=2.0)
    return {
        "what": f"denoise 64x64x3, bank of {cond.images.shape[0]}, view_mode={view_mode}",
        "seconds": t["median_s"],
        "target_s": TARGET_DENOISE_S,
        "met": t["median_s"] <= TARGET_DENOISE_S,
    }


def default_run_time(out: Path) -> dict:
    from ..train.config import preset
    from ..train.run import train

    t0 = time.perf_counter()
    r = train(preset("gd", out=out, progress=False), resume=False)
    s = time.perf_counter() - t0
    return {
        "what": "gdbench generate 'a yellow duck' --preset gd (2000 steps, 64 px, outputs included)",
        "seconds": s,
        "target_s": TARGET_RUN_S,
        "met": s <= TARGET_RUN_S,
        "gaussians": len(r.state.scene()),
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/train.csv"))
    ap.add_argument("--skip-run", action="store_true", help="only time the denoiser")
    args = ap.parse_args(argv)
    rows = [denoise_time("window"), denoise_time("none")]
    if not args.skip_run:
        rows.append(default_run_time(args.out.parent / "bm_train_run"))
    for r in rows:
        print(f"{r['what']}: {r['seconds']:.4g} s (target <= {r['target_s']} s) -> {'met' if r['met'] else 'NOT met'}")
    write_csv(rows, args.out)
    write_json({"environment": environment(), "rows": rows}, args.out.with_name(args.out.stem + "_summary.json"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
