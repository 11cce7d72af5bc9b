"""The 'gsplat' backend: ``rasterize`` on CUDA tensors through gsplat's CUDA kernels
(``gsplat.rasterization``, 1.5.3), with this renderer's conventions.

What maps one to one: activated inputs, wxyz quaternions (one of norm up to ``QUAT_EPS`` is the
identity here, so it is replaced before gsplat normalises it), the near and far plane, eps2d (the
same low-pass dilation, classic mode, no compensation), SH along the camera-to-mean direction
with the same +0.5 and clamp at 0, expected depth (sum w z / alpha, 0 where alpha is 0), the
background blended with the final transmittance, per-camera colours and batch dimensions, and
``means2d`` in the graph (``retain_grad()`` gives densification its screen-space gradients). Not
quite: gsplat rounds ``radii`` up to whole pixels, so its ``visible`` can include a few more
Gaussians at the image's edge than ours; ``means2d`` is 0 for culled Gaussians (ours: their
projection); its tiles are 16 px whatever ``tile_size`` says (results do not depend on them).

What differs (docs/renderer.md, "On a GPU"): gsplat's kernels fix alpha_min at 1/255, t_min at
1e-4 and clamp alpha at 0.999. A smaller ``alpha_max`` (ours: 0.99) is applied by capping each
Gaussian's opacity at it before the kernel, with a straight-through gradient: exact where the
clamp acts at a Gaussian's centre, within ``1 - alpha_max`` of alpha elsewhere on Gaussians
more opaque than the cap, and the opacity's gradient is the unclamped one at the centre (ours
is 0 there). Below alpha_max 0.99 that residual grows, and 'auto' takes the torch compositor.
Sums run in another order (and gsplat builds with fast math), and the backward
adds with atomics: results agree with the C++ compositor to float rounding, not to the bit, and
CUDA gradients can differ between two identical calls.

Outputs gsplat cannot give (``weight_sq``, the structured noise's variance), float64, SH with
other than 3 channels or degree above 4, gradients for the intrinsics, other alpha_min or t_min:
'auto' takes the torch compositor for those calls (``unsupported`` says why); an explicit
``backend='gsplat'`` refuses them in one line.
"""

from __future__ import annotations

import functools
import os

import torch
from torch import Tensor

from .project import QUAT_EPS

GSPLAT_ALPHA_MIN = 1.0 / 255.0
GSPLAT_ALPHA_MAX = 0.999
GSPLAT_T_MIN = 1e-4
GSPLAT_MAX_SH_DEGREE = 4
CAP_MIN = 0.99
"""The lowest alpha_max the opacity cap stands in for: its residual is below 1 - alpha_max."""


@functools.cache
def gsplat_status() -> tuple[bool, str]:
    """(True, '') when gsplat's CUDA kernels can run here, else (False, why). The first call on a
    machine may compile them (gsplat builds them on first use: a minute or more). Set
    GDBENCH_NO_GSPLAT=1 to keep 'auto' on the torch compositor."""
    if os.environ.get("GDBENCH_NO_GSPLAT"):
        return False, "GDBENCH_NO_GSPLAT is set"
    if not torch.cuda.is_available():
        return False, "torch sees no CUDA device"
    try:
        from gsplat.cuda._backend import _C
    except Exception as e:  # missing package, failed build: the reason, not a crash
        return False, f"gsplat's CUDA kernels are unavailable ({type(e).__name__}: {str(e).splitlines()[0][:200]})"
    if _C is None:
        return False, "gsplat's CUDA kernels did not build (gsplat printed why above)"
    return True, ""


