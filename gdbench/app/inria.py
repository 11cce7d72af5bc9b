"""An Inria 3DGS model folder of a scene (``gdbench export --format inria``; docs/export.md).

The folder the Inria code (graphdeco-inria/gaussian-splatting) writes after training, which its
``render.py -m FOLDER`` and the SIBR viewer (``SIBR_gaussianViewer_app -m FOLDER``) load:

- ``point_cloud/iteration_<N>/point_cloud.ply``: the scene in the Inria PLY layout at SH degree 3
  (Inria's loader wants all 45 ``f_rest_*``), N the run's steps (30000, Inria's last iteration,
  for a scene without a run), recording its up axis and run (``core.filetags``);
- ``cameras.json``: one entry per view as Inria's ``camera_to_JSON`` writes it: ``position``
  (the camera centre in the world) and ``rotation`` (camera-to-world, OpenCV axes: x right,
  y down, z forward, as rows of a 3x3 list), ``fx``, ``fy`` in pixels, ``width``, ``height``,
  ``img_name``, ``id``;
- ``cfg_args``: the ``Namespace(...)`` line Inria's ``get_combined_args`` evaluates, with
  ``source_path`` and ``model_path`` the folder itself and ``sh_degree=3``;
- the source data ``render.py`` reads its cameras from: a NeRF-synthetic ("Blender") scene,
  ``transforms_train.json`` (``camera_angle_x``; per frame ``file_path`` and the camera-to-world
  ``transform_matrix`` in OpenGL axes) with the views rendered as ``train/r_<k>.png`` (over the
  run's background, opaque), and an empty ``transforms_test.json``.

The views are the run's turntable (``turntable.RUN_TURNTABLE``) or, for a scene from elsewhere,
the same orbit about its bounds at the distance that frames it; scene and cameras are turned
together to ``up`` (default -y, the Inria / COLMAP convention), so each image is the scene seen
from its camera.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from gdbench.core.camera import Cameras
from gdbench.core.filetags import up_rotation
from gdbench.core.scene import GaussianScene

INRIA_ITERATION = 30000
"""The iteration of a scene without a run (the Inria code's last, the one its loader picks)."""

_CV_TO_GL = np.diag([1.0, -1.0, -1.0, 1.0])


def turned_cameras(cams: Cameras, rotation: torch.Tensor) -> Cameras:
    """``cams`` looking at the scene turned by ``rotation`` [3, 3] as they looked at it before:
    viewmat ``V diag(R^T, 1)``."""
    m = torch.eye(4, dtype=torch.float64)
    m[:3, :3] = rotation.double().T
    return Cameras((cams.viewmats.double() @ m).to(cams.viewmats.dtype), cams.Ks, cams.width, cams.height)


def inria_cameras_json(cams: Cameras) -> list[dict]:
    """Inria's ``cameras.json`` entries of ``cams`` (the module docstring)."""
    out = []
    for k in range(len(cams)):
        c2w = torch.linalg.inv(cams.viewmats[k].double()).numpy()
        K = cams.Ks[k].double().numpy()
        out.append(
            {
                "id": k,
                "img_name": f"r_{k}",
                "width": cams.width,
                "height": cams.height,
                "position": c2w[:3, 3].tolist(),
                "rotation": c2w[:3, :3].tolist(),
                "fy": float(K[1, 1]),
                "fx": float(K[0, 0]),
            }
        )
    return out


def write_inria_model(
    scene: GaussianScene,
    folder: str | Path,
    cams: Cameras,
    *,
    up: str = "-y",
    run: str | None = None,
    iteration: int | None = None,
    background=(1.0, 1.0, 1.0),
) -> Path:
    """Write the Inria model folder of ``scene`` (+Z up) seen from ``cams`` (module docstring);
    every file atomically; returns the folder."""
    import imageio.v3 as iio

    from gdbench.app.export import export_scene
    from gdbench.core.io import atomic_write
    from gdbench.core.turntable import render_views, to_uint8

    folder = Path(folder)
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"out (--out): {folder} is a file; --format inria writes a folder")
    if folder.is_dir() and any(folder.iterdir()):
        if not (folder / "cfg_args").is_file():
            raise ValueError(
                f"out (--out): {folder} holds files and is not an Inria model folder; pass a new or empty folder"
            )
        # a model folder written before: its files go, so no older iteration is left for Inria's
        # loader to pick (it takes the highest) and no frame of another view count stays
        import shutil

        for name in ("point_cloud", "train"):
            shutil.rmtree(folder / name, ignore_errors=True)
        for name in ("cameras.json", "cfg_args", "transforms_train.json", "transforms_test.json"):
            (folder / name).unlink(missing_ok=True)
    if len(set(np.asarray(cams.Ks[:, 0, 0]).round(6).tolist())) != 1 or cams.width != cams.height:
        raise ValueError("cams: the Blender source format has one field of view and square images for all views")
    iteration = INRIA_ITERATION if iteration is None else int(iteration)
    rotation = up_rotation(up)
    turned = turned_cameras(cams, rotation)
    ply = folder / "point_cloud" / f"iteration_{iteration}" / "point_cloud.ply"
    ply.parent.mkdir(parents=True, exist_ok=True)
    export_scene(scene, ply, fmt="ply", up=up, sh_degree=3, run=run)

    def write_text(path: Path, text: str) -> None:
        atomic_write(path, lambda f: f.write(text.encode()))

    write_text(folder / "cameras.json", json.dumps(inria_cameras_json(turned)))
    white = bool(np.allclose(background, 1.0))
    src = str(folder.resolve())
    write_text(
        folder / "cfg_args",
        f"Namespace(sh_degree=3, source_path={src!r}, model_path={src!r}, images='images', depths='', "
        f"resolution=-1, white_background={white}, train_test_exp=False, data_device='cuda', eval=False)",
    )
    fovx = 2 * math.atan(cams.width / (2 * float(cams.Ks[0, 0, 0])))
    frames = []
    images = folder / "train"
    images.mkdir(exist_ok=True)
    rgb = render_views(scene, cams, background=background)  # the scene as it is, from its own cameras
    for k in range(len(cams)):
        c2w = torch.linalg.inv(turned.viewmats[k].double()).numpy() @ _CV_TO_GL
        frames.append({"file_path": f"./train/r_{k}", "rotation": 0.0, "transform_matrix": c2w.tolist()})
        data = to_uint8(rgb[k : k + 1])[0]
        atomic_write(images / f"r_{k}.png", lambda f, data=data: iio.imwrite(f, data, extension=".png"))
    write_text(folder / "transforms_train.json", json.dumps({"camera_angle_x": fovx, "frames": frames}, indent=1))
    write_text(folder / "transforms_test.json", json.dumps({"camera_angle_x": fovx, "frames": []}, indent=1))
    return folder
