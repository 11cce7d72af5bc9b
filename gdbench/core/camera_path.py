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


def _fail(path: Path, what: str) -> ValueError:
    return ValueError(f"camera_path (--camera-path): {path}: {what}")


def read_camera_path(path: str | Path) -> tuple[Cameras, float]:
    """(cameras, fps) of a nerfstudio camera path file (module docstring); errors name the file
    and the field."""
    path = Path(path)
    try:
        data = json.loads(path.read_text())
    except FileNotFoundError:
        raise FileNotFoundError(f"camera_path (--camera-path): no file at {path}") from None
    except ValueError as e:
        raise _fail(path, f"not JSON ({e})") from e
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
        c2w = np.asarray(cam.get("camera_to_world") if isinstance(cam, dict) else None, dtype=object)
        try:
            c2w = np.asarray(c2w.tolist(), dtype=np.float64).reshape(4, 4)
        except (TypeError, ValueError):
            raise _fail(path, f"camera_path[{i}].camera_to_world: expected 16 numbers (a row-major 4x4)") from None
        fov = cam.get("fov")
        if isinstance(fov, bool) or not isinstance(fov, (int, float)) or not 0 < fov < 180:
            raise _fail(path, f"camera_path[{i}].fov is {fov!r}; expected vertical degrees in (0, 180)")
        r = c2w[:3, :3]
        if not np.all(np.isfinite(c2w)) or abs(np.linalg.det(r) - 1) > 1e-3 or np.abs(r @ r.T - np.eye(3)).max() > 1e-3:
            raise _fail(path, f"camera_path[{i}].camera_to_world: its 3x3 part is not a rotation")
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
