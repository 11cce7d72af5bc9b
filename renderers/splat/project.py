"""Stage 1: EWA projection of 3D Gaussians to screen-space ellipses.

Conventions (docs/conventions.md): OpenCV camera (x right, y down, z forward),
world-to-camera ``viewmats`` [4,4], intrinsics ``Ks`` [3,3] in pixels, pixel centres at
``+0.5``, quaternions wxyz.

For Gaussian i seen by camera c (rotation W, translation t):

    mu_c     = W mu + t                         (camera-space mean, depth z = mu_c.z)
    mean2d   = (fx x/z + cx, fy y/z + cy)
    J        = [[fx/z, 0, -fx tx/z^2], [0, fy/z, -fy ty/z^2]]
               with tx = z * clamp(x/z, -(cx/fx + 0.3 tan_fovx), (W-cx)/fx + 0.3 tan_fovx)
               (gsplat's 1.3 tan-fov clamp; same for y)
    Sigma'   = (J W R S)(J W R S)^T + eps2d I
    conic    = Sigma'^-1 stored as (A, B, C):  power(d) = -1/2 (A dx^2 + 2 B dx dy + C dy^2)

det(Sigma') is computed with Lagrange's identity |t1 x t2|^2 + eps2d (|t1|^2 + |t2|^2) + eps2d^2
(t1, t2 the rows of J W R S), which is positive by construction instead of a difference of
two large numbers, so stiff covariances (condition number 1e8) keep a finite conic.

Culling: a Gaussian is visible in a camera when near_plane < z < far_plane, its opacity is at
least ``alpha_min`` and its screen extent touches the image. The extent is opacity-aware:
every pixel with ``o * exp(power) >= alpha_min`` lies within ``radius = sqrt(2 ln(o / alpha_min))
* sqrt(diag(Sigma'))`` of the mean (per axis, the exact bounding box of that ellipse), so the
tiled renderer is exact with respect to the dense formula. Culled entries have radius 0.
"""

from __future__ import annotations

from typing import NamedTuple

import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from torch import Tensor

QUAT_EPS = 1e-12


class Projection(NamedTuple):
    """Per (camera, Gaussian) screen-space quantities. ``*B C`` leading dims."""

    means2d: Float[Tensor, "*B C N 2"]
    """Projected means in pixels (pixel centres at +0.5)."""
    conics: Float[Tensor, "*B C N 3"]
    """Inverse 2D covariance (A, B, C); power = -1/2 (A dx^2 + 2 B dx dy + C dy^2)."""
    depths: Float[Tensor, "*B C N"]
    """Camera-space z of the mean."""
    radii: Float[Tensor, "*B C N 2"]
    """Half-extent in x and y of the alpha >= alpha_min ellipse, 0 when culled."""
    visible: Bool[Tensor, "*B C N"]
    """True where the Gaussian can touch a pixel of the camera."""


def normalize_quats(quats: Float[Tensor, "*B N 4"]) -> Float[Tensor, "*B N 4"]:
    """Unit quaternions; a (near-)zero quaternion becomes the identity with zero gradient."""
    norm = torch.linalg.vector_norm(quats, dim=-1, keepdim=True)
    ok = norm > QUAT_EPS
    identity = torch.zeros_like(quats)
    identity[..., 0] = 1.0
    return torch.where(ok, quats / torch.where(ok, norm, torch.ones_like(norm)), identity)


def quat_to_rotmat(quats: Float[Tensor, "*B 4"]) -> Float[Tensor, "*B 3 3"]:
    """Rotation matrix of unit quaternions (w, x, y, z)."""
    w, x, y, z = quats.unbind(-1)
    rows = [
        1 - 2 * (y * y + z * z),
        2 * (x * y - w * z),
        2 * (x * z + w * y),
        2 * (x * y + w * z),
        1 - 2 * (x * x + z * z),
        2 * (y * z - w * x),
        2 * (x * z - w * y),
        2 * (y * z + w * x),
        1 - 2 * (x * x + y * y),
    ]
    return torch.stack(rows, dim=-1).reshape(quats.shape[:-1] + (3, 3))


