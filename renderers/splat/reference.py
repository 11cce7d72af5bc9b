"""The slow, obviously-correct twin of ``rasterize``: dense, all pairs, float64 by default.

No tiles, no radii, no chunked backward: every Gaussian is evaluated at every pixel and
gradients come from autograd. It shares with the fast path only the SH basis (``sh.py``, tested
on its own against scipy), the settings object and the two-line finishing step (background
through T, depth normalised by alpha: ``composite.finish_images``). It is the oracle of the tests and the dense
baseline of the benchmark (``dtype=torch.float32`` there). Memory is O(N x H x W) per
image unless ``pixel_chunk`` bounds the pixels evaluated at once.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from ._checks import check_outputs
from .composite import finish_images
from .rasterize import RenderOutput
from .settings import RasterSettings, resolve_settings
from .sh import eval_sh


def _rotation(q: Tensor) -> Tensor:
    """Rotation matrix of a quaternion (w, x, y, z) of any norm; zero means identity."""
    n = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    ok = n > 1e-12
    unit = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=q.dtype, device=q.device).expand_as(q)
    q = torch.where(ok, q / torch.where(ok, n, torch.ones_like(n)), unit)
    w, x, y, z = q.unbind(-1)
    R = torch.stack(
        [
            torch.stack([w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
            torch.stack([2 * (x * y + w * z), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)], -1),
            torch.stack([2 * (x * z - w * y), 2 * (y * z + w * x), w * w - x * x - y * y + z * z], -1),
        ],
        -2,
    )
    return R


def project_reference(means, quats, scales, viewmat, K, width, height, *, near_plane=0.01, far_plane=1e10, eps2d=0.3):
    """EWA projection of N Gaussians into one camera, written out plainly.

    Returns (mean2d [N, 2], cov2d [N, 2, 2] including eps2d, z [N], in_range [N]).
    """
    Wr, t = viewmat[:3, :3], viewmat[:3, 3]
    mc = means @ Wr.T + t  # camera-space means [N, 3]
    x, y, z = mc.unbind(-1)
    fx, fy, cx, cy = K[0, 0], K[1, 1], K[0, 2], K[1, 2]
    ok = (z > near_plane) & (z < far_plane)
    z1 = torch.where(ok, z, torch.ones_like(z))

    # 3D covariance R S S^T R^T, rotated into the camera, pushed through the Jacobian.
    R = _rotation(quats)
    S = torch.diag_embed(scales)
    cov3 = R @ S @ S @ R.transpose(-1, -2)
    cov_cam = Wr @ cov3 @ Wr.T
    limx = 0.3 * 0.5 * width / fx
    limy = 0.3 * 0.5 * height / fy
    u = torch.clamp(x / z1, min=-(cx / fx + limx), max=(width - cx) / fx + limx)
    v = torch.clamp(y / z1, min=-(cy / fy + limy), max=(height - cy) / fy + limy)
    J = torch.zeros(means.shape[0], 2, 3, dtype=means.dtype, device=means.device)
    J[:, 0, 0] = fx / z1
    J[:, 0, 2] = -fx * u / z1
    J[:, 1, 1] = fy / z1
    J[:, 1, 2] = -fy * v / z1
    cov2 = J @ cov_cam @ J.transpose(-1, -2) + eps2d * torch.eye(2, dtype=means.dtype, device=means.device)
    mean2 = torch.stack([fx * x / z1 + cx, fy * y / z1 + cy], -1)
    return mean2, cov2, z, ok


def render_image(
    means,
    quats,
    scales,
    opacities,
    feats,
    viewmat,
    K,
    width,
    height,
    *,
    background=None,
    near_plane=0.01,
    far_plane=1e10,
    eps2d=0.3,
    alpha_min=1.0 / 255.0,
    alpha_max=0.99,
    t_min=1e-4,
    pixel_chunk=None,
) -> dict[str, Tensor]:
    """One camera, N Gaussians with per-Gaussian features [N, D]; returns [H, W, *] images."""
    mean2, cov2, z, ok = project_reference(
        means, quats, scales, viewmat, K, width, height, near_plane=near_plane, far_plane=far_plane, eps2d=eps2d
    )
    prec = torch.linalg.inv(cov2)  # [N, 2, 2]

    order = torch.sort(torch.where(ok, z, torch.full_like(z, float("inf"))).detach(), stable=True).indices
    mean2, prec, o, f, zz, ok = mean2[order], prec[order], opacities[order], feats[order], z[order], ok[order]

    ys, xs = torch.meshgrid(
        torch.arange(height, dtype=means.dtype, device=means.device) + 0.5,
        torch.arange(width, dtype=means.dtype, device=means.device) + 0.5,
        indexing="ij",
    )
    pix = torch.stack([xs, ys], -1).reshape(-1, 2)
    step = pixel_chunk or pix.shape[0]
    parts: dict[str, list[Tensor]] = {"rgb": [], "T": [], "depth": [], "wsq": []}
    for s in range(0, pix.shape[0], step):
        d = pix[None, s : s + step, :] - mean2[:, None, :]  # [N, P, 2]
        maha = torch.einsum("npi,nij,npj->np", d, prec, d)
        alpha = torch.clamp(o[:, None] * torch.exp(-0.5 * maha), max=alpha_max)
        alpha = torch.where((alpha >= alpha_min) & ok[:, None], alpha, torch.zeros_like(alpha))
        with torch.no_grad():
            kept = torch.cumprod(1 - alpha, 0) >= t_min
        alpha = torch.where(kept, alpha, torch.zeros_like(alpha))
        T_incl = torch.cumprod(1 - alpha, 0)
        T = torch.cat([torch.ones_like(T_incl[:1]), T_incl[:-1]], 0)
        w = alpha * T  # [N, P]
        parts["rgb"].append(w.T @ f)
        parts["T"].append(T_incl[-1] if w.shape[0] else torch.ones_like(pix[s : s + step, 0]))
        parts["depth"].append(w.T @ zz)
        parts["wsq"].append((w * w).sum(0))
    rgb, T, dep, wsq = (torch.cat(parts[k], 0).reshape(height, width, -1) for k in ("rgb", "T", "depth", "wsq"))
    rgb, alpha, depth = finish_images(rgb, T, dep, background)
    return {"rgb": rgb, "alpha": alpha, "depth": depth, "weight_sq": wsq}


def rasterize_reference(
    means,
    quats,
    scales,
    opacities,
    colors,
    viewmats,
    Ks,
    width,
    height,
    *,
    sh_degree=None,
    background=None,
    outputs: Sequence[str] = ("rgb", "alpha"),
    dtype: torch.dtype | None = torch.float64,
    pixel_chunk: int | None = None,
    settings: RasterSettings | None = None,
    **overrides,
) -> RenderOutput:
    """Same call as ``renderers.splat.rasterize``; computed densely in ``dtype`` (None keeps the input's).

    Gradients flow back to the inputs in their own dtype. Returns image outputs only
    (rgb, alpha, depth, weight_sq), in ``dtype``. Of the settings it uses the image-formation
    constants (tiles, chunks and backends do not exist here).
    """
    st = resolve_settings(settings, overrides)
    outputs = check_outputs(outputs)
    constants = st.projection() | {"alpha_max": st.alpha_max, "t_min": st.t_min}
    cast = (lambda x: x.to(dtype)) if dtype is not None else (lambda x: x)
    batch = means.shape[:-2]
    C = viewmats.shape[-3]
    nb = int(torch.Size(batch).numel())
    per_camera = colors.dim() == len(batch) + (4 if sh_degree is not None else 3)

    def at(x: Tensor, b: int) -> Tensor:
        return cast(x.reshape((nb,) + x.shape[len(batch) :])[b])

    images: dict[str, list[Tensor]] = {k: [] for k in ("rgb", "alpha", "depth", "weight_sq")}
    for b in range(nb):
        m, q, s, o = at(means, b), at(quats, b), at(scales, b), at(opacities, b)
        col = at(colors, b)
        vm, ks = at(viewmats, b), at(Ks, b)
        for c in range(C):
            cb = col[c] if per_camera else col
            if sh_degree is not None:
                campos = -vm[c, :3, :3].T @ vm[c, :3, 3]
                dirs = torch.nn.functional.normalize(m - campos, dim=-1)
                feats = eval_sh(sh_degree, cb, dirs)
            else:
                feats = cb
            bg = None
            if background is not None:
                bg = cast(background) if background.dim() == 1 else at(background, b)[c]
            out = render_image(
                m,
                q,
                s,
                o,
                feats,
                vm[c],
                ks[c],
                width,
                height,
                background=bg,
                pixel_chunk=pixel_chunk,
                **constants,
            )
            for k in images:
                images[k].append(out[k])
    shape = batch + (C, height, width)
    result = {}
    for k in ("rgb", "alpha", "depth", "weight_sq"):
        if k in outputs:
            stacked = torch.stack(images[k], 0) if images[k] else None
            result[k] = stacked.reshape(shape + stacked.shape[-1:]) if stacked is not None else None
    return RenderOutput(**result)
