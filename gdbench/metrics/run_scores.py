"""``gdbench score RUN``: all scores of a run folder, written to its ``scores.json``.

- ground truth (empirical-prior runs): PSNR/SSIM against the procedural asset at 12 held-out
  poses after the best azimuth alignment (``gt.py``);
- COLMAP consistency (``colmap_consistency.py``): registration rate, Var(theta) of adjacent
  relative-rotation angles (the headline), translation-direction error.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

from ..scene import GaussianScene


def score_run(run: str | Path, *, gt: bool = True, colmap: bool = True, views: int = 100, size: int = 256) -> dict:
    from ..train.outputs import write_json_atomic

    run = Path(run)
    ply = run / "scene.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"run: no scene.ply in {run} (is the run finished?)")
    info = json.loads((run / "run.json").read_text()) if (run / "run.json").is_file() else {}
    scene = GaussianScene.load_ply(ply)
    out: dict = {"run": str(run), "gaussians": len(scene), "caption": info.get("caption")}
    t0 = time.perf_counter()
    if gt and info.get("caption"):
        from .gt import score_against_asset

        s = score_against_asset(scene, info["caption"])
        out["gt"] = {"psnr": s.psnr, "ssim": s.ssim, "offset_deg": s.offset_deg, "psnr_unaligned": s.psnr_unaligned}
    if colmap:
        from .colmap_consistency import score_scene

        out["colmap"] = score_scene(scene, views=views, size=size).as_dict()
    out["seconds"] = time.perf_counter() - t0
    previous = json.loads((run / "scores.json").read_text()) if (run / "scores.json").is_file() else {}
    write_json_atomic(previous | out, run / "scores.json")
    return out
