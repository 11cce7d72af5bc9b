"""A renderer written outside gdbench, checked through its public protocol only: gsplat 1.5.3's own
torch stages (projection, covariance) with a dense front-to-back compositor that follows gsplat's
CUDA kernel (alpha = min(0.999, o exp(-sigma)), skipped below 1/255, a pixel done once its
transmittance would fall below 1e-4). It imports nothing from gdbench but the protocol's spec.

    gdbench compare --renderer docs/examples/gsplat_renderer.py:SPEC
    gdbench bench stability --renderer docs/examples/gsplat_renderer.py:SPEC
    gdbench conformance --renderer docs/examples/gsplat_renderer.py:SPEC --out report/
    pytest --gdbench-renderer docs/examples/gsplat_renderer.py:SPEC

(docs/references.md, "Bring your own renderer".)
"""

from __future__ import annotations

from types import SimpleNamespace

import torch

from gdbench.refcheck.protocol import RendererSpec

ALPHA_MAX, ALPHA_MIN, T_DONE = 0.999, 1.0 / 255.0, 1e-4


def rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, background=None,
              outputs=("rgb", "alpha"), pixel_chunk=1024):  # fmt: skip
    """RGB colours [N, 3]; returns rgb [C, H, W, 3] and alpha [C, H, W, 1], differentiable."""
    from gsplat.cuda import _torch_impl as ti

    covars, _ = ti._quat_scale_to_covar_preci(quats, scales, compute_covar=True, compute_preci=False, triu=False)
    radii, means2d, depths, conics, _ = ti._fully_fused_projection(means, covars, viewmats, Ks, width, height)
    ys, xs = torch.meshgrid(torch.arange(height), torch.arange(width), indexing="ij")
    pix = torch.stack([xs, ys], -1).reshape(-1, 2).to(means) + 0.5
    rgbs, alphas = [], []
    for c in range(viewmats.shape[0]):
        keep = (radii[c] > 0).all(-1) if radii.dim() == 3 else radii[c] > 0
        ids = torch.nonzero(keep).squeeze(1)
        ids = ids[torch.argsort(depths[c, ids], stable=True)]  # front to back
        m, q, o, col = means2d[c, ids], conics[c, ids], opacities[ids], colors[ids]
        rgb_c, alpha_c = [], []
        for p0 in range(0, pix.shape[0], pixel_chunk):
            d = pix[p0 : p0 + pixel_chunk, None, :] - m[None]  # [P, n, 2]
            sigma = 0.5 * (q[..., 0] * d[..., 0] ** 2 + q[..., 2] * d[..., 1] ** 2) + q[..., 1] * d[..., 0] * d[..., 1]
            a = torch.clamp_max(o * torch.exp(-sigma), ALPHA_MAX)
            a = torch.where((sigma >= 0) & (a >= ALPHA_MIN), a, torch.zeros_like(a))
            with torch.no_grad():
                live = torch.cumprod(1 - a, 1) > T_DONE
            a = torch.where(live, a, torch.zeros_like(a))
            T = torch.cumprod(torch.cat([a.new_ones(a.shape[0], 1), 1 - a], 1), 1)
            rgb_c.append((a * T[:, :-1]) @ col)
            alpha_c.append(1 - T[:, -1:])
        rgb, alpha = torch.cat(rgb_c), torch.cat(alpha_c)
        if background is not None:
            rgb = rgb + (1 - alpha) * background
        rgbs.append(rgb.reshape(height, width, 3))
        alphas.append(alpha.reshape(height, width, 1))
    return SimpleNamespace(rgb=torch.stack(rgbs), alpha=torch.stack(alphas))


SPEC = RendererSpec("gsplat_example", rasterize, colors="rgb", gradients=True, tolerance="exact", alpha_max=ALPHA_MAX)
"""What it supports: RGB colours, CPU, gradients, gsplat's alpha clamp; judged as an exact rasterizer."""
