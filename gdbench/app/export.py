"""Export a ``GaussianScene`` for other viewers, and read the files back (docs/export.md).

Formats (``FORMATS``):

- ``"ply"``: the Inria 3DGS layout (``ply.write_ply``), float32: a float32 scene round-trips
  exactly. Read by the Inria code, gsplat, Open3D, SuperSplat, antimatter15's converter and most
  viewers. ``sh_degree`` pads (or truncates) the SH bands: the Inria loader at degree 3 wants all
  45 ``f_rest_*`` properties.
- ``"splat"``: antimatter15's 32-byte rows (position f32x3, linear scale f32x3, RGBA u8x4 with the
  DC colour and the opacity, rotation u8x4 ``q / |q| * 128 + 128`` in w x y z order), sorted by
  descending ``volume * opacity`` as antimatter15's ``convert.py`` does. Bytes are truncated as
  that converter and gsplat's exporter do (each row equals gsplat 1.5.3's; tested). DC colour
  only: SH bands >= 1 are dropped and colours are clipped to [0, 1].
- ``"ply-compressed"``: SuperSplat / PlayCanvas's chunked compressed PLY (``ply.read_compressed_ply``
  describes the layout), Morton-ordered chunks of 256. The packing arithmetic is gsplat 1.5.3's
  ``ply_compressed`` and splat-transform's (byte-identical to gsplat's for the same order; tested),
  with two differences: every Gaussian is kept (gsplat drops opacities <= 1/255), and a chunk
  whose values are all equal packs 0 (gsplat divides 0 by 0 there); scenes of SH degree 0 get no
  ``sh`` element (as splat-transform writes them).

gsplat's ``export_splats`` itself is not called: gsplat is a test-only dependency, its ``.splat``
order is not the viewer's, its zero-quaternion and constant-chunk cases divide by zero, and it
writes the file in place (ours go through ``io.atomic_write``: a crash leaves no half file).

``up`` rotates the scene (+Z up, docs/conventions.md) by ``filetags.up_rotation`` (about the x
axis for -Y, the Inria / COLMAP convention most 3DGS viewers assume, and +Y, so +X, an asset's
front, stays +X). Means and quaternions rotate, and SH bands of degree 1..3 rotate with their
real Wigner-D matrices (``rotate_scene``), so the rotated scene seen from the rotated camera is
the same image. Every file records its up axis and the run it comes from (``core.filetags``: PLY
header comments, a .splat's sidecar), and ``load_scene`` reads them back.

Zero quaternions (the identity in our convention, ``renderers.splat.project.normalize_quats``)
are written as (1, 0, 0, 0), which other readers understand.
"""

from __future__ import annotations

import json
import math
import numbers
import os
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from torch import Tensor

from gdbench.core.camera import quat_mul, rotmat_to_quat
from gdbench.core.filetags import UP_AXES, UpAxis, ply_comments, resolve_up, sidecar, sidecar_json, up_rotation
from gdbench.core.io import atomic_write, check_folder
from gdbench.core.ply import CHUNK_SIZE, LOG_SCALE_RANGE, opacity_logit
from gdbench.core.scene import GaussianScene
from renderers.splat.sh import C0, sh_basis

FORMATS = ("ply", "splat", "ply-compressed")
SUFFIXES = {"ply": ".ply", "splat": ".splat", "ply-compressed": ".ply"}
"""The file name suffix each format wants (case-insensitive). A compressed PLY is conventionally
named ``*.compressed.ply`` (SuperSplat's and splat-transform's name; readers tell it by its header)."""

SPLAT_DTYPE = np.dtype([("position", "<f4", 3), ("scale", "<f4", 3), ("rgba", "u1", 4), ("rot", "u1", 4)])
"""One row of a ``.splat`` file (32 bytes)."""

_QUAT_EPS = 1e-12  # renderers.splat.project.QUAT_EPS: quaternions this short are the identity
_SCALE_BOUND = 20.0  # compressed PLY: log-scale chunk bounds are clamped to +-20 (gsplat, SuperSplat)


