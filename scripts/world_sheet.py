"""The world's objects from the front, the side and the back (docs/figures/world_sheet.png), and
how different each one's back is from its front (docs/results/world/front_back.csv).

    python scripts/world_sheet.py --out docs

Each object (``assets.families.WORLD``) is rendered with pyrender as the banks are (elevation 15,
radius 1, fovy 50, 96 px) at azimuth 0 (front), 10, 90 (side) and 180 (back). ``front_back`` is the
mean absolute difference between the front and back images, ``front_10`` the same between the
front and the view 10 degrees round; their ratio says how much more the back differs from the
front than a small turn does. An object symmetric front to back shows at 180 degrees the mirror
image of its front (the mirror x -> -x takes one camera to the other and flips the image), so the
back is also compared with the front mirrored left-right (``front_back_mirrored``, and its
``ratio_mirrored`` to ``front_10``): near 0 for such an object, whatever its silhouette. Whole
images weigh silhouettes, and an object seen end-on (a car, a cat) changes its silhouette more
in 10 degrees than between front and back; so the test that counts is ``front_part_ratio``, as
the Janus metric reads a view (``metrics.views.front_part_ratio``): over the pixels where the
front view shows its marked front parts (``shapes.front``), the mean squared error between the
back view and the front view, divided by that between the view 10 degrees round and the front
view, both box-filtered over 4 px. Above 1: the back does not show what the front shows there.
"""

from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from gdbench.core.provenance import code_commit, utc_now


def views(mesh, azimuths, size: int = 96) -> np.ndarray:
    import torch

    from gdbench.core.camera import SphericalPoses
    from renderers.pyrender_points.mesh import render_mesh

    az = torch.tensor(azimuths, dtype=torch.float64)
    poses = SphericalPoses(az, torch.full_like(az, 15.0), torch.ones_like(az), torch.full_like(az, 50.0))
    pose_gl, K = poses.cameras(size, size).to_opengl()
    rgb, _, _ = render_mesh(mesh, pose_gl.double().numpy(), K.double().numpy(), size, size)
    return rgb


def front_mask(mesh, size: int = 96) -> np.ndarray:
    """[H, W] bool: where the front view (azimuth 0, as ``views``) shows the mesh's marked front parts."""
    import torch

    from gdbench.core.camera import SphericalPoses
    from gdbench.metrics.views import part_masks

    one = torch.ones(1, dtype=torch.float64)
    return part_masks(mesh, SphericalPoses(0 * one, 15 * one, one, 50 * one), size)[0]


def _box(img: np.ndarray, k: int = 4) -> np.ndarray:
    from scipy.ndimage import uniform_filter

    return uniform_filter(img, size=(k, k, 1), mode="nearest")


def main(argv: list[str] | None = None) -> None:
    from PIL import Image, ImageDraw

    from gdbench.assets.families import WORLD

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", default="docs")
    args = p.parse_args(argv)
    out = Path(args.out)
    (out / "figures").mkdir(parents=True, exist_ok=True)
    (out / "results" / "world").mkdir(parents=True, exist_ok=True)
    stamp = {"commit": code_commit(), "utc": utc_now()}  # before any write
    rows, tiles = [], []
    for caption, spec in WORLD.items():
        mesh = spec.build()
        img = views(mesh, [0.0, 10.0, 90.0, 180.0])
        mask = front_mask(mesh)
        b = [_box(im) for im in img]
        mse = lambda k, b=b, mask=mask: float(((b[k] - b[0]) ** 2)[mask].mean())  # noqa: E731
        front_back = float(np.abs(img[0] - img[3]).mean())
        mirrored = float(np.abs(img[0] - img[3][:, ::-1]).mean())
        front_10 = float(np.abs(img[0] - img[1]).mean())
        rows.append(
            {
                "caption": caption,
                "kind": spec.kind,
                "front_back": round(front_back, 4),
                "front_back_mirrored": round(mirrored, 4),
                "front_10": round(front_10, 4),
                "ratio": round(front_back / max(front_10, 1e-9), 2),
                "ratio_mirrored": round(mirrored / max(front_10, 1e-9), 2),
                "front_pixels": int(mask.sum()),
                "front_part_ratio": round(mse(3) / max(mse(1), 1e-12), 2),
            }
        )
        tiles.append((caption, np.concatenate([img[0], img[2], img[3]], 1)))
        print(" ".join(f"{k}={v}" for k, v in rows[-1].items()), flush=True)
    cols, h, w = 4, tiles[0][1].shape[0] + 14, tiles[0][1].shape[1]
    sheet = Image.new("RGB", (cols * w, -(-len(tiles) // cols) * h), "white")
    draw = ImageDraw.Draw(sheet)
    for i, (caption, tile) in enumerate(tiles):
        x, y = (i % cols) * w, (i // cols) * h
        sheet.paste(Image.fromarray((np.clip(tile, 0, 1) * 255).astype(np.uint8)), (x, y + 14))
        draw.text((x + 4, y + 1), caption, fill=(0, 0, 0))
    sheet.save(out / "figures" / "world_sheet.png")
    with open(out / "results" / "world" / "front_back.csv", "w", newline="") as f:
        wr = csv.DictWriter(f, [*rows[0], *stamp])
        wr.writeheader()
        wr.writerows(r | stamp for r in rows)
    print(f"-> {out / 'figures' / 'world_sheet.png'}")


if __name__ == "__main__":
    main()
