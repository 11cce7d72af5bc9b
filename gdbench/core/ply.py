"""3DGS PLY files in the layout of the original 3DGS code (Kerbl et al. 2023).

One ``vertex`` element of float32 properties, in this order::

    x y z nx ny nz f_dc_0..2 f_rest_0..(3(K-1)-1) opacity scale_0..2 rot_0..3

``f_rest`` is channel-major (all red coefficients of bands >= 1, then green, then blue),
``opacity`` is the logit, ``scale_*`` the log-scale and ``rot_*`` the wxyz quaternion;
normals are written as zero and ignored on read. Viewers and Open3D read and write this
layout. Values are stored as float32, so a float32 scene round-trips exactly.

``read_ply`` also reads the chunked compressed PLY of SuperSplat / PlayCanvas (elements ``chunk``,
``vertex`` with ``packed_*`` properties and an optional ``sh``; ``read_compressed_ply``, written by
``gdbench.app.export``): it is told apart by its header, not its name.

This module knows the file format only, as plain tensors (``FIELDS``); ``GaussianScene.load_ply``
and ``save_ply`` (scene.py) turn them into a scene and back.
"""

from __future__ import annotations

import math
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

    from gdbench.core.io import atomic_write

    path = Path(path)
    means, quats, log_scales, opacity_logits, sh = (fields[k].detach().to("cpu", torch.float32) for k in FIELDS)
    n, k = sh.shape[0], sh.shape[1]
    rest = sh[:, 1:, :].transpose(1, 2).reshape(n, 3 * (k - 1))  # channel-major
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
    """The ``FIELDS`` of a 3DGS PLY (ours, the Inria code's, Open3D's, or a compressed PLY: see
    ``read_compressed_ply``) as float32 tensors. Errors name the file and the problem."""
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
    if is_compressed(ply):
        _check_extent(path, ply)
        return read_compressed_ply(path, ply)
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
    if missing and {"x", "y", "z"} <= names:  # points without Gaussians: a point cloud to start a run from
        raise ValueError(
            f"{path}: a point cloud, not a 3DGS PLY (missing vertex properties {missing}); to start a run from "
            f"its points, pass it to `gdbench generate PROMPT --init ply --init-ply {path}`"
        )
    if missing:
        raise ValueError(f"{path}: not a 3DGS PLY, missing vertex properties {missing}")
    if "filter_3D" in names:
        import warnings

        warnings.warn(
            f"{path}: its filter_3D property (Mip-Splatting's 3D smoothing filter) is ignored: the scene is read "
            "and rendered as plain 3D Gaussians",
            stacklevel=2,
        )
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


# ------------------------------------------------------------------ compressed PLY (SuperSplat)
CHUNK_SIZE = 256
"""Gaussians per chunk of a compressed PLY: chunk i holds the bounds of vertices 256 i .. 256 i + 255."""

CHUNK_BOUNDS = tuple(f"{m}_{a}" for m in ("min", "max") for a in "xyz") + tuple(
    f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"
)
CHUNK_COLORS = tuple(f"{m}_{c}" for m in ("min", "max") for c in "rgb")
"""Colour bounds of a chunk; files written before they existed pack colours in [0, 1] directly."""

PACKED = ("packed_position", "packed_rotation", "packed_scale", "packed_color")

OPACITY_LOGIT_LIMIT = 40.0
"""Opacity 0 and 1 (a quantised byte of 0 or 255) are read as logits -40 and 40, as PlayCanvas's
reader does: finite, and invisible or opaque to float32 precision."""


def is_compressed(ply) -> bool:
    """Whether a ``plyfile.PlyData`` is a compressed PLY: a ``chunk`` element and a ``vertex`` element
    with the four ``packed_*`` properties."""
    elements = {el.name for el in ply.elements}
    if "chunk" not in elements or "vertex" not in elements:
        return False
    names = set(ply["vertex"].data.dtype.names or ())
    return all(p in names for p in PACKED)