def _choice(name: str, value, choices: tuple[str, ...]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ValueError(f"{name}: expected one of {', '.join(map(repr, choices))}, got {value!r}")
    return value


# ------------------------------------------------------------------------------ rotations
def _fibonacci_dirs(n: int) -> Tensor:
    i = torch.arange(n, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / n
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = torch.sqrt(1.0 - z * z)
    return torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)


def sh_rotation(rotation: Tensor, degree: int) -> list[Tensor]:
    """Per band l = 1..degree, the float64 [2l+1, 2l+1] matrix D_l that rotates SH coefficients:
    a Gaussian whose coefficients are ``D_l c_l`` shows in direction ``R d`` the colour the original
    shows in direction ``d``. Each band of the basis (``renderers.splat.sh.sh_basis``) is a
    rotation-invariant space, so ``Y_l(R^T d) = D_l^T Y_l(d)`` holds exactly for one matrix (the
    real Wigner-D matrix in this basis); it is solved by least squares on 64 directions, exact to
    float64 rounding (~1e-15), for any rotation and any degree up to 3."""
    dirs = _fibonacci_dirs(64)
    y = sh_basis(degree, dirs)
    y_rot = sh_basis(degree, dirs @ rotation.to(torch.float64))  # rows: Y(R^T d)
    return [
        torch.linalg.lstsq(y[:, l * l : (l + 1) ** 2], y_rot[:, l * l : (l + 1) ** 2]).solution
        for l in range(1, degree + 1)
    ]


def _canonical_quats(quats: Tensor) -> Tensor:
    """Quaternions with the (near-)zero ones, which mean the identity, replaced by (1, 0, 0, 0)."""
    zero = torch.linalg.vector_norm(quats, dim=-1) <= _QUAT_EPS
    if not bool(zero.any()):
        return quats
    identity = torch.zeros_like(quats)
    identity[:, 0] = 1.0
    return torch.where(zero[:, None], identity, quats)


def rotate_scene(scene: GaussianScene, rotation: Tensor) -> GaussianScene:
    """``scene`` rotated about the origin by ``rotation`` [3, 3] (a proper rotation): means ``R x``,
    quaternions ``q_R q`` (norms kept; zero ones, the identity, become ``q_R``), SH bands by
    ``sh_rotation``. Rendered from a camera rotated the same way (viewmat ``V diag(R^T, 1)``) it
    gives the original image. Computed in float64, returned in the scene's dtype."""
    rotation = torch.as_tensor(rotation, dtype=torch.float64)
    if rotation.shape != (3, 3):
        raise ValueError(f"rotation: expected shape [3, 3], got {list(rotation.shape)}")
    err = float((rotation @ rotation.T - torch.eye(3, dtype=torch.float64)).abs().max())
    if err > 1e-6 or float(torch.linalg.det(rotation)) < 0:
        raise ValueError(f"rotation: expected a proper rotation matrix (R R^T = I, det 1); |R R^T - I| = {err:.3g}")
    dtype, device = scene.means.dtype, scene.means.device
    f64 = scene.to("cpu", torch.float64)
    means = f64.means @ rotation.T
    quats = quat_mul(rotmat_to_quat(rotation), _canonical_quats(f64.quats))
    sh = f64.sh.clone()
    for l, d in enumerate(sh_rotation(rotation, scene.sh_degree), start=1):
        sh[:, l * l : (l + 1) ** 2] = torch.einsum("ij,njc->nic", d, f64.sh[:, l * l : (l + 1) ** 2])
    out = GaussianScene(means, quats, f64.log_scales, f64.opacity_logits, sh)
    return out.to(device, dtype)


# ------------------------------------------------------------------------------ .splat
def _splat_bytes(s: GaussianScene) -> bytes:
    """antimatter15's .splat rows of a float32 CPU scene with canonical quaternions."""
    key = s.log_scales.double().sum(1) + torch.nn.functional.logsigmoid(s.opacity_logits.double())
    s = s.subset(torch.argsort(-key, stable=True))  # descending volume * opacity
    rgba = torch.cat([s.sh[:, 0] * C0 + 0.5, torch.sigmoid(s.opacity_logits)[:, None]], dim=1)
    rot = s.quats / torch.linalg.norm(s.quats, dim=1, keepdim=True) * 128 + 128
    rows = np.empty(len(s), dtype=SPLAT_DTYPE)
    rows["position"] = s.means.numpy()
    rows["scale"] = torch.exp(s.log_scales).numpy()
    rows["rgba"] = (rgba * 255).clamp(0, 255).to(torch.uint8).numpy()  # truncated, as convert.py and gsplat
    rows["rot"] = rot.clamp(0, 255).to(torch.uint8).numpy()
    return rows.tobytes()


def _check_rows(path: Path, name: str, col: np.ndarray, lo: float = -math.inf, hi: float = math.inf) -> None:
    bad = np.flatnonzero(~(np.isfinite(col) & (col >= lo) & (col <= hi)).all(axis=1))
    if bad.size:
        raise ValueError(
            f"{path}: {name} of row {bad[0]} is {col[bad[0]].tolist()}; expected finite values in [{lo:g}, {hi:g}]"
        )


def read_splat(path: str | Path) -> GaussianScene:
    """A ``.splat`` file as a float32 scene: scales' logs, DC coefficients ``(c / 255 - 0.5) / C0``,
    opacity logits of ``a / 255`` (0 and 255 as -+40, ``ply.opacity_logit``), quaternions
    ``(b - 128) / 128`` (wxyz, not normalised: the renderer normalises). Errors name the file."""
    path = Path(path)
    data = path.read_bytes()
    if len(data) % SPLAT_DTYPE.itemsize:
        raise ValueError(
            f"{path}: {len(data)} bytes is not a whole number of {SPLAT_DTYPE.itemsize}-byte .splat rows "
            "(truncated, or not a .splat file)"
        )
    rows = np.frombuffer(data, dtype=SPLAT_DTYPE)
    _check_rows(path, "position", rows["position"])
    _check_rows(path, "scale", rows["scale"], lo=np.finfo(np.float32).tiny)
    log_scales = np.log(rows["scale"].astype(np.float64))
    _check_rows(path, "log(scale)", log_scales, LOG_SCALE_RANGE[0] - 1e-6, LOG_SCALE_RANGE[1] + 1e-6)
    rgba = rows["rgba"].astype(np.float64) / 255.0
    t = lambda a: torch.from_numpy(np.array(a, dtype=np.float32))  # noqa: E731
    return GaussianScene(
        t(rows["position"]),
        t((rows["rot"].astype(np.float64) - 128.0) / 128.0),
        t(log_scales),
        t(opacity_logit(rgba[:, 3])),
        t((rgba[:, None, :3] - 0.5) / C0),
    )


# ------------------------------------------------------------------------------ compressed PLY
def _morton_order(means: Tensor) -> Tensor:
    """Order of the means along a 3D Morton curve of 1024^3 cells over their bounding box (stable)."""
    lo, hi = means.amin(0), means.amax(0)
    ext = torch.where(hi > lo, hi - lo, torch.ones_like(hi))
    q = ((means - lo) / ext * 1024).floor().clamp(0, 1023).to(torch.int64)

    def spread(x: Tensor) -> Tensor:  # 10 bits -> every third bit
        x = (x | (x << 16)) & 0x030000FF
        x = (x | (x << 8)) & 0x0300F00F
        x = (x | (x << 4)) & 0x030C30C3
        return (x | (x << 2)) & 0x09249249

    code = spread(q[:, 0]) | (spread(q[:, 1]) << 1) | (spread(q[:, 2]) << 2)
    return torch.argsort(code, stable=True)


def _pack_unorm(x: Tensor, bits: int) -> Tensor:
    t = (1 << bits) - 1
    return torch.clamp((x * t + 0.5).floor(), 0, t).to(torch.int64)


def _normalise(x: Tensor, lo: Tensor, hi: Tensor) -> Tensor:
    """(x - lo) / (hi - lo) per chunk ([C, 256, D] by [C, D]); 0 where a chunk's range is empty."""
    ext = (hi - lo)[:, None]
    return torch.where(ext > 0, (x - lo[:, None]) / ext, torch.zeros_like(x))


def _pack_111011(t: Tensor) -> Tensor:
    return (_pack_unorm(t[..., 0], 11) << 21) | (_pack_unorm(t[..., 1], 10) << 11) | _pack_unorm(t[..., 2], 11)


def _pack_rotation(q: Tensor) -> Tensor:
    """ "Smallest three": index of the largest |component| (2 bits), the others 10 bits each."""
    q = q / torch.linalg.norm(q, dim=-1, keepdim=True)
    largest = torch.argmax(q.abs(), dim=-1)
    rows = torch.arange(q.shape[0])
    q = torch.where((q[rows, largest] < 0)[:, None], -q, q)
    others = torch.tensor([[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]])[largest]
    packed = _pack_unorm(q[rows[:, None], others] * (math.sqrt(2) * 0.5) + 0.5, 10)
    return (largest << 30) | (packed[:, 0] << 20) | (packed[:, 1] << 10) | packed[:, 2]


def _compressed_ply_bytes(s: GaussianScene, comments: list[str] = ()) -> bytes:
    """SuperSplat's compressed PLY of a float32 CPU scene with canonical quaternions, ``comments``
    in its header (SuperSplat writes one there too)."""
    n, k = len(s), s.sh.shape[1]
    nc = -(-n // CHUNK_SIZE)
    names = [f"{m}_{a}" for m in ("min", "max") for a in "xyz"]
    names += [f"{m}_scale_{a}" for m in ("min", "max") for a in "xyz"]
    names += [f"{m}_{c}" for m in ("min", "max") for c in "rgb"]
    header = ["ply", "format binary_little_endian 1.0", *(f"comment {c}" for c in comments), f"element chunk {nc}"]
    header += [f"property float {p}" for p in names]
    header += [f"element vertex {n}"] + [
        f"property uint packed_{p}" for p in ("position", "rotation", "scale", "color")
    ]
    if k > 1:
        header += [f"element sh {n}"] + [f"property uchar f_rest_{i}" for i in range(3 * (k - 1))]
    head = ("\n".join([*header, "end_header"]) + "\n").encode("ascii")
    if n == 0:
        return head
    s = s.subset(_morton_order(s.means))
    pad = nc * CHUNK_SIZE - n

    def chunked(x: Tensor) -> Tensor:  # [n, ...] -> [nc, 256, ...], the last chunk filled with its last row
        x = torch.cat([x, x[-1:].expand(pad, *x.shape[1:])])
        return x.reshape(nc, CHUNK_SIZE, *x.shape[1:])

    means, log_scales = chunked(s.means), chunked(s.log_scales)
    colors = chunked(s.sh[:, 0] * C0 + 0.5)
    opacities = 1 / (1 + torch.exp(-chunked(s.opacity_logits)))  # gsplat's sigmoid, bit for bit
    lo_m, hi_m = means.amin(1), means.amax(1)
    lo_s = log_scales.amin(1).clamp(-_SCALE_BOUND, _SCALE_BOUND)
    hi_s = log_scales.amax(1).clamp(-_SCALE_BOUND, _SCALE_BOUND)
    lo_c, hi_c = colors.amin(1), colors.amax(1)
    position = _pack_111011(_normalise(means, lo_m, hi_m))
    scale = _pack_111011(_normalise(log_scales, lo_s, hi_s))
    rgba = torch.cat([_normalise(colors, lo_c, hi_c), opacities[..., None]], dim=-1)
    color = (
        (_pack_unorm(rgba[..., 0], 8) << 24)
        | (_pack_unorm(rgba[..., 1], 8) << 16)
        | (_pack_unorm(rgba[..., 2], 8) << 8)
        | _pack_unorm(rgba[..., 3], 8)
    )
    vertex = torch.stack(
        [position.reshape(-1)[:n], _pack_rotation(s.quats), scale.reshape(-1)[:n], color.reshape(-1)[:n]], dim=1
    )
    chunks = torch.cat([lo_m, hi_m, lo_s, hi_s, lo_c, hi_c], dim=1)
    rest = s.sh[:, 1:].transpose(1, 2).reshape(n, -1)  # channel-major, as f_rest
    sh = ((rest / 8 + 0.5) * 256).trunc().clamp(0, 255).to(torch.uint8)
    return head + chunks.numpy().astype("<f4").tobytes() + vertex.numpy().astype("<u4").tobytes() + sh.numpy().tobytes()


# ------------------------------------------------------------------------------ public API
def _check_sh_degree(sh_degree) -> int | None:
    if sh_degree is None:
        return None
    if isinstance(sh_degree, bool) or not isinstance(sh_degree, numbers.Integral) or not 0 <= sh_degree <= 3:
        raise ValueError(f"sh_degree: expected None or an integer in 0..3, got {sh_degree!r}")
    return int(sh_degree)


def _check_path(path, fmt: str) -> Path:
    if not isinstance(path, (str, os.PathLike)):
        raise TypeError(f"path: expected a file name (str or Path), got {type(path).__name__}")
    path = Path(path)
    want = SUFFIXES[fmt]
    if path.suffix.lower() != want:
        hint = " (conventionally *.compressed.ply)" if fmt == "ply-compressed" else ""
        raise ValueError(f"path: fmt {fmt!r} writes a {want} file{hint}; got {str(path)!r}")
    if path.is_dir():
        raise ValueError(f"path: {path} is a folder; expected a file name")
    check_folder(path.parent, "path")
    return path


def export_scene(
    scene: GaussianScene,
    path: str | Path,
    *,
    fmt: Literal["ply", "splat", "ply-compressed"],
    up: UpAxis = "+z",
    sh_degree: int | None = None,
    run: str | None = None,
) -> Path:
    """Write ``scene`` to ``path`` in ``fmt`` (see the module docstring), atomically; returns the path.

    ``up``: the axis that is up in the file (``filetags.UP_AXES``: "+z", ours; "-y" for Inria /
    COLMAP-convention viewers; "+y", ...), by ``filetags.up_rotation`` and ``rotate_scene`` (SH
    rotated exactly). The file records it, and ``run`` (the id of the run the scene comes from),
    as ``filetags`` describes: PLY header comments, or a ``.splat``'s sidecar ``<path>.json``.
    ``sh_degree``: the SH degree written (``ply`` and ``ply-compressed``): higher than the scene's
    pads with zero coefficients (same colours), lower truncates (drops view-dependent colour);
    None keeps the scene's. A ``.splat`` holds no SH bands, so there it must be None or 0.
    The file name must end in the format's suffix (``SUFFIXES``: .ply, .splat, .ply); a mismatch is
    a ValueError, not a silent rename. The scene is written as float32 from any dtype or device.
    """
    if not isinstance(scene, GaussianScene):
        raise TypeError(f"scene: expected a GaussianScene, got {type(scene).__name__}")
    fmt = _choice("fmt", fmt, FORMATS)
    up = _choice("up", up, UP_AXES)
    if run is not None and (not isinstance(run, str) or not run.strip() or any(c.isspace() for c in run)):
        raise ValueError(f"run: expected None or a run id without spaces, got {run!r}")
    sh_degree = _check_sh_degree(sh_degree)
    if fmt == "splat" and sh_degree not in (None, 0):
        raise ValueError(f"sh_degree: a .splat file holds the DC colour only; expected None or 0, got {sh_degree}")
    path = _check_path(path, fmt)
    s = scene.detach().to("cpu", torch.float32)
    if sh_degree is not None:
        s = s.with_sh_degree(sh_degree)
    s = GaussianScene(s.means, _canonical_quats(s.quats), s.log_scales, s.opacity_logits, s.sh)
    if up != "+z":
        s = rotate_scene(s, up_rotation(up))
    comments = ply_comments(up, run)
    if fmt == "ply":
        return s.save_ply(path, comments=comments)
    if fmt == "ply-compressed":
        data = _compressed_ply_bytes(s, comments)
        return atomic_write(path, lambda f: f.write(data))
    data = _splat_bytes(s)
    tags = json.dumps(sidecar_json(up, run), indent=1) + "\n"
    atomic_write(sidecar(path), lambda f: f.write(tags.encode()))  # first: a .splat never lacks its tags
    return atomic_write(path, lambda f: f.write(data))


def load_scene(path: str | Path, *, up: UpAxis | None = None, flag: str = "up") -> GaussianScene:
    """A scene from any file ``export_scene`` writes: a 3DGS PLY (padded or not), a compressed PLY
    (told apart by its header, ``ply.read_ply``) or a ``.splat`` (by its name: the format has no
    header), rotated back to +Z up. ``up`` is the file's up axis; None takes the one the file
    records (``filetags.read_tags``), else +z; one that differs from the recorded one is refused
    (``filetags.resolve_up``; ``flag`` names the option in that error). Errors name the file."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"path: no file at {path}")
    up = resolve_up(path, up, flag)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic in (b"ply\n", b"ply\r"):
        scene = GaussianScene.load_ply(path)
    elif path.suffix.lower() == ".splat":
        scene = read_splat(path)
    elif path.suffix.lower() in (".glb", ".obj"):
        raise ValueError(
            f"path: {path} is a mesh, which gdbench writes for other tools but does not read; expected a 3DGS "
            "PLY, a compressed PLY or a .splat"
        )
    else:
        raise ValueError(f"{path}: neither a PLY file (no 'ply' line first) nor named *.splat")
    return scene if up == "+z" else rotate_scene(scene, up_rotation(up).T)
