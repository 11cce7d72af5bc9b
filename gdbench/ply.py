"""3DGS PLY files in the layout of the original 3DGS code (Kerbl et al. 2023).

One ``vertex`` element of float32 properties, in this order::

    x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3

``f_rest`` is channel-major (all red coefficients of bands >= 1, then green, then blue),
``opacity`` is the logit, ``scale_*`` the log-scale and ``rot_*`` the wxyz quaternion;
normals are written as zero and ignored on read. Viewers and Open3D read and write this
layout. Values are stored as float32, so a float32 scene round-trips exactly.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np
import torch

from .scene import GaussianScene

_REST_TO_K = {0: 1, 9: 4, 24: 9, 45: 16}


def _names(k: int) -> list[str]:
    rest = [f"f_rest_{i}" for i in range(3 * (k - 1))]
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + rest
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_ply(scene: GaussianScene, path: str | Path) -> Path:
    """Write ``scene`` as a binary little-endian 3DGS PLY, atomically (temp file + rename)."""
    from plyfile import PlyData, PlyElement

    path = Path(path)
    s = scene.detach().to("cpu", torch.float32)
    n, k = s.sh.shape[0], s.sh.shape[1]
    rest = s.sh[:, 1:, :].transpose(1, 2).reshape(n, -1)  # channel-major
    cols = [s.means, torch.zeros(n, 3), s.sh[:, 0, :], rest, s.opacity_logits[:, None], s.log_scales, s.quats]
    data = torch.cat(cols, dim=1).numpy()
    names = _names(k)
    assert data.shape[1] == len(names)
    arr = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        arr[name] = data[:, i]
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".ply.tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            PlyData([PlyElement.describe(arr, "vertex")], text=False).write(f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def read_ply(path: str | Path) -> GaussianScene:
    """Read a 3DGS PLY (ours, the Inria code's, Open3D's). Errors name the file and the problem."""
    from plyfile import PlyData

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no PLY file at {path}")
    try:
        ply = PlyData.read(str(path))
        v = ply["vertex"].data
    except KeyError:
        raise ValueError(f"{path}: PLY file has no 'vertex' element") from None
    except Exception as e:  # plyfile raises several types for truncated or malformed files
        raise ValueError(f"{path}: not a readable PLY file ({type(e).__name__}: {e})") from e
    names = set(v.dtype.names or ())
    required = [
        "x",
        "y",
        "z",
        "f_dc_0",
        "f_dc_1",
        "f_dc_2",
        "opacity",
        *(f"scale_{i}" for i in range(3)),
        *(f"rot_{i}" for i in range(4)),
    ]
    missing = [r for r in required if r not in names]
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    if n_rest not in _REST_TO_K or any(f"f_rest_{i}" not in names for i in range(n_rest)):
        raise ValueError(f"{path}: expected f_rest_0..f_rest_(n-1) with n in {sorted(_REST_TO_K)}, found {n_rest}")
    k = _REST_TO_K[n_rest]
    n = len(v)

    def col(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[key], dtype=np.float32) for key in keys], axis=1))

    means = col("x", "y", "z")
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")
    rest = col(*(f"f_rest_{i}" for i in range(n_rest))) if n_rest else torch.zeros(n, 0)
    sh = torch.cat([dc[:, None, :], rest.reshape(n, 3, k - 1).transpose(1, 2)], dim=1)
    try:
        return GaussianScene(
            means,
            col("rot_0", "rot_1", "rot_2", "rot_3"),
            col("scale_0", "scale_1", "scale_2"),
            col("opacity")[:, 0],
            sh,
        )
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from e