def opacity_logit(a: np.ndarray) -> np.ndarray:
    """Logits of opacities in [0, 1]; 0 and 1 become -+``OPACITY_LOGIT_LIMIT``."""
    a = np.asarray(a, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        logit = np.log(a) - np.log1p(-a)
    logit = np.where(a <= 0, -np.inf, np.where(a >= 1, np.inf, logit))
    return np.clip(logit, -OPACITY_LOGIT_LIMIT, OPACITY_LOGIT_LIMIT)


def _unorm(packed: np.ndarray, shift: int, bits: int) -> np.ndarray:
    mask = (1 << bits) - 1
    return ((packed >> shift) & mask).astype(np.float64) / mask


def read_compressed_ply(path: str | Path, ply=None) -> dict[str, Tensor]:
    """The ``FIELDS`` of a compressed PLY (SuperSplat / PlayCanvas ``.compressed.ply``, gsplat's
    ``ply_compressed``, ``gdbench.app.export``) as float32 tensors; ``ply`` is the file's ``PlyData``
    if already read.

    Per chunk of 256 vertices, float bounds: position ``min_x..max_z``, log-scale
    ``min_scale_x..max_scale_z`` and (optional) colour ``min_r..max_b``. Per vertex, four uint32:
    ``packed_position`` and ``packed_scale`` are 11-10-11-bit fractions of the chunk's range (x in the
    top bits), ``packed_color`` 8-8-8-8 (r g b in the chunk's colour range, then opacity in [0, 1]),
    ``packed_rotation`` the "smallest three": the top 2 bits index the largest |component| of the
    unit quaternion (rot_0..3, i.e. w x y z), the three others follow as 10 bits each of
    ``c / sqrt(2) + 0.5``, and the largest is ``sqrt(1 - sum of their squares)``. The optional ``sh``
    element holds ``f_rest_*`` (channel-major, as in the plain layout) as uint8 ``trunc((f / 8 + 0.5)
    * 256)`` (bins of 1/32), read at the middle of their bin, ``(v + 0.5) / 32 - 4`` (error <= 1/64),
    except the bin of [0, 1/32), read as 0 so that zero coefficients (padded or untrained bands)
    stay zero (error < 1/32). PlayCanvas's engine reads ``v * 8 / 255 - 4`` (0 becomes 0.0157),
    splat-transform ``v / 32 - 4`` (the lower end: error in [0, 1/32)). Colours are turned back
    into DC coefficients ``(c - 0.5) / C0``; opacity into a logit (``opacity_logit``)."""
    from plyfile import PlyData

    from renderers.splat.sh import C0

    path = Path(path)
    if ply is None:
        try:
            ply = PlyData.read(str(path))
        except Exception as e:
            raise ValueError(f"{path}: not a readable PLY file ({type(e).__name__}: {e})") from e
    if not is_compressed(ply):
        raise ValueError(f"{path}: not a compressed PLY (expected elements 'chunk' and 'vertex' with {list(PACKED)})")
    v, c = ply["vertex"].data, ply["chunk"].data
    n, nc = len(v), len(c)
    if nc != -(-n // CHUNK_SIZE):
        raise ValueError(
            f"{path}: a compressed PLY of {n} vertices has {-(-n // CHUNK_SIZE)} chunks of {CHUNK_SIZE}, "
            f"the header declares {nc}"
        )
    cnames = set(c.dtype.names or ())
    missing = [p for p in CHUNK_BOUNDS if p not in cnames]
    if missing:
        raise ValueError(f"{path}: compressed PLY chunk element is missing properties {missing}")
    has_colors = all(p in cnames for p in CHUNK_COLORS)
    for name in PACKED:
        if v[name].dtype.kind != "u" or v[name].dtype.itemsize != 4:
            raise ValueError(f"{path}: {name} is {v[name].dtype}; expected uint32")
    ci = np.arange(n) // CHUNK_SIZE
    bounds = {}
    for name in CHUNK_BOUNDS + (CHUNK_COLORS if has_colors else ()):
        col = np.asarray(c[name], dtype=np.float64)
        bad = np.flatnonzero(~np.isfinite(col))
        if bad.size:
            raise ValueError(f"{path}: {name} of chunk {bad[0]} is {col[bad[0]]}; expected finite values")
        bounds[name] = col[ci]

    def lerp(axis: str, t: np.ndarray) -> np.ndarray:  # PlayCanvas's lerp: exact at both ends
        return bounds[f"min_{axis}"] * (1 - t) + bounds[f"max_{axis}"] * t

    def unpack_111011(name: str) -> list[np.ndarray]:
        p = np.asarray(v[name], dtype=np.int64)
        return [_unorm(p, 21, 11), _unorm(p, 11, 10), _unorm(p, 0, 11)]

    means = np.stack([lerp(a, t) for a, t in zip("xyz", unpack_111011("packed_position"))], 1)
    log_scales = np.stack([lerp(f"scale_{a}", t) for a, t in zip("xyz", unpack_111011("packed_scale"))], 1)
    packed = np.asarray(v["packed_color"], dtype=np.int64)
    rgb = [_unorm(packed, s, 8) for s in (24, 16, 8)]
    if has_colors:
        rgb = [lerp(a, t) for a, t in zip("rgb", rgb)]
    dc = (np.stack(rgb, 1) - 0.5) / C0
    opacity = opacity_logit(_unorm(packed, 0, 8))
    packed = np.asarray(v["packed_rotation"], dtype=np.int64)
    small = np.stack([(_unorm(packed, s, 10) - 0.5) * math.sqrt(2.0) for s in (20, 10, 0)], 1)
    largest = (packed >> 30) & 3
    others = np.array([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    quats = np.empty((n, 4))
    rows = np.arange(n)
    quats[rows[:, None], others] = small
    quats[rows, largest] = np.sqrt(np.maximum(0.0, 1.0 - (small**2).sum(1)))
    rest = np.zeros((n, 0))
    if "sh" in {el.name for el in ply.elements}:
        s = ply["sh"].data
        names = list(s.dtype.names or ())
        n_rest = len(names)
        # an sh element without properties (gsplat writes one at degree 0) holds nothing
        bad_rows = n_rest > 0 and len(s) != n
        if bad_rows or n_rest not in _REST_TO_K or names != [f"f_rest_{i}" for i in range(n_rest)]:
            raise ValueError(
                f"{path}: the sh element has {len(s)} rows of {names[:3]}...; expected {n} rows of "
                f"f_rest_0..f_rest_(k-1) with k in {sorted(_REST_TO_K)}"
            )
        if n_rest:
            v8 = np.stack([np.asarray(s[name], dtype=np.float64) for name in names], 1)
            rest = np.where(v8 == 128, 0.0, (v8 + 0.5) / 32.0 - 4.0)
    k = _REST_TO_K[rest.shape[1]]
    _check_values(path, {f"scale_{i}": log_scales[:, i] for i in range(3)}, [f"scale_{i}" for i in range(3)])
    sh = np.concatenate([dc[:, None, :], rest.reshape(n, 3, k - 1).transpose(0, 2, 1)], axis=1)
    f32 = lambda a: torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))  # noqa: E731
    return dict(zip(FIELDS, (f32(means), f32(quats), f32(log_scales), f32(opacity), f32(sh))))
