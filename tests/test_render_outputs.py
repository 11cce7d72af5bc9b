"""``gdbench render --outputs rgb,depth,alpha`` and ``--camera-path`` (nerfstudio's camera_path.json).

Oracles: one flat opaque Gaussian facing a camera at a known distance (its depth is that distance,
its alpha its opacity at the centre); nerfstudio's convention written out by hand (a camera at
+Z looking down is the identity rotation in OpenGL axes); the orbit's cameras through a file
and back."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import torch

from gdbench.core.scene import GaussianScene


def _disk(opacity: float = 0.9) -> GaussianScene:
    """One flat Gaussian in the z = 0 plane at the origin, 0.3 across (sigma), red."""
    return GaussianScene.from_activated(
        torch.zeros(1, 3), torch.tensor([[0.3, 0.3, 0.001]]), torch.tensor([opacity]), torch.tensor([[0.9, 0.1, 0.1]])
    )


def _path_file(tmp_path, entries, width=32, height=24, **extra):
    data = {"camera_type": "perspective", "render_width": width, "render_height": height, "fps": 10} | extra
    data["camera_path"] = entries
    p = tmp_path / "camera_path.json"
    p.write_text(json.dumps(data))
    return p


def _above(distance: float, fov: float = 40.0) -> dict:
    """nerfstudio's pose of a camera on +Z looking down at the origin: OpenGL axes (z backwards),
    so the identity rotation and the position."""
    c2w = np.eye(4)
    c2w[2, 3] = distance
    return {"camera_to_world": c2w.reshape(-1).tolist(), "fov": fov, "aspect": 32 / 24}


def test_depth_and_alpha_of_a_disk_seen_from_a_camera_path(tmp_path):
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Render

    _disk().save_ply(tmp_path / "disk.ply")
    path = _path_file(tmp_path, [_above(2.0), _above(3.0)])
    r = main(Render(tmp_path / "disk.ply", camera_path=path, outputs="rgb,depth,alpha", out=tmp_path / "r"))
    depth, alpha = np.load(r["depth_npy"]), np.load(r["alpha_npy"])
    assert depth.shape == alpha.shape == (2, 24, 32)  # the path's size: height x width
    # the four pixels around the principal point, half a pixel off it in x and y: the screen-space
    # Gaussian of sigma 0.3 f / d, blurred by eps2d (3DGS's 0.3 px^2), times the opacity
    from renderers.splat.settings import RasterSettings

    f = 12 / math.tan(math.radians(20))
    for k, d in enumerate((2.0, 3.0)):
        var = (0.3 * f / d) ** 2 + RasterSettings().eps2d
        assert float(depth[k, 11:13, 15:17].mean()) == pytest.approx(d, abs=1e-3)
        assert float(alpha[k, 11:13, 15:17].mean()) == pytest.approx(0.9 * math.exp(-0.25 / var), abs=2e-3)
    assert float(alpha[0, 0, 0]) < float(alpha[0, 12, 16]) and float(depth[0, 0, 0]) >= 0
    # the disk looks 1.5 times wider from 2 than from 3 (pinhole): the alpha-weighted spread
    widths = [float(np.sqrt((alpha[k].sum(0) * (np.arange(32) - 15.5) ** 2).sum() / alpha[k].sum())) for k in (0, 1)]
    assert widths[0] / widths[1] == pytest.approx(1.5, rel=0.05)
    for key in ("gif", "sheet", "depth_gif", "depth_sheet", "alpha_gif", "alpha_sheet"):
        assert r[key].endswith((".gif", ".png"))


def test_camera_path_round_trip_and_convention(tmp_path):
    from gdbench.core.camera import SphericalPoses
    from gdbench.core.camera_path import read_camera_path, write_camera_path

    cams = SphericalPoses.orbit(5, radius=1.3, elevation=15.0, fovy=45.0).cameras(40, 30)
    write_camera_path(cams, tmp_path / "orbit.json", fps=7)
    back, fps = read_camera_path(tmp_path / "orbit.json")
    assert fps == 7 and (back.width, back.height) == (40, 30)
    torch.testing.assert_close(back.viewmats, cams.viewmats, atol=1e-6, rtol=0)
    torch.testing.assert_close(back.Ks, cams.Ks, atol=1e-4, rtol=0)
    # nerfstudio's camera on +Z with the identity rotation looks down -Z: ours, looking at the origin
    (one, _) = read_camera_path(_path_file(tmp_path, [_above(2.0)]))
    point = torch.tensor([0.0, 0.0, 0.0, 1.0])
    cam = one.viewmats[0] @ point
    assert cam[2] == pytest.approx(2.0)  # in front of the camera (OpenCV +z forward), 2 away
    up = one.viewmats[0] @ torch.tensor([0.0, 1.0, 0.0, 1.0])
    assert up[1] < 0  # the world's +Y is up in the image (OpenCV y points down)
    assert float(one.Ks[0, 1, 1]) == pytest.approx(24 / 2 / math.tan(math.radians(20)))


@pytest.mark.parametrize(
    "entries,extra,match",
    [
        ([], {}, "non-empty 'camera_path' list"),
        ([{"camera_to_world": [1, 0, 0], "fov": 40}], {}, r"camera_path\[0\]\.camera_to_world: expected 16 numbers"),
        ([_above(2.0) | {"fov": 0}], {}, r"camera_path\[0\]\.fov is 0"),
        ([_above(2.0) | {"camera_to_world": np.diag([2.0, 2.0, 2.0, 1.0]).reshape(-1).tolist()}], {}, "not a rotation"),
        ([_above(2.0)], {"camera_type": "fisheye"}, "only 'perspective'"),
        ([_above(2.0)], {"render_width": 4}, "'render_width' is 4"),
        ([_above(2.0) | {"camera_to_world": [*_above(2.0)["camera_to_world"][:15], 2.0]}], {}, "last row is"),
        ([_above(2.0) | {"camera_to_world": [float("nan"), *_above(2.0)["camera_to_world"][1:]]}], {}, "non-finite"),
        ([_above(2.0) | {"camera_to_world": ["1", *_above(2.0)["camera_to_world"][1:]]}], {}, "expected 16 numbers"),
    ],
)
def test_bad_camera_paths_are_refused_naming_the_field(tmp_path, entries, extra, match):
    from gdbench.core.camera_path import read_camera_path

    with pytest.raises(ValueError, match=rf"camera_path \(--camera-path\): .*{match}"):
        read_camera_path(_path_file(tmp_path, entries, **extra))


def test_a_folder_or_a_missing_file_as_camera_path_is_named(tmp_path):
    from gdbench.core.camera_path import read_camera_path

    with pytest.raises(FileNotFoundError, match=r"camera_path \(--camera-path\): no file at"):
        read_camera_path(tmp_path)
    with pytest.raises(FileNotFoundError, match=r"camera_path \(--camera-path\): no file at"):
        read_camera_path(tmp_path / "missing.json")


def test_unknown_outputs_are_refused_before_any_work(tmp_path):
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Render

    _disk().save_ply(tmp_path / "disk.ply")
    with pytest.raises(ValueError, match=r"outputs \(--outputs\): expected some of rgb,depth,alpha.*'rgb,normals'"):
        main(Render(tmp_path / "disk.ply", outputs="rgb,normals", out=tmp_path / "r"))
    assert not (tmp_path / "r").exists()
