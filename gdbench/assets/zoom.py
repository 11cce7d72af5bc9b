"""A change of field of view at one camera position is a zoom of the pinhole image about its
principal point: this module resamples images between fields of view exactly for a
piecewise-constant source (area resampling).

A target pixel covers an interval of the normalised image plane, ``[(2 i / n - 1) t,
(2 (i + 1) / n - 1) t]`` with ``t = tan(fov / 2)`` (principal point at the centre, pixel
centres at +0.5). Its value is the source averaged over that interval, each source pixel
weighted by the length it overlaps; whatever falls outside the source frame is background.
The 2D operator is separable, ``Y' = A_y Y A_x^T`` per channel: at equal fields of view and
an integer size ratio it is the box filter (``F.interpolate(mode="area")``), at equal sizes
the identity.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor


def zoom_matrix(n_out: int, n_in: int, scale: float) -> Tensor:
    """Area weights A [n_out, n_in] (float64) of a centred zoom along one axis.

    ``scale`` = (target half-extent) / (source half-extent) in the normalised image plane;
    rows sum to the fraction of the target pixel inside the source frame (1 when ``scale`` <= 1).
    """
    if n_out < 1 or n_in < 1:
        raise ValueError(f"n_out, n_in: expected positive sizes, got {n_out}, {n_in}")
    if not (math.isfinite(scale) and scale > 0):
        raise ValueError(f"scale: expected a positive ratio of half-extents, got {scale}")
    edges = (torch.arange(n_out + 1, dtype=torch.float64) * 2 / n_out - 1) * scale  # normalised plane
    edges = (edges + 1) * (n_in / 2)  # source pixel units, 0..n_in spans the source frame
    lo, hi = edges[:-1, None], edges[1:, None]
    j = torch.arange(n_in, dtype=torch.float64)[None]
    overlap = (torch.minimum(hi, j + 1) - torch.maximum(lo, j)).clamp_min(0)
    return overlap / (hi - lo)


def zoom_images(
    images: Tensor,
    src_fovy: float,
    dst_fovy: float,
    height: int,
    width: int,
    *,
    background: Tensor | float = 0.0,
) -> Tensor:
    """Images [V, h, w, C] seen at vertical field of view ``src_fovy`` (degrees), as a pinhole
    camera at the same position would see them at ``dst_fovy`` and ``height`` x ``width`` pixels
    (square pixels, centred principal points). Pixels beyond the source frame get ``background``."""
    if images.dim() != 4:
        raise ValueError(f"images: expected shape [V, h, w, C], got {list(images.shape)}")
    for name, f in (("src_fovy", src_fovy), ("dst_fovy", dst_fovy)):
        if not 0 < f < 180:
            raise ValueError(f"{name}: expected degrees in (0, 180), got {f}")
    _, h, w, C = images.shape
    ty_src, ty_dst = math.tan(math.radians(src_fovy) / 2), math.tan(math.radians(dst_fovy) / 2)
    sy = ty_dst / ty_src
    sx = (ty_dst * width / height) / (ty_src * w / h)
    Ay, Ax = zoom_matrix(height, h, sy), zoom_matrix(width, w, sx)
    dt = images.dtype if images.dtype in (torch.float32, torch.float64) else torch.float32
    from renderers.splat._ext import load_extension

    ext = load_extension() if images.device.type == "cpu" else None
    if ext is not None:  # the few non-zero weights per row only: ~30x faster for the prior's bank
        out = ext.zoom_taps(images.to(dt).contiguous(), *taps(Ay), *taps(Ax))
    else:
        out = _zoom_dense(images.to(dt), Ay, Ax)
    inside = Ay.sum(1)[:, None] * Ax.sum(1)[None, :]  # [height, width]
    if bool((inside < 1 - 1e-12).any()):
        bg = torch.as_tensor(background, dtype=torch.float64).reshape(-1)
        out = out + ((1 - inside)[None, :, :, None] * bg.expand(C)).to(dt)
    return out.to(images.dtype).contiguous()


def _zoom_dense(x: Tensor, Ay: Tensor, Ax: Tensor) -> Tensor:
    """``A_y Y A_x^T`` per image and channel as two dense matrix products in ``x``'s precision
    (the weights are exact in float64 and lose nothing that matters when rounded to float32):
    rows, then columns. The path without the C++ extension, and the tests' oracle for it."""
    V, h, w, C = x.shape
    height, width = Ay.shape[0], Ax.shape[0]
    dt = x.dtype
    x = x.permute(0, 3, 2, 1).reshape(V * C * w, h)  # rows of h
    rows = (x @ Ay.to(dt).T).reshape(V, C, w, height).transpose(2, 3).reshape(V * C * height, w)
    return (rows @ Ax.to(dt).T).reshape(V, C, height, width).permute(0, 2, 3, 1)  # [V, height, width, C]


def taps(A: Tensor) -> tuple[Tensor, Tensor]:
    """A's non-zero entries per row as taps: indices [n_out, K] (int64) and weights [n_out, K]
    (float64), K the most any row has; a row's overlap with the source is one run of columns,
    and the padding taps past the source's end get weight 0."""
    nz = A != 0
    first = nz.to(torch.int64).argmax(1)
    K = max(int(nz.sum(1).max()), 1)
    idx = first[:, None] + torch.arange(K)[None]
    inside = idx < A.shape[1]
    idx = torch.where(inside, idx, torch.zeros_like(idx))
    return idx.contiguous(), torch.where(inside, torch.gather(A, 1, idx), torch.zeros((), dtype=A.dtype)).contiguous()