def unsupported(
    settings,
    want: set[str],
    means: Tensor,
    colors: Tensor,
    Ks: Tensor,
    sh_degree: int | None,
) -> str | None:
    """Why gsplat's kernels cannot render this call as asked, or None when they can."""
    if "weight_sq" in want:
        return "give weight_sq (the sum of squared weights)"
    if means.shape[-2] == 0:
        return "render an empty scene"
    if means.dtype != torch.float32:
        return f"render {means.dtype} (float32 only)"
    if settings.alpha_min != GSPLAT_ALPHA_MIN or settings.t_min != GSPLAT_T_MIN:
        return f"take alpha_min or t_min other than its fixed {GSPLAT_ALPHA_MIN:.6g} and {GSPLAT_T_MIN:g}"
    if not CAP_MIN <= settings.alpha_max <= GSPLAT_ALPHA_MAX:
        return (
            f"clamp alpha outside [{CAP_MIN}, {GSPLAT_ALPHA_MAX}] (its clamp, or the opacity cap within 0.01 of ours)"
        )
    if sh_degree is not None and (colors.shape[-1] != 3 or sh_degree > GSPLAT_MAX_SH_DEGREE):
        return "evaluate SH other than 3 channels up to degree 4"
    if Ks.requires_grad and torch.is_grad_enabled():
        return "give gradients for Ks"
    return None


def cap_opacities(opacities: Tensor, alpha_max: float) -> Tensor:
    """The opacities capped at ``alpha_max`` where it is below gsplat's clamp, with the gradient
    of the opacity itself (straight through the cap); as they are otherwise."""
    if alpha_max >= GSPLAT_ALPHA_MAX:
        return opacities
    return opacities + (opacities.clamp_max(alpha_max) - opacities).detach()


def rasterize_gsplat(
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
    sh_degree: int | None,
    background: Tensor | None,
    want: set[str],
    settings,
    batch: tuple[int, ...],
    n_cameras: int,
):
    """``rasterize``'s work on gsplat's kernels (inputs checked by ``rasterize``)."""
    from gsplat import rasterization

    from .rasterize import RenderOutput

    norm = quats.norm(dim=-1, keepdim=True)
    identity = torch.tensor([1.0, 0.0, 0.0, 0.0], dtype=quats.dtype, device=quats.device)
    quats = torch.where(norm > QUAT_EPS, quats, identity)  # as ``project.normalize_quats``
    opacities = cap_opacities(opacities, settings.alpha_max)
    depth = "depth" in want
    images = bool(want & {"rgb", "alpha", "depth"})
    bg = None
    if background is not None and "rgb" in want:
        bg = background.expand(batch + (n_cameras, colors.shape[-1]))
    if "rgb" in want:
        mode = "RGB+ED" if depth else "RGB"
        feats = colors
    else:  # alpha or depth alone: one channel of zeros is the cheapest colour
        mode = "ED" if depth else "RGB"
        feats = means.new_zeros(means.shape[:-1] + (1,))
        sh_degree = None
    rgbd, alpha, meta = rasterization(
        means,
        quats,
        scales,
        opacities,
        feats,
        viewmats,
        Ks,
        width,
        height,
        near_plane=settings.near_plane,
        far_plane=settings.far_plane,
        eps2d=settings.eps2d,
        sh_degree=sh_degree,
        packed=False,
        tile_size=16,  # results do not depend on the tiles; gsplat's kernels launch tile_size^2 threads
        backgrounds=bg,
        render_mode=mode,
        rasterize_mode="classic",
    )
    out: dict = {}
    if images:
        if "rgb" in want:
            out["rgb"] = rgbd[..., :-1] if depth else rgbd
        if depth:
            out["depth"] = rgbd[..., -1:]
        if "alpha" in want:
            out["alpha"] = alpha
    radii = meta["radii"]  # [*B, C, N, 2] int32 (gsplat 1.5)
    visible = (radii > 0).all(-1)
    if "radii" in want:
        out["radii"] = radii.to(means.dtype)
    if "visible" in want:
        out["visible"] = visible
    if "means2d" in want:  # gsplat leaves culled Gaussians' entries unset (at::empty): 0 there
        m2d = meta["means2d"]
        # The tensor the images were rasterised from, so that its retained gradient is densification's
        # (a copy, say torch.where's, lies off the loss's path: its .grad stays None). Zeroed through
        # .data, which autograd does not version: no kernel reads a culled Gaussian's entry.
        m2d.data.masked_fill_(~visible[..., None], 0.0)
        out["means2d"] = m2d
    return RenderOutput(**out)
