"""Ray-traced Gaussians: Mitsuba's ``ellipsoids`` shape with the ``volprim_rf_basic`` integrator.

Per ray, the integrator visits the ellipsoid shells (``extent`` = 3 sigma) in hit order and
blends each Gaussian's peak response along the ray, alpha = min(o G(t_peak), 0.9999), with SH
colour max(0, sum Y(d) f + 0.5) evaluated along the ray direction; it stops once the path
throughput falls below 0.01. Compared with splatting this removes the affine projection and
the per-Gaussian sort order, but has no 2D low-pass (eps2d) and a looser termination; see
docs/references.md. Pixels are box-filtered with ``spp`` random samples.

alpha comes from a second render in which every Gaussian emits 1 (there is no background in
the integrator, so that render is exactly 1 - T). Gradients reach torch through
``drjit.wrap``.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from renderers.splat import RenderOutput
from renderers.splat.sh import C0

from ._lib import import_mitsuba, mitsuba_cameras, sensor_dict


def _scene(mi, cam: dict, n: int, k: int, spp: int, extent: float, max_depth: int):
    z = lambda *shape: mi.TensorXf(torch.zeros(*shape).numpy())  # noqa: E731
    q = torch.zeros(n, 4)
    q[:, 3] = 1
    return mi.load_dict({
        "type": "scene",
        "integrator": {"type": "volprim_rf_basic", "max_depth": max_depth, "srgb_primitives": False},
        "sensor": sensor_dict(mi, cam, spp),
        "primitives": {"type": "ellipsoids", "centers": z(n, 3), "scales": mi.TensorXf(torch.ones(n, 3).numpy()),
                       "quaternions": mi.TensorXf(q.numpy()), "opacities": z(n, 1), "sh_coeffs": z(n, 3 * k),
                       "extent": extent},
    })  # fmt: skip


def _wrapped(mi, dr, scene, spp: int, seed: int):
    """A torch-callable render of ``scene`` (data, opacities, sh) -> image, differentiable."""
    params = mi.traverse(scene)

    @dr.wrap(source="torch", target="drjit")
    def render(d, o, c):
        params["primitives.data"] = d.array  # flat storage of the (N, 10) tensor
        params["primitives.opacities"] = o.array
        params["primitives.sh_coeffs"] = c.array
        params.update()
        return mi.render(scene, params, spp=spp, seed=seed)

    return render


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
    outputs: Sequence[str] = ("rgb", "alpha"),
    spp: int = 64,
    extent: float = 3.0,
    max_depth: int = 256,
    seed: int = 0,
) -> RenderOutput:
    """Same call shape as ``renderers.splat.rasterize`` (no batch dims): rgb and alpha [C, H, W, *]."""
    mi, dr = import_mitsuba()

    N = means.shape[0]
    if N == 0:  # Mitsuba cannot build an empty ellipsoids shape: the image is the background
        C = viewmats.shape[0]
        zero = sum(t.sum() for t in (means, quats, scales, opacities, colors)) * 0  # keeps the graph
        alpha = torch.zeros(C, height, width, 1, dtype=means.dtype) + zero
        bg = torch.zeros(3, dtype=means.dtype) if background is None else background
        rgb = alpha + (bg if bg.dim() == 1 else bg[:, None, None, :])
        return RenderOutput(rgb=rgb if "rgb" in outputs else None, alpha=alpha if "alpha" in outputs else None)
    if sh_degree is None:
        sh = ((colors - 0.5) / C0)[:, None, :]
    else:
        sh = colors[:, : (sh_degree + 1) ** 2, :]
    K = sh.shape[1]
    q = quats / quats.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    xyzw = torch.cat([q[:, 1:], q[:, :1]], 1)
    data = torch.cat([means, scales, xyzw], 1)  # the shape's (N, 10) layout
    cams = mitsuba_cameras(viewmats.float(), Ks.float(), width, height)
    unit = torch.zeros(N, K, 3)
    unit[:, 0] = 0.5 / C0  # emission exactly 1: that render is alpha
    rgbs, alphas = [], []
    flat_sh = sh.reshape(N, 3 * K).float().contiguous()  # coefficient-major, RGB interleaved: (k * 3 + channel)
    flat_unit = unit.reshape(N, 3 * K).float().contiguous()
    d, o = data.float().contiguous(), opacities.float()[:, None].contiguous()
    want_alpha = "alpha" in outputs or background is not None
    for i, cam in enumerate(cams):
        # one scene per render: Dr.Jit replays a render in its backward pass, so two renders must
        # never share the scene whose parameters the other one overwrites
        rgbs.append(_wrapped(mi, dr, _scene(mi, cam, N, K, spp, extent, max_depth), spp, seed + i)(d, o, flat_sh))
        if want_alpha:
            scene = _scene(mi, cam, N, K, spp, extent, max_depth)
            alphas.append(_wrapped(mi, dr, scene, spp, seed + i)(d, o, flat_unit)[..., :1])
    rgb = torch.stack(rgbs).to(means.dtype)
    alpha = torch.stack(alphas).to(means.dtype) if alphas else None
    if background is not None:
        rgb = rgb + (1 - alpha) * (background if background.dim() == 1 else background[:, None, None, :])
    return RenderOutput(rgb=rgb if "rgb" in outputs else None, alpha=alpha if "alpha" in outputs else None)
