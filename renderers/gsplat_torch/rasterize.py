"""gsplat's torch stages, completed to run on CPU (see the package docstring)."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from renderers.splat import RenderOutput
from renderers.splat.composite import finish_images

ALPHA_MAX = 0.999
"""gsplat's clamp (RasterizeToPixels3DGSFwd.cu); the Inria kernel and ours default to 0.99."""
ALPHA_MIN = 1.0 / 255.0
T_DONE = 1e-4


def _gsplat():
    try:
        from gsplat.cuda import _torch_impl
    except ImportError as e:
        raise ImportError("the gsplat peer needs gsplat: pip install gsplat==1.5.3 (no CUDA needed)") from e
    return _torch_impl


def _composite(
    means2d,
    conics,
    opacities,
    colors,
    depths,
    offsets,
    flatten_ids,
    width,
    height,
    tile_size,
    want_depth: bool,
    want_wsq: bool,
    tiles_per_chunk: int = 64,
):
    """Front-to-back blending per tile with autograd; inputs flattened over images (I*N)."""
    I, th, tw = offsets.shape
    device, dtype = means2d.device, means2d.dtype
    if means2d.shape[0] == 0:  # empty scene: one inert row to index (every lane is masked by `valid`)
        pad = lambda x: torch.cat([x, x.new_zeros((1, *x.shape[1:]))])  # noqa: E731
        means2d, conics, opacities, colors, depths = map(pad, (means2d, conics, opacities, colors, depths))
    M = flatten_ids.numel()
    starts = offsets.reshape(-1).long()
    ends = torch.cat([starts[1:], torch.tensor([M], device=device)])
    D = colors.shape[-1]
    area = tile_size * tile_size
    lane = torch.arange(area, device=device)
    feats, trans, deps, wsqs = [], [], [], []
    n_tiles = I * th * tw
    for c0 in range(0, n_tiles, tiles_per_chunk):
        t = torch.arange(c0, min(c0 + tiles_per_chunk, n_tiles), device=device)
        cnt = ends[t] - starts[t]
        L = max(int(cnt.max()) if cnt.numel() else 0, 1)
        k = torch.arange(L, device=device)
        valid = k[None] < cnt[:, None]
        if M:
            pos = torch.where(valid, starts[t][:, None] + k[None], torch.zeros_like(k)[None]).clamp_max(M - 1)
            g = flatten_ids.long()[pos]
        else:
            g = torch.zeros(len(t), L, dtype=torch.long, device=device)
        local = t % (th * tw)
        px = ((local % tw)[:, None] * tile_size + lane % tile_size).to(dtype) + 0.5
        py = ((local // tw)[:, None] * tile_size + lane // tile_size).to(dtype) + 0.5
        dx = px[:, None, :] - means2d[g][..., 0:1]
        dy = py[:, None, :] - means2d[g][..., 1:2]
        c = conics[g]
        sigma = 0.5 * (c[..., 0:1] * dx * dx + c[..., 2:3] * dy * dy) + c[..., 1:2] * dx * dy
        alpha = torch.clamp_max(opacities[g][..., None] * torch.exp(-sigma), ALPHA_MAX)
        ok = valid[..., None] & (sigma >= 0) & (alpha >= ALPHA_MIN)
        alpha = torch.where(ok, alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            keep = torch.cumprod(1 - alpha, dim=1) > T_DONE  # the Gaussian reaching T <= 1e-4 is excluded
        alpha = torch.where(keep, alpha, torch.zeros_like(alpha))
        T_incl = torch.cumprod(1 - alpha, dim=1)
        T = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
        w = alpha * T
        feats.append(torch.einsum("tlp,tld->tpd", w, colors[g]))
        trans.append(T_incl[:, -1])
        if want_depth:
            deps.append(torch.einsum("tlp,tl->tp", w, depths[g]))
        if want_wsq:
            wsqs.append((w * w).sum(1))

    def untile(parts, ch):
        x = torch.cat(parts).reshape(I, th, tw, tile_size, tile_size, ch).permute(0, 1, 3, 2, 4, 5)
        return x.reshape(I, th * tile_size, tw * tile_size, ch)[:, :height, :width]

    return (
        untile(feats, D),
        untile([x[..., None] for x in trans], 1),
        untile([x[..., None] for x in deps], 1) if want_depth else None,
        untile([x[..., None] for x in wsqs], 1) if want_wsq else None,
    )


def rasterize(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    background: Tensor | None = None,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    outputs: Sequence[str] = ("rgb", "alpha"),
    tile_size: int = 16,
) -> RenderOutput:
    """gsplat's image formation for C cameras ([N] Gaussians, [C] cameras, no batch dims)."""
    ti = _gsplat()
    if means.dim() != 2:
        raise ValueError(f"means: the gsplat peer takes [N, 3] (no batch dims), got {list(means.shape)}")
    N, C = means.shape[0], viewmats.shape[0]
    covars, _ = ti._quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False, triu=False)
    radii, means2d, depths, conics, _ = ti._fully_fused_projection(
        means, covars, viewmats, Ks, width, height, eps2d=eps2d, near_plane=near_plane, far_plane=far_plane
    )
    if sh_degree is not None:
        campos = torch.linalg.inv(viewmats)[:, :3, 3]
        dirs = means[None] - campos[:, None]
        coeffs = colors if colors.dim() == 4 else colors[None].expand(C, *colors.shape)
        feats = torch.clamp_min(ti._spherical_harmonics(sh_degree, dirs, coeffs) + 0.5, 0.0)
    else:
        feats = colors if colors.dim() == 3 else colors[None].expand(C, *colors.shape)
    tw, th = math.ceil(width / tile_size), math.ceil(height / tile_size)
    _, isect_ids, flatten_ids = ti._isect_tiles(means2d, radii, depths, tile_size, tw, th, sort=True)
    offsets = ti._isect_offset_encode(isect_ids, C, tw, th)
    want = set(outputs)
    rgb, T, dep, wsq = _composite(
        means2d.reshape(C * N, 2),
        conics.reshape(C * N, 3),
        opacities[None].expand(C, N).reshape(C * N),
        feats.reshape(C * N, feats.shape[-1]),  # (explicit: -1 is ambiguous when N = 0)
        depths.reshape(C * N),
        offsets,
        flatten_ids,
        width,
        height,
        tile_size,
        "depth" in want,
        "weight_sq" in want,
    )
    rgb, alpha, dep = finish_images(rgb, T, dep, background)
    out = {"rgb": rgb if "rgb" in want else None, "alpha": alpha if "alpha" in want else None}
    if dep is not None:
        out["depth"] = dep
    if wsq is not None:
        out["weight_sq"] = wsq
    if "means2d" in want:
        out["means2d"] = means2d
    if "radii" in want:
        out["radii"] = radii.to(means.dtype)
    return RenderOutput(**out)
