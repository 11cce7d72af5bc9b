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

Backend = Literal["auto", "torch", "cpp", "gsplat"]
BACKENDS = ("auto", "torch", "cpp", "gsplat")


def resolve_backend(backend: str, device: torch.device) -> str:
    """'auto' picks the C++ kernel on CPU when it is available, gsplat's CUDA kernels on CUDA when
    they run there (``gsplat_backend``), else torch. The compositor stages treat 'gsplat' as
    torch (they run for what gsplat cannot give, such as weight_sq)."""
    if backend not in BACKENDS:
        raise ValueError(f"backend: expected one of {BACKENDS}, got {backend!r}")
    if backend == "torch":
        return "torch"
    if backend == "gsplat" and device.type != "cuda":
        raise ValueError(f"backend: 'gsplat' runs on CUDA tensors only, got tensors on {device}")
    if device.type != "cpu":
        if backend == "cpp":
            raise ValueError(f"backend: 'cpp' runs on CPU tensors only, got tensors on {device}")
        from .gsplat_backend import gsplat_status

        ok, why = gsplat_status() if device.type == "cuda" else (False, "not CUDA")
        if backend == "gsplat" and not ok:
            raise RuntimeError(f"backend: 'gsplat' is unavailable ({why})")
        return "gsplat" if ok else "torch"
    if load_extension() is None:
        if backend == "cpp":
            raise RuntimeError(f"backend: the C++ compositor is unavailable ({extension_status()})")
        return "torch"
    return "cpp"


def _cpp_forward(splats: Splats, bins: TileBins, blend: BlendParams, want: tuple[bool, bool, bool]):
    """The C++ compositor's forward of flat contiguous inputs (``_flat``): features, transmittance,
    depth, weight_sq (tile layout; empty where not wanted) and each pixel's stop index."""
    return load_extension().composite_forward(
        *splats, bins.gauss_ids, bins.tile_start, bins.tiles_x, bins.tiles_y,
        bins.tile_size, *blend, *want,
    )  # fmt: skip


def tiles_to_images(x: Tensor, bins: TileBins, size: tuple[int, int]) -> Tensor:
    """[T, area] or [T, area, D] in tile layout -> [I, H, W, 1 or D] images (``size`` = (H, W));
    an empty tensor (an output not asked for) stays empty."""
    if x.numel() == 0:
        return x
    ts, ty, tx = bins.tile_size, bins.tiles_y, bins.tiles_x
    x = x.reshape(-1, ty, tx, ts, ts, 1 if x.dim() == 2 else x.shape[-1]).permute(0, 1, 3, 2, 4, 5)
    x = x.reshape(x.shape[0], ty * ts, tx * ts, x.shape[-1])
    H, W = size
    return x if (ty * ts, tx * ts) == (H, W) else x[:, :H, :W].contiguous()


def images_to_tiles(g: Tensor, bins: TileBins, size: tuple[int, int], channels: bool) -> Tensor:
    """The inverse of ``tiles_to_images`` for gradients: [I, H, W, d] -> [T, area(, d)], zero in
    the tiles' padding beyond the image."""
    ts, ty, tx = bins.tile_size, bins.tiles_y, bins.tiles_x
    H, W = size
    if (ty * ts, tx * ts) != (H, W):
        full = g.new_zeros(g.shape[0], ty * ts, tx * ts, g.shape[-1])
        full[:, :H, :W] = g
        g = full
    g = g.reshape(-1, ty, ts, tx, ts, g.shape[-1]).permute(0, 1, 3, 2, 4, 5)
    return g.reshape((-1, ts * ts) + ((g.shape[-1],) if channels else ()))


class _Composite(torch.autograd.Function):
    """Flattens its inputs to the kernels' [I N, .] and lays their tile outputs out as images
    [I, H, W, .] inside the Function: those views and copies are then no autograd nodes."""

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
        size: tuple[int, int],
    ) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        ctx.shapes = [x.shape for x in (means2d, conics, opacities, features, depths)]
        splats = _flat(means2d, conics, opacities, features, depths)
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
        ctx.bins, ctx.chunks, ctx.blend, ctx.want, ctx.backend, ctx.size = bins, chunks, blend, want, backend, size
        # the C++ backward runs back to front from each pixel's final transmittance and stop index
        ctx.trans, ctx.last = (trans.detach(), last) if last is not None else (None, None)
        feat, trans, dep, wsq = (tiles_to_images(x, bins, size) for x in (feat, trans, dep, wsq))
        for r, w in zip((feat, dep, wsq), want, strict=True):
            if not w:
                ctx.mark_non_differentiable(r)
        return feat, trans, dep, wsq

    @staticmethod
    def backward(ctx: Any, g_feat: Tensor, g_trans: Tensor, g_depth: Tensor, g_wsq: Tensor):  # type: ignore[override]
        splats = Splats(*ctx.saved_tensors)
        bins: TileBins = ctx.bins
        want, size = ctx.want, ctx.size
        ref = splats.means2d
        n_tiles = bins.tile_start.numel() - 1
        area = bins.tile_size**2

        def tiles(g: Tensor | None, wanted: bool, channels: bool = False) -> Tensor | None:
            return images_to_tiles(g, bins, size, channels) if wanted and g is not None else None

        grads = Outputs(
            tiles(g_feat, want[0], channels=True),
            tiles(g_trans, True) if g_trans is not None else ref.new_zeros(n_tiles, area),
            tiles(g_depth, want[1]),
            tiles(g_wsq, want[2]),
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
        g = [x.reshape(shape) for x, shape in zip(g, ctx.shapes, strict=True)]
        return (*g, None, None, None, None, None, None, None)


def _flat(means2d: Tensor, conics: Tensor, opacities: Tensor, features: Tensor, depths: Tensor) -> Splats:
    """The compositor's flat [I N, .] inputs (contiguous) from per-image ones [..., N, .]."""
    return Splats(
        means2d.reshape(-1, 2).contiguous(),
        conics.reshape(-1, 3).contiguous(),
        opacities.reshape(-1).contiguous(),
        features.reshape(-1, features.shape[-1]).contiguous(),
        depths.reshape(-1).contiguous(),
    )


def composite(
    splats: Splats,
    bins: TileBins,
    n_images: int,
    blend: BlendParams,
    *,
    size: tuple[int, int],
    features: bool = True,
    depth: bool = False,
    weight_sq: bool = False,
    transmittance: bool = True,
    budget: int = 1 << 22,
    backend: str = "auto",
) -> Outputs:
    """Differentiable tiled compositing of per-image inputs [I, N, .] (any leading shape that
    flattens to I N); outputs are images [I, H, W, 1 or D] (``size`` = (H, W)), None where not
    requested (``transmittance=False`` lets a render without gradients skip laying out T)."""
    backend = resolve_backend(backend, splats.means2d.device)
    want = (features, depth, weight_sq)
    if backend == "cpp" and not (torch.is_grad_enabled() and any(t.requires_grad for t in splats)):
        # nothing to differentiate: the kernel without the autograd Function's bookkeeping
        feat, trans, dep, wsq = _cpp_forward(_flat(*splats), bins, blend, want)[:4]
        trans = tiles_to_images(trans, bins, size) if transmittance else None
        feat, dep, wsq = (tiles_to_images(x, bins, size) for x in (feat, dep, wsq))
    else:
        feat, trans, dep, wsq = _Composite.apply(*splats, bins, n_images, blend, want, budget, backend, size)
    return Outputs(feat if features else None, trans, dep if depth else None, wsq if weight_sq else None)
