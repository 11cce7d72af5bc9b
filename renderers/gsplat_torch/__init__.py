"""The peer: gsplat's own image formation on CPU.

gsplat 1.5.3 runs its projection, tile intersection and SH in pure torch
(``gsplat.cuda._torch_impl``), but its rasterization needs CUDA. ``rasterize`` here calls
those torch stages unchanged and completes the last step (rasterize to pixels, accumulate)
with vectorised torch ops and autograd, following gsplat's CUDA kernel: alpha =
min(0.999, o exp(-sigma)), skipped when sigma < 0 or alpha < 1/255, and the pixel is done when
T (1 - alpha) <= 1e-4 (that Gaussian excluded). Same call shape as ``renderers.splat.rasterize``.
"""

from .rasterize import ALPHA_MAX, rasterize

__all__ = ["ALPHA_MAX", "rasterize"]
