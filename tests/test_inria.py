"""``gdbench export --format inria`` (gdbench.app.inria), read back the way the Inria code reads a
model folder: ``cfg_args`` evaluated as ``get_combined_args`` does, the PLY by Inria's
``GaussianModel.load_ply`` arithmetic (written out here with plyfile), the cameras by
``camera_to_JSON``'s and ``readCamerasFromTransforms``'s conventions (written out here). Oracle:
the images in the folder, rendered from the scene as it is, equal the Inria-side reading rendered
from the Inria-side cameras."""

from __future__ import annotations

import json
import math
from argparse import Namespace
from pathlib import Path

import numpy as np
import pytest
import torch

from gdbench.core.scene import GaussianScene


def _inria_load_ply(path: Path) -> GaussianScene:
    """Inria's ``GaussianModel.load_ply`` (sh_degree 3), to our scene's fields."""
    from plyfile import PlyData

    v = PlyData.read(str(path)).elements[0]
    xyz = np.stack([np.asarray(v[a]) for a in "xyz"], 1)
    dc = np.stack([np.asarray(v[f"f_dc_{i}"]) for i in range(3)], 1)[:, None, :]
    rest_names = sorted((p.name for p in v.properties if p.name.startswith("f_rest_")), key=lambda n: int(n[7:]))
    assert len(rest_names) == 3 * (3 + 1) ** 2 - 3  # the loader asserts all 45
    rest = np.stack([np.asarray(v[n]) for n in rest_names], 1).reshape(len(xyz), 3, 15).transpose(0, 2, 1)
    scales = np.stack([np.asarray(v[f"scale_{i}"]) for i in range(3)], 1)
    rots = np.stack([np.asarray(v[f"rot_{i}"]) for i in range(4)], 1)
    t = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return GaussianScene(t(xyz), t(rots), t(scales), t(np.asarray(v["opacity"])), t(np.concatenate([dc, rest], 1)))


def _inria_viewmats_from_cameras_json(entries: list[dict]) -> torch.Tensor:
    """``camera_to_JSON`` wrote position and rotation of inv(Rt): Rt = inv([rot | pos])."""
    out = []
    for e in entries:
        c2w = np.eye(4)
        c2w[:3, :3] = np.asarray(e["rotation"])
        c2w[:3, 3] = np.asarray(e["position"])
        out.append(np.linalg.inv(c2w))
    return torch.from_numpy(np.stack(out))


def _inria_viewmats_from_transforms(path: Path) -> tuple[torch.Tensor, float]:
    """``readCamerasFromTransforms``: c2w from Blender/OpenGL to COLMAP axes, w2c = inv(c2w)."""
    contents = json.loads(path.read_text())
    out = []
    for frame in contents["frames"]:
        c2w = np.array(frame["transform_matrix"])
        c2w[:3, 1:3] *= -1
        out.append(np.linalg.inv(c2w))
    return torch.from_numpy(np.stack(out)), contents["camera_angle_x"]


@pytest.fixture
def run_folder(tmp_path):
    from gdbench.core.builtin import demo_scene
    from gdbench.core.filetags import ply_comments
    from gdbench.core.io import sha256_file, write_json

    run = tmp_path / "run"
    run.mkdir()
    demo_scene(300, seed=4).save_ply(run / "scene.ply", comments=ply_comments("+z", "0123456789abcdef"))
    config = {"seed": 0, "resolution": 32, "turntable_frames": 6, "background": [1.0, 1.0, 1.0]}
    write_json(
        {"run_id": "0123456789abcdef", "config": config, "steps": 1234, "scene_sha256": sha256_file(run / "scene.ply")},
        run / "run.json",
    )
    return run


