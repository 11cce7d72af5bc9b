"""Camera paths in nerfstudio's ``camera_path.json`` format (what its viewer exports and
``ns-render camera-path`` reads), for ``gdbench render --camera-path`` (docs/commands.md).

The fields read: ``render_width``, ``render_height`` (pixels), ``fps`` (optional, 24), and per
entry of ``camera_path`` a ``camera_to_world`` (16 numbers, a row-major 4x4 pose in OpenGL axes:
x right, y up, z backwards, as nerfstudio's) and ``fov`` (vertical, degrees). Only perspective
cameras (``camera_type`` absent or "perspective"); ``aspect`` is taken from the render size.
The world is the scene's, as the scene file gives it after gdbench turns it to +Z up.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import torch

from gdbench.core.camera import Cameras, intrinsics

_GL_TO_CV = np.diag([1.0, -1.0, -1.0, 1.0])


def _number(x) -> bool:
    return isinstance(x, (int, float)) and not isinstance(x, bool)


def _fail(path: Path, what: str) -> ValueError:
    return ValueError(f"camera_path (--camera-path): {path}: {what}")


def read_camera_path(path: str | Path) -> tuple[Cameras, float]:
    """(cameras, fps) of a nerfstudio camera path file (module docstring); errors name the file
    and the field."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"camera_path (--camera-path): no file at {path}")
    try:
        data = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise _fail(path, f"not a readable JSON file ({e})") from e
    if not isinstance(data, dict) or not isinstance(data.get("camera_path"), list) or not data["camera_path"]:
        raise _fail(path, "expected an object with a non-empty 'camera_path' list (nerfstudio's format)")
    if data.get("camera_type", "perspective") != "perspective":
        raise _fail(path, f"camera_type {data['camera_type']!r}: only 'perspective' cameras are rendered")
    size = []
    for key in ("render_width", "render_height"):
        v = data.get(key)
        if isinstance(v, bool) or not isinstance(v, int) or v < 8:
            raise _fail(path, f"'{key}' is {v!r}; expected an int >= 8 (pixels)")
        size.append(v)
    fps = data.get("fps", 24)
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not 0 < fps <= 240:
        raise _fail(path, f"'fps' is {fps!r}; expected a number in (0, 240]")
    viewmats, fovs = [], []
    for i, cam in enumerate(data["camera_path"]):
        where = f"camera_path[{i}].camera_to_world"
        raw = cam.get("camera_to_world") if isinstance(cam, dict) else None
        flat = raw
        if isinstance(raw, list) and raw and all(isinstance(r, list) for r in raw):
            flat = [x for r in raw for x in r]  # a nested 4x4 is read too
        if not isinstance(flat, list) or len(flat) != 16 or not all(_number(x) for x in flat):
            raise _fail(path, f"{where}: expected 16 numbers (a row-major 4x4)")
        c2w = np.asarray(flat, dtype=np.float64).reshape(4, 4)
        if not np.all(np.isfinite(c2w)):
            raise _fail(path, f"{where}: holds a non-finite number")
        if not np.allclose(c2w[3], [0, 0, 0, 1], atol=1e-6):
            raise _fail(path, f"{where}: its last row is {c2w[3].tolist()}; expected 0 0 0 1")
        fov = cam.get("fov")
        if not _number(fov) or not 0 < fov < 180:
            raise _fail(path, f"camera_path[{i}].fov is {fov!r}; expected vertical degrees in (0, 180)")
        r = c2w[:3, :3]
        if abs(np.linalg.det(r) - 1) > 1e-3 or np.abs(r @ r.T - np.eye(3)).max() > 1e-3:
            raise _fail(path, f"{where}: its 3x3 part is not a rotation")
        viewmats.append(np.linalg.inv(c2w @ _GL_TO_CV))
        fovs.append(float(fov))
    w, h = size
    Ks = intrinsics(torch.tensor(fovs, dtype=torch.float64), w, h)
    return Cameras(torch.from_numpy(np.stack(viewmats)).float(), Ks, w, h), float(fps)


def write_camera_path(cams: Cameras, path: str | Path, fps: float = 24.0) -> Path:
    """``cams`` as a nerfstudio camera path (square pixels, centred principal points), atomically."""
    from gdbench.core.io import atomic_write

    entries = []
    for k in range(len(cams)):
        c2w = np.linalg.inv(cams.viewmats[k].double().numpy()) @ _GL_TO_CV
        fov = math.degrees(2 * math.atan(cams.height / (2 * float(cams.Ks[k, 1, 1]))))
        entries.append({"camera_to_world": c2w.reshape(-1).tolist(), "fov": fov, "aspect": cams.width / cams.height})
    data = {
        "camera_type": "perspective",
        "render_width": cams.width,
        "render_height": cams.height,
        "fps": fps,
        "seconds": len(cams) / fps,
        "camera_path": entries,
    }
    text = json.dumps(data, indent=1)
    return atomic_write(Path(path), lambda f: f.write(text.encode()))
