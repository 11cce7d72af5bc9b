"""The compositor as a ``torch.autograd.Function`` with a hand-written backward.

Two implementations of the same math (``composite.py`` states it):
- ``"cpp"``: the C++/OpenMP CPU kernel (``csrc/composite_cpu.cpp``), pixel by pixel with
  early termination; the default on CPU when it builds.
- ``"torch"``: chunked, vectorised torch ops; runs on any device (CUDA included) and is
  the fallback when the extension is unavailable.
Saved: the inputs and the tile lists (and for the C++ kernel each pixel's final transmittance
and stop index); alphas are recomputed in the backward.
"""

from __future__ import annotations

from typing import Any, Literal

import torch
from torch import Tensor

from ._ext import extension_status, load_extension
from .bin_tiles import TileBins
from .composite import BlendParams, Outputs, Splats, composite_backward, composite_forward, plan_chunks

Backend = Literal["auto", "torch", "cpp"]


def resolve_backend(backend: str, device: torch.device) -> str:
    """'auto' picks the C++ kernel on CPU when it is available, else torch."""
    if backend not in ("auto", "torch", "cpp"):
        raise ValueError(f"backend: expected 'auto', 'torch' or 'cpp', got {backend!r}")
    if backend == "torch":
        return "torch"
    if device.type != "cpu":
        if backend == "cpp":
            raise ValueError(f"backend: 'cpp' runs on CPU tensors only, got tensors on {device}")
        return "torch"
    if load_extension() is None:
        if backend == "cpp":
            raise RuntimeError(f"backend: the C++ compositor is unavailable ({extension_status()})")
        return "torch"
    return "cpp"


def _cpp_forward(splats: Splats, bins: TileBins, blend: BlendParams, want: tuple[bool, bool, bool]):
    """The C++ compositor's forward: features, transmittance, depth, weight_sq (tile layout; empty
    where not wanted) and each pixel's stop index."""
    return load_extension().composite_forward(
        *(x.contiguous() for x in splats), bins.gauss_ids, bins.tile_start, bins.tiles_x, bins.tiles_y,
        bins.tile_size, *blend, *want,
    )  # fmt: skip


class _Composite(torch.autograd.Function):
    @staticmethod
    def forward(  # type: ignore[override]
        ctx: Any,
        means2d: Tensor,
        conics: Tensor,
        opacities: Tensor,
        features: Tensor,
        depths: Tensor,
        bins: TileBins,
        n_images: int,
        blend: BlendParams,
        want: tuple[bool, bool, bool],
        budget: int,
        backend: str,
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        splats = Splats(*(x.contiguous() for x in (means2d, conics, opacities, features, depths)))
        last = None
        if backend == "cpp":
            chunks = None
            feat, trans, dep, wsq, last = _cpp_forward(splats, bins, blend, want)
        else:
            chunks = plan_chunks(bins, budget)
            out = composite_forward(
                splats, bins, chunks, n_images, blend, features=want[0], depth=want[1], weight_sq=want[2]
            )
            empty = means2d.new_zeros(0)
            feat, trans, dep, wsq = (x if x is not None else empty for x in out)
        ctx.save_for_backward(*splats)
        ctx.bins, ctx.chunks, ctx.blend, ctx.want, ctx.backend = bins, chunks, blend, want, backend
        # the C++ backward runs back to front from each pixel's final transmittance and stop index
        ctx.trans, ctx.last = (trans.detach(), last) if last is not None else (None, None)
        results = (feat, dep, wsq)
        for r, w in zip(results, want, strict=True):
            if not w:
                ctx.mark_non_differentiable(r)
        return feat, trans, dep, wsq

    @staticmethod
    def backward(ctx: Any, g_feat: Tensor, g_trans: Tensor, g_depth: Tensor, g_wsq: Tensor):  # type: ignore[override]
        splats = Splats(*ctx.saved_tensors)
        bins: TileBins = ctx.bins
        want = ctx.want
        ref = splats.means2d
        n_tiles = bins.tile_start.numel() - 1
        area = bins.tile_size**2
        grads = Outputs(
            g_feat if want[0] and g_feat is not None else None,
            g_trans if g_trans is not None else ref.new_zeros(n_tiles, area),
            g_depth if want[1] and g_depth is not None else None,
            g_wsq if want[2] and g_wsq is not None else None,
        )
        if ctx.backend == "cpp":
            empty = ref.new_zeros(0)
            g = Splats(
                *load_extension().composite_backward(
                    *splats,
                    bins.gauss_ids,
                    bins.tile_start,
                    bins.tiles_x,
                    bins.tiles_y,
                    bins.tile_size,
                    *ctx.blend,
                    ctx.trans,
                    ctx.last,
                    *(g.contiguous() if g is not None else empty for g in grads),
                )
            )
        else:
            g = composite_backward(splats, bins, ctx.chunks, ctx.blend, grads)
        return g.means2d, g.conics, g.opacities, g.features, g.depths, None, None, None, None, None, None


def composite(
    splats: Splats,
    bins: TileBins,
    n_images: int,
    blend: BlendParams,
    *,
    features: bool = True,
    depth: bool = False,
    weight_sq: bool = False,
    budget: int = 1 << 22,
    backend: str = "auto",
) -> Outputs:
    """Differentiable tiled compositing; outputs in tile layout, None where not requested."""
    backend = resolve_backend(backend, splats.means2d.device)
    want = (features, depth, weight_sq)
    if backend == "cpp" and not (torch.is_grad_enabled() and any(t.requires_grad for t in splats)):
        # nothing to differentiate: the kernel without the autograd Function's bookkeeping
        feat, trans, dep, wsq, _ = _cpp_forward(splats, bins, blend, want)
    else:
        feat, trans, dep, wsq = _Composite.apply(*splats, bins, n_images, blend, want, budget, backend)
    return Outputs(feat if features else None, trans, dep if depth else None, wsq if weight_sq else None)