def test_the_model_folder_reads_back_with_inrias_conventions(run_folder):
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export
    from gdbench.core.camera import Cameras
    from gdbench.core.filetags import read_tags
    from gdbench.core.turntable import render_views

    r = main(Export(run_folder, format="inria"))
    folder = Path(r["path"])
    assert folder == run_folder / "inria.y_down" and r["up"] == "-y"
    cfg = eval(  # as Inria's get_combined_args reads it
        (folder / "cfg_args").read_text(), {"Namespace": Namespace}
    )
    assert cfg.sh_degree == 3 and Path(cfg.source_path) == folder.resolve() == Path(cfg.model_path)
    assert cfg.white_background is True
    ply = folder / "point_cloud" / "iteration_1234" / "point_cloud.ply"  # the run's steps
    scene = _inria_load_ply(ply)
    assert (read_tags(ply).up, read_tags(ply).run) == ("-y", "0123456789abcdef")
    entries = json.loads((folder / "cameras.json").read_text())
    assert len(entries) == 6 and {e["img_name"] for e in entries} == {f"r_{k}" for k in range(6)}
    V = _inria_viewmats_from_cameras_json(entries)
    V2, fovx = _inria_viewmats_from_transforms(folder / "transforms_train.json")
    torch.testing.assert_close(V, V2, atol=1e-9, rtol=0)  # render.py's cameras are the viewer's
    e = entries[0]
    assert e["fx"] == pytest.approx(e["width"] / (2 * math.tan(fovx / 2)))
    K = torch.tensor([[e["fx"], 0, e["width"] / 2], [0, e["fy"], e["height"] / 2], [0, 0, 1]]).expand(6, 3, 3)
    cams = Cameras(V.float(), K.float(), e["width"], e["height"])
    inria_side = render_views(scene, cams)
    import imageio.v3 as iio

    images = torch.from_numpy(np.stack([iio.imread(folder / "train" / f"r_{k}.png") for k in range(6)])) / 255.0
    assert float(images.std()) > 0.05  # the object, not an empty frame
    assert float((inria_side - images[..., :3]).abs().max()) <= 1.5 / 255  # 8-bit rounding
    # and it can fail: the scene left unturned (+Z up) seen from the same cameras is another image
    unturned = render_views(GaussianScene.load_ply(run_folder / "scene.ply"), cams)
    assert float((unturned - images[..., :3]).abs().max()) > 0.2


def test_a_scene_from_elsewhere_is_framed_and_gets_inrias_last_iteration(tmp_path):
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export
    from gdbench.core.builtin import demo_scene

    s = demo_scene(300, seed=5)
    s = GaussianScene(
        s.means * 3 + torch.tensor([2.0, -1.0, 0.5]), s.quats, s.log_scales + math.log(3), s.opacity_logits, s.sh
    )
    s.save_ply(tmp_path / "far.ply")
    r = main(Export(tmp_path / "far.ply", format="inria", up="+z", out=tmp_path / "model"))
    folder = Path(r["path"])
    assert (folder / "point_cloud" / "iteration_30000" / "point_cloud.ply").is_file()
    import imageio.v3 as iio

    img = iio.imread(folder / "train" / "r_0.png").astype(np.float64) / 255
    covered = (img[..., :3] < 0.98).any(-1).mean()
    assert 0.05 < covered < 0.9  # framed: the object fills part of the frame, not none or all
    with pytest.raises(ValueError, match=r"sh_degree \(--sh-degree\): --format inria writes SH degree 3"):
        main(Export(tmp_path / "far.ply", format="inria", sh_degree=1, out=tmp_path / "m2"))


def test_writing_again_replaces_the_model_and_a_foreign_folder_is_refused(run_folder, tmp_path):
    """Inria's loader takes the highest iteration: an export into a model folder written before
    must leave only its own (a copy of the scene without its run writes iteration 30000, the run's
    export 1234)."""
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export

    first = main(Export(run_folder / "scene.ply", format="inria", out=tmp_path / "m", src_up="+z"))
    (run_folder / "copy.ply").write_bytes((run_folder / "scene.ply").read_bytes())
    main(Export(run_folder / "copy.ply", format="inria", out=tmp_path / "m"))
    main(Export(run_folder, format="inria", out=tmp_path / "m"))
    clouds = sorted(p.parent.name for p in (tmp_path / "m").glob("point_cloud/iteration_*/point_cloud.ply"))
    assert first["path"] == str(tmp_path / "m") and clouds == ["iteration_1234"]
    (tmp_path / "other").mkdir()
    (tmp_path / "other" / "notes.txt").write_text("mine")
    with pytest.raises(ValueError, match=r"out \(--out\): .*other holds files and is not an Inria model folder"):
        main(Export(run_folder, format="inria", out=tmp_path / "other"))
