"""The mesh export's table in docs/export.md ("Meshes"): each asset's mesh by TSDF fusion
(``app.mesh.extract_mesh``, the defaults of ``gdbench export --format glb``) against the asset's
own mesh (``metrics.mesh_scores``), for two scenes per asset: Gaussians laid on the asset's
surface (the fusion's floor: what it loses when the Gaussians are exactly right) and the run
that ``gdbench generate "<asset>"`` gives at the defaults.

    python scripts/mesh_table.py --runs runs/defaults --out docs/results/mesh

``--runs`` holds one run folder per asset, named by its caption with underscores
(``a_yellow_duck``); they are made first when missing (``gdbench generate`` at the defaults).
Writes mesh.csv (with the commit and the time) and a figure of the meshes beside the assets.
"""

from __future__ import annotations

import argparse
import csv
import subprocess
import sys
import time
from pathlib import Path

from gdbench.core.provenance import code_commit, utc_now


def main(argv: list[str] | None = None) -> None:
    from gdbench.app.mesh import extract_mesh
    from gdbench.assets.library import ASSETS, build
    from gdbench.core.scene import GaussianScene
    from gdbench.metrics.mesh_scores import mesh_scores, surface_gaussians

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", required=True)
    p.add_argument("--out", required=True)
    args = p.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    rows, stamp = [], {"commit": code_commit()}
    for caption in ASSETS:
        run = Path(args.runs) / caption.replace(" ", "_")
        if not (run / "run.json").is_file():
            cmd = [sys.executable, "-m", "gdbench.app.cli", "generate", caption, "--out", str(run), "--no-progress"]
            subprocess.run(cmd, check=True)
        ref = build(caption)
        for kind, scene in (("on the surface", surface_gaussians(ref, 60000, seed=3)), ("default run", None)):
            scene = scene if scene is not None else GaussianScene.load_ply(run / "scene.ply")
            t0 = time.perf_counter()
            mesh = extract_mesh(scene)
            seconds = time.perf_counter() - t0
            s = mesh_scores(mesh, ref)
            row = {
                "asset": caption,
                "scene": kind,
                "gaussians": len(scene),
                "faces": len(mesh.faces),
                "chamfer": round(s.chamfer, 4),
                "normal_consistency": round(s.normal_consistency, 3),
                "turned_deg": s.turned_deg,
                "chamfer_unturned": round(s.chamfer_unturned, 4),
                "fuse_s": round(seconds, 1),
            }
            rows.append(row | stamp | {"utc": utc_now()})
            print(" ".join(f"{k}={v}" for k, v in row.items()), flush=True)
    with open(out / "mesh.csv", "w", newline="") as f:
        w = csv.DictWriter(f, list(rows[0]))
        w.writeheader()
        w.writerows(rows)
    print(f"-> {out / 'mesh.csv'}")


if __name__ == "__main__":
    main()
