"""``gdbench score RUN``: all scores of a run folder, written to its ``scores.json``.

- ground truth (empirical-prior runs): PSNR/SSIM against the procedural asset at 12 held-out
  poses after the best azimuth alignment (``gt.py``);
- COLMAP consistency (``colmap_consistency.py``): registration rate, Var(theta) of adjacent
  relative-rotation angles (the headline), translation-direction error.

Scores are tied to the scene they measured: ``scores.json`` records the SHA-256 of
``scene.ply`` (and the run id), and blocks measured on another scene are dropped, never shown
beside new ones. A broken ``run.json`` or ``scores.json`` is reported (naming the file) before
any scoring starts.
"""

from __future__ import annotations

import time
from pathlib import Path

from ..io import read_json, sha256_file, write_json
from ..scene import GaussianScene


def previous_scores(run: Path, scene_sha: str) -> dict:
    """The blocks of ``run/scores.json`` that belong to the scene with hash ``scene_sha``."""
    path = run / "scores.json"
    if not path.is_file():
        return {}
    old = read_json(path, what="scores.json")
    if old.get("scene_sha256") != scene_sha:
        return {}  # measured on another scene (or before scores were tied to scenes): stale
    return old


def score_run(run: str | Path, *, gt: bool = True, colmap: bool = True, views: int = 100, size: int = 256) -> dict:
    """Scores of a finished run folder into its scores.json; ``gt`` adds the ground-truth blocks
    (PSNR/SSIM, and the view metrics: multi-face rate, instance consistency, floaters)."""
    run = Path(run)
    if not run.is_dir():
        raise FileNotFoundError(f"run: no run folder at {run}")
    ply = run / "scene.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"run: no scene.ply in {run} (is the run finished?)")
    info = read_json(run / "run.json", what="run.json") if (run / "run.json").is_file() else {}
    scene_sha = sha256_file(ply)
    previous = previous_scores(run, scene_sha)  # a broken scores.json fails here, before the work
    scene = GaussianScene.load_ply(ply)
    out: dict = {
        "run": str(run),
        "run_id": info.get("run_id"),
        "scene_sha256": scene_sha,
        "gaussians": len(scene),
        "caption": info.get("caption"),
    }
    t0 = time.perf_counter()
    config = info.get("config", {})
    bg = tuple(float(c) for c in config.get("background", (1.0, 1.0, 1.0)))  # the run's own background
    if gt and info.get("caption"):
        from .gt import score_against_asset
        from .views import score_scene as view_scores

        variants = int(config.get("variants", 1))
        out["views"] = view_scores(scene, info["caption"], variants=variants, background=bg).as_dict()
        v = out["views"]["majority_variant"]  # the instance the run converged to is its ground truth
        s = score_against_asset(scene, info["caption"], variant=v, background=bg)
        out["gt"] = {
            "psnr": s.psnr,
            "ssim": s.ssim,
            "offset_deg": s.offset_deg,
            "psnr_unaligned": s.psnr_unaligned,
            "variant": v,
            "background": list(bg),
        }
    if colmap:
        from .colmap_consistency import score_scene

        out["colmap"] = score_scene(scene, views=views, size=size, background=bg).as_dict()
    out["seconds"] = time.perf_counter() - t0
    write_json(previous | out, run / "scores.json")
    return previous | out


def report(s: dict) -> str:
    """The lines ``gdbench score`` prints."""
    lines = [f"gdbench score: {s['run']} ({s['gaussians']} Gaussians) -> {Path(s['run']) / 'scores.json'}"]
    if "gt" in s:
        g = s["gt"]
        lines.append(f"  GT: PSNR {g['psnr']:.2f} dB, SSIM {g['ssim']:.3f} (offset {g['offset_deg']:.0f} deg)")
    if "views" in s:
        v = s["views"]
        lines.append(
            f"  views: multi-face {v['multi_face_rate']:.2f}, front share {v['front_share']:.2f}, "
            f"instance consistency {v['instance_consistency']:.2f}, floaters {v['floaters']:.3f}"
        )
    if "colmap" in s:
        c = s["colmap"]
        lines.append(
            f"  COLMAP: registered {c['registration_rate']:.2f}, Var(theta) {c['var_theta_deg2']:.4g} deg^2, "
            f"failure rate {c.get('failure_rate', float('nan')):.2f}, "
            f"translation-direction error {c['translation_dir_err_deg']:.3g} deg"
        )
    return "\n".join(lines)
