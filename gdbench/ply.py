"""3DGS PLY files in the layout of the original 3DGS code (Kerbl et al. 2023).

One ``vertex`` element of float32 properties, in this order::

    x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3

``f_rest`` is channel-major (all red coefficients of bands >= 1, then green, then blue),
``opacity`` is the logit, ``scale_*`` the log-scale and ``rot_*`` the wxyz quaternion;
normals are written as zero and ignored on read. Viewers and Open3D read and write this
layout. Values are stored as float32, so a float32 scene round-trips exactly.

This module knows the file format only, as plain tensors (``FIELDS``); ``GaussianScene.load_ply``
and ``save_ply`` (scene.py) turn them into a scene and back.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

FIELDS = ("means", "quats", "log_scales", "opacity_logits", "sh")
"""What a 3DGS PLY holds, as GaussianScene names it: [N, 3], [N, 4] wxyz, [N, 3], [N], [N, K, 3]."""

_REST_TO_K = {0: 1, 9: 4, 24: 9, 45: 16}

LOG_SCALE_RANGE = (-30.0, 12.0)
"""Log-scales a PLY may hold. Above 12 (scales beyond 1.6e5 scene units) the float32 covariance
loses precision: an anisotropic Gaussian at 15 differs from the float64 twin by 3e-4 in alpha,
and above ~43 float32 Gaussians vanish (alpha 0 where the twin gives 0.7). Below -30 a Gaussian is
far under a pixel at any distance and only its 2D dilation is left."""


MAX_HEADER = 16 << 20
"""A header longer than this (16 MiB) is refused rather than searched further."""


_END_HEADER = re.compile(rb"(?:^|\n)end_header\r?\n")


def _body_offset(path: Path) -> int:
    """Where the body starts: after the ``end_header`` line, however long the header is."""
    buf = b""
    with open(path, "rb") as f:
        while True:
            chunk = f.read(1 << 16)
            buf += chunk
            m = _END_HEADER.search(buf)  # a line of its own: "end_header" in a comment is not the end
            if m is not None:
                return m.end()
            if not chunk:
                if buf.endswith(b"\nend_header"):  # a header with no body and no last newline
                    return len(buf)
                raise ValueError(f"{path}: the PLY header has no end_header line")
            if len(buf) > MAX_HEADER:
                raise ValueError(f"{path}: the PLY header is longer than {MAX_HEADER >> 20} MiB; refusing to read on")


def _element_bytes(el) -> int:
    """Bytes of a binary element's rows: fixed-size properties by their dtype, list properties by
    the lengths the file gave each row."""
    from plyfile import PlyListProperty

    size = 0
    for prop in el.properties:
        if isinstance(prop, PlyListProperty):
            len_dtype, val_dtype = (np.dtype(d) for d in prop.list_dtype())
            lengths = sum(len(row) for row in el.data[prop.name])
            size += el.count * len_dtype.itemsize + lengths * val_dtype.itemsize
        else:
            size += el.count * np.dtype(prop.dtype()).itemsize
    return size


def _check_extent(path: Path, ply) -> None:
    """The header's counts must cover the file exactly, for every element layout (vertices alone,
    or followed by faces or others): no rows beyond them, no trailing bytes, no missing rows."""
    body = _body_offset(path)
    counts = ", ".join(f"{el.count} {el.name}" for el in ply.elements)
    if ply.text:
        with open(path, "rb") as f:
            f.seek(body)
            rows = sum(1 for line in f if line.strip())
        want = sum(el.count for el in ply.elements)
        if rows != want:
            raise ValueError(f"{path}: the header declares {want} rows ({counts}) but the file has {rows} rows")
        return
    extra = path.stat().st_size - body - sum(_element_bytes(el) for el in ply.elements)
    if extra > 0:
        v = ply["vertex"]
        rows = extra / v.data.dtype.itemsize
        raise ValueError(
            f"{path}: {extra} bytes follow the {counts} rows the header declares "
            f"({rows:g} vertex rows' worth: a count is too small, or the file has trailing data)"
        )


def _check_values(path: Path, v, names: list[str]) -> None:
    for name in names:
        col = np.asarray(v[name], dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(col))
        if bad.size:
            raise ValueError(f"{path}: {name} of vertex {bad[0]} is {col[bad[0]]}; expected finite values")
        if name.startswith("scale_") and col.size:
            lo, hi = LOG_SCALE_RANGE
            out = np.flatnonzero((col < lo) | (col > hi))
            if out.size:
                raise ValueError(
                    f"{path}: {name} of vertex {out[0]} is {col[out[0]]:g} (a log-scale); expected values in "
                    f"[{lo:g}, {hi:g}] (docs/reliability.md)"
                )


def _names(k: int) -> list[str]:
    rest = [f"f_rest_{i}" for i in range(3 * (k - 1))]
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + rest
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def write_ply(fields: dict[str, Tensor], path: str | Path, *, comments: list[str] | None = None) -> Path:
    """Write a scene's ``fields`` (``FIELDS``, any float dtype and device) as a binary little-endian
    3DGS PLY, atomically (temp file + rename); ``comments`` go into the header (gdbench writes the
    run id there)."""
    from plyfile import PlyData, PlyElement

    from .io import atomic_write

    path = Path(path)
    means, quats, log_scales, opacity_logits, sh = (fields[k].detach().to("cpu", torch.float32) for k in FIELDS)
    n, k = sh.shape[0], sh.shape[1]
    rest = sh[:, 1:, :].transpose(1, 2).reshape(n, -1)  # channel-major
    cols = [means, torch.zeros(n, 3), sh[:, 0, :], rest, opacity_logits[:, None], log_scales, quats]
    data = torch.cat(cols, dim=1).numpy()
    names = _names(k)
    assert data.shape[1] == len(names)
    arr = np.empty(n, dtype=[(name, "<f4") for name in names])
    for i, name in enumerate(names):
        arr[name] = data[:, i]
    ply = PlyData([PlyElement.describe(arr, "vertex")], text=False, comments=list(comments or []))
    return atomic_write(path, ply.write)


def header_comments(path: str | Path) -> list[str]:
    """The ``comment`` lines of a PLY header (gdbench writes ``gdbench run <run id>``), read
    from at most its first 64 KiB without parsing the body."""
    with open(path, "rb") as f:
        head = f.read(1 << 16)
    m = _END_HEADER.search(head)
    lines = head[: m.start() if m else len(head)].decode("ascii", errors="replace").splitlines()
    return [line[len("comment ") :].strip() for line in lines if line.startswith("comment ")]


def read_ply(path: str | Path) -> dict[str, Tensor]:
    """The ``FIELDS`` of a 3DGS PLY (ours, the Inria code's, Open3D's) as float32 tensors. Errors
    name the file and the problem."""
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
    _check_extent(path, ply)
    n_rest = sum(1 for name in names if name.startswith("f_rest_"))
    if n_rest not in _REST_TO_K or any(f"f_rest_{i}" not in names for i in range(n_rest)):
        raise ValueError(f"{path}: expected f_rest_0..f_rest_(n-1) with n in {sorted(_REST_TO_K)}, found {n_rest}")
    k = _REST_TO_K[n_rest]
    n = len(v)
    _check_values(path, v, required + [f"f_rest_{i}" for i in range(n_rest)])

    def col(*keys: str) -> torch.Tensor:
        return torch.from_numpy(np.stack([np.asarray(v[key], dtype=np.float32) for key in keys], axis=1))

    means = col("x", "y", "z")
    dc = col("f_dc_0", "f_dc_1", "f_dc_2")
    rest = col(*(f"f_rest_{i}" for i in range(n_rest))) if n_rest else torch.zeros(n, 0)
    sh = torch.cat([dc[:, None, :], rest.reshape(n, 3, k - 1).transpose(1, 2)], dim=1)
    quats, log_scales = col("rot_0", "rot_1", "rot_2", "rot_3"), col("scale_0", "scale_1", "scale_2")
    return dict(zip(FIELDS, (means, quats, log_scales, col("opacity")[:, 0], sh)))