def covariance_factor(quats: Float[Tensor, "*B N 4"], scales: Float[Tensor, "*B N 3"]) -> Float[Tensor, "*B N 3 3"]:
    """M = R(q) diag(s), so that Sigma = M M^T."""
    return quat_to_rotmat(normalize_quats(quats)) * scales[..., None, :]


def project(
    means: Float[Tensor, "*B N 3"],
    quats: Float[Tensor, "*B N 4"],
    scales: Float[Tensor, "*B N 3"],
    opacities: Float[Tensor, "*B N"],
    viewmats: Float[Tensor, "*B C 4 4"],
    Ks: Float[Tensor, "*B C 3 3"],
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    alpha_min: float = 1.0 / 255.0,
) -> Projection:
    """EWA-project N Gaussians into C cameras (inputs already checked by ``rasterize``)."""
    R = viewmats[..., :3, :3]  # [*B, C, 3, 3]
    t = viewmats[..., :3, 3]  # [*B, C, 3]
    means_c = torch.einsum("...cij,...nj->...cni", R, means) + t[..., :, None, :]
    x, y, z = means_c.unbind(-1)  # [*B, C, N]

    valid_z = (z > near_plane) & (z < far_plane)
    zs = torch.where(valid_z, z, torch.ones_like(z))  # safe divisor: no inf/NaN leaks into grads

    fx = Ks[..., 0, 0, None]
    fy = Ks[..., 1, 1, None]
    cx = Ks[..., 0, 2, None]
    cy = Ks[..., 1, 2, None]
    means2d = torch.stack([fx * x / zs + cx, fy * y / zs + cy], dim=-1)

    tan_fovx = 0.5 * width / fx
    tan_fovy = 0.5 * height / fy
    tx = zs * torch.clamp(x / zs, min=-(cx / fx + 0.3 * tan_fovx), max=(width - cx) / fx + 0.3 * tan_fovx)
    ty = zs * torch.clamp(y / zs, min=-(cy / fy + 0.3 * tan_fovy), max=(height - cy) / fy + 0.3 * tan_fovy)
    zero = torch.zeros_like(zs)
    J = torch.stack([fx / zs, zero, -fx * tx / (zs * zs), zero, fy / zs, -fy * ty / (zs * zs)], dim=-1).reshape(
        zs.shape + (2, 3)
    )

    M = covariance_factor(quats, scales)  # [*B, N, 3, 3]
    T = J @ (R[..., :, None, :, :] @ M[..., None, :, :, :])  # [*B, C, N, 2, 3]
    t1, t2 = T.unbind(-2)
    a = (t1 * t1).sum(-1) + eps2d
    c = (t2 * t2).sum(-1) + eps2d
    b = (t1 * t2).sum(-1)
    cross = torch.linalg.cross(t1, t2)
    det = (cross * cross).sum(-1) + eps2d * (a + c - eps2d)  # = a c - b^2, exactly
    conics = torch.stack([c / det, -b / det, a / det], dim=-1)

    o = opacities[..., None, :].expand_as(z)
    ratio = torch.where(o >= alpha_min, o / alpha_min, torch.ones_like(o))
    extend = torch.sqrt(2.0 * torch.log(ratio))
    radii = extend[..., None] * torch.sqrt(torch.stack([a, c], dim=-1))

    inside = (
        (means2d[..., 0] + radii[..., 0] > 0)
        & (means2d[..., 0] - radii[..., 0] < width)
        & (means2d[..., 1] + radii[..., 1] > 0)
        & (means2d[..., 1] - radii[..., 1] < height)
    )
    visible = valid_z & (o >= alpha_min) & inside & torch.isfinite(conics).all(-1)
    radii = torch.where(visible[..., None], radii, torch.zeros_like(radii)).detach()
    return Projection(means2d, conics, z, radii, visible)


