"""The renderer at scale: 1M Gaussians with SH degree 3 at 1920x1080, forward and
forward+backward, time and peak memory (each in its own process), written to CSV/JSON.
Targets: forward at most 1 s and peak memory at most 1.5 GB on the 2-core machine.

    python -m gdbench.bench.bm_scale --out bench_results/scale.csv
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
from pathlib import Path

import torch

from gdbench.bench.common import environment, peak_rss_mb, random_cloud, rss_mb, timeit, write_csv, write_json

TARGETS = {"fwd_s": 1.0, "peak_rss_mb": 1536.0}
CASE = {"n": 1_000_000, "width": 1920, "height": 1080, "sh_degree": 3}


def run(mode: str, n: int = CASE["n"], width: int = CASE["width"], height: int = CASE["height"]) -> dict:
    from gdbench.core.camera import SphericalPoses
    from renderers.splat import rasterize

    base = rss_mb()
    scene = random_cloud(n)
    g = torch.Generator().manual_seed(1)
    sh = torch.randn(n, 16, 3, generator=g) * 0.2
    cams = SphericalPoses.orbit(1, radius=1.5, elevation=20.0, fovy=50.0).cameras(width, height)
    args = dict(viewmats=cams.viewmats, Ks=cams.Ks, width=width, height=height, sh_degree=3, background=torch.ones(3))
    params = {k: scene[k] for k in ("means", "quats", "scales", "opacities")} | {"colors": sh}
    if mode == "fwd":

        def fn():
            with torch.no_grad():
                rasterize(**params, **args)
    else:
        leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}

        def fn():
            for v in leaves.values():
                v.grad = None
            out = rasterize(**leaves, **args)
            (out.rgb.sum() + out.alpha.sum()).backward()

    t = timeit(fn, warmup=1, min_repeats=3, budget_s=5.0)
    return {"mode": mode, **CASE, "n": n, "width": width, "height": height, **t, "peak_rss_mb": peak_rss_mb(),
            "start_rss_mb": base, "status": "ok"}  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/scale.csv"))
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        print(json.dumps(run(args.worker)))
        return 0
    rows = []
    for mode in ("fwd", "fwd+bwd"):
        proc = subprocess.run([sys.executable, "-m", "gdbench.bench.bm_scale", "--worker", mode], capture_output=True,
                              text=True)  # fmt: skip
        if proc.returncode == 0:
            rows.append(json.loads(proc.stdout.strip().splitlines()[-1]))
        else:
            rows.append({"mode": mode, **CASE, "status": "failed: " + (proc.stderr.strip().splitlines() or ["?"])[-1]})
    fwd = next((r for r in rows if r["mode"] == "fwd" and r["status"] == "ok"), None)
    targets = {}
    if fwd:
        targets["fwd_s"] = {"value": fwd["median_s"], "target": f"<= {TARGETS['fwd_s']}",
                            "met": fwd["median_s"] <= TARGETS["fwd_s"]}  # fmt: skip
        targets["peak_rss_mb"] = {"value": fwd["peak_rss_mb"], "target": f"<= {TARGETS['peak_rss_mb']}",
                                  "met": fwd["peak_rss_mb"] <= TARGETS["peak_rss_mb"]}  # fmt: skip
    write_csv(rows, args.out)
    write_json({"environment": environment(), "case": CASE, "targets": targets, "rows": rows},
               args.out.with_name(args.out.stem + "_summary.json"))  # fmt: skip
    for r in rows:
        if r["status"] == "ok":
            print(f"1M SH3 1920x1080 {r['mode']}: {r['median_s']:.3f} s, peak RSS {r['peak_rss_mb']:.0f} MB")
        else:
            print(f"1M SH3 1920x1080 {r['mode']}: {r['status']}")
    for k, v in targets.items():
        print(f"target {k}: {v['value']:.4g} (want {v['target']}) -> {'met' if v['met'] else 'NOT met'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
