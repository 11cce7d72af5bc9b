"""In-process A/B of the learned prior's guided epsilon: the eager module against the frozen
TorchScript graph the prior runs on the CPU (issue 56). Two trainers at the same seed (gd preset,
learned prior) step in alternating blocks, so the machine's phase moves both alike; after the
same steps their parameters must be equal bit for bit.

    python scripts/ab_learned_graph.py --out docs/results/learned_prior/ab_graph.csv
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # run from a checkout without the install


def main(argv: list[str] | None = None) -> int:
    from gdbench.bench.common import environment, write_csv, write_json
    from gdbench.bench.roofline import peak_gflops
    from gdbench.priors.learned.prior import _Epsilon
    from gdbench.train.config import preset
    from gdbench.train.trainer import init_state, make_context, train_step

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, required=True, help="the CSV to write (with a _summary.json beside it)")
    ap.add_argument("--blocks", type=int, default=8)
    ap.add_argument("--block", type=int, default=20)
    args = ap.parse_args(argv)
    runs = {}
    for name in ("eager", "graph"):
        ctx = make_context(preset("gd", prior="learned", out=Path(tempfile.mkdtemp()) / name, progress=False))
        if name == "eager":  # the eager module where the prior would trace its graph
            p = ctx.prior
            for guided in (True, False):
                for camera in (True, False):
                    scale = p.guidance_scale if guided else 1.0
                    p._graphs[guided, camera, scale] = _Epsilon(p.unet, p.abar, scale, camera)
        runs[name] = (ctx, init_state(ctx), [], [])
    before = peak_gflops()
    for _ in range(30):
        for ctx, state, *_ in runs.values():
            train_step(state, ctx)
    for _ in range(args.blocks):
        for ctx, state, steps, priors in runs.values():
            for _ in range(args.block):
                t0 = time.perf_counter()
                m = train_step(state, ctx)
                steps.append(time.perf_counter() - t0)
                priors.append(m["t_prior"])
    after = peak_gflops()
    kinds = {name: {type(m).__name__ for m in ctx.prior._graphs.values()} for name, (ctx, *_) in runs.items()}
    if kinds["eager"] != {"_Epsilon"} or "_Epsilon" in kinds["graph"]:
        raise SystemExit(f"the A/B did not run what it names: {kinds}")
    a, b = runs["eager"][1].params, runs["graph"][1].params
    same = all(torch.equal(a[k], b[k]) for k in a)
    rows = [{"module": name, "step_s": statistics.median(s), "prior_s": statistics.median(p), "steps": len(s),
             "bit_identical": same, "gflops_before": before, "gflops_after": after}
            for name, (_, _, s, p) in runs.items()]  # fmt: skip
    for r in rows:
        print(f"{r['module']}: step {1e3 * r['step_s']:.2f} ms, prior {1e3 * r['prior_s']:.2f} ms")
    print(f"parameters equal bit for bit: {same}; machine {before:.0f} -> {after:.0f} GFLOP/s")
    write_csv(rows, args.out)
    write_json({"environment": environment(), "rows": rows}, args.out.with_name(args.out.stem + "_summary.json"))
    return 0 if same else 1


if __name__ == "__main__":
    raise SystemExit(main())