def view_dirs(means: Float[Tensor, "*B N 3"], viewmats: Float[Tensor, "*B C 4 4"]) -> Float[Tensor, "*B C N 3"]:
    """Unit directions from each camera centre to each Gaussian mean (for SH colour)."""
    R = viewmats[..., :3, :3]
    t = viewmats[..., :3, 3]
    campos = -torch.einsum("...ji,...j->...i", R, t)  # -R^T t, [*B, C, 3]
    return F.normalize(means[..., None, :, :] - campos[..., :, None, :], dim=-1)


class _ProjectCPU(torch.autograd.Function):
    """``project`` by the C++ extension (``csrc/project_cpu.cpp``), with its hand-written backward
    (gradients reach means, quats and scales; radii and visibility carry none). The inputs are
    flattened to the kernel's [Bt, N, .] and the outputs shaped [*B, C, N, .] inside the Function,
    so those views are no autograd nodes (a training step walked ~11 of them)."""

    @staticmethod
    def forward(ctx, means, quats, scales, opacities, viewmats, Ks, settings, lead):  # type: ignore[override]
        from ._ext import load_extension

        flat = _flatten(means, quats, scales, opacities, viewmats, Ks)
        outs = load_extension().project_forward(*flat, *settings)
        ctx.save_for_backward(*flat[:3], *flat[4:])
        ctx.settings, ctx.shapes = settings, (means.shape, quats.shape, scales.shape)
        m2d, con, dep, rad, vis = _shape_outputs(outs, lead)
        ctx.mark_non_differentiable(rad, vis)
        return m2d, con, dep, rad, vis

    @staticmethod
    def backward(ctx, g_m2d, g_con, g_dep, _g_rad, _g_vis):  # type: ignore[override]
        from ._ext import load_extension

        means, quats, scales, viewmats, Ks = ctx.saved_tensors
        empty = means.new_zeros(0)
        grads = (g.contiguous() if g is not None else empty for g in (g_m2d, g_con, g_dep))
        gm, gq, gs = load_extension().project_backward(means, quats, scales, viewmats, Ks, *ctx.settings, *grads)
        sm, sq, ss = ctx.shapes
        return gm.reshape(sm), gq.reshape(sq), gs.reshape(ss), None, None, None, None, None


def _flatten(means, quats, scales, opacities, viewmats, Ks) -> tuple[Tensor, ...]:
    """The kernel's contiguous [Bt, N, .] and [Bt, C, ., .] views of ``project_cpu``'s inputs."""
    N, C = means.shape[-2], viewmats.shape[-3]
    Bt = int(torch.Size(means.shape[:-2]).numel())
    return (
        means.reshape(Bt, N, 3).contiguous(),
        quats.reshape(Bt, N, 4).contiguous(),
        scales.reshape(Bt, N, 3).contiguous(),
        opacities.reshape(Bt, N).contiguous(),
        viewmats.reshape(Bt, C, 4, 4).contiguous(),
        Ks.reshape(Bt, C, 3, 3).contiguous(),
    )


def _shape_outputs(outs, lead: tuple[int, ...]) -> tuple[Tensor, ...]:
    m2d, con, dep, rad, vis = outs
    return (
        m2d.reshape(lead + (2,)),
        con.reshape(lead + (3,)),
        dep.reshape(lead),
        rad.reshape(lead + (2,)),
        vis.reshape(lead),
    )


def project_cpu(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    alpha_min: float = 1.0 / 255.0,
) -> Projection:
    """``project`` fused in C++ (CPU tensors; the C++ extension must be loaded). Same results as
    ``project`` to float rounding; gradients for means, quats and scales only (not the cameras)."""
    lead = tuple(means.shape[:-2]) + (viewmats.shape[-3], means.shape[-2])
    settings = (width, height, near_plane, far_plane, eps2d, alpha_min)
    if torch.is_grad_enabled() and any(t.requires_grad for t in (means, quats, scales)):
        return Projection(*_ProjectCPU.apply(means, quats, scales, opacities, viewmats, Ks, settings, lead))
    # nothing to differentiate: the kernel without the autograd Function's bookkeeping
    from ._ext import load_extension

    flat = _flatten(means, quats, scales, opacities, viewmats, Ks)
    return Projection(*_shape_outputs(load_extension().project_forward(*flat, *settings), lead))
