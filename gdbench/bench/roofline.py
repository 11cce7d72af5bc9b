"""How far the splat renderer is from what the machine can do: the floating-point work of a
render (pixel-Gaussian pairs the compositor evaluates, times the operations per pair) against
the machine's measured peak (a float32 matrix product on the same threads, in the same run).

The pairs are counted from the projection: every Gaussian visits the pixel centres of its
alpha >= alpha_min box inside the image (an upper bound: early termination skips most of them
in a dense scene). ``bm_render`` also reports the bound for the lanes the C++ forward evaluated,
8 per block of its work counters (at 10k Gaussians, 256 px: 3.2M lanes against 7.8M box pairs),
the closer measure of the work done.
Operations per pair, forward: the power (10), exp (about 20: range reduction and a degree-7
polynomial), alpha, the clamp and the transmittance (5), and the accumulation of D colour
channels, depth and weight_sq (2 D + 4): 45 for RGB. The backward recomputes the forward's
terms and forms about 40 more per pair (the gradients of alpha, the conic, the mean, the colour).
"""

from __future__ import annotations

import time

import torch

FLOPS_PER_PAIR = {"fwd": 45, "fwd+bwd": 130}


def pixel_pairs(scene: dict, cams) -> int:
    """Pixel-Gaussian pairs the compositor evaluates (before early termination)."""
    from renderers.splat.project import project

    with torch.no_grad():
        p = project(
            scene["means"], scene["quats"], scene["scales"], scene["opacities"],
            cams.viewmats, cams.Ks, cams.width, cams.height,
        )  # fmt: skip
    m, r, vis = p.means2d.double(), p.radii.double(), p.visible
    lo = torch.ceil(m - r - 0.5).clamp_min(0)
    hi = torch.minimum(torch.floor(m + r - 0.5), torch.tensor([cams.width - 1.0, cams.height - 1.0], dtype=m.dtype))
    span = (hi - lo + 1).clamp_min(0)
    return int((span[..., 0] * span[..., 1])[vis].sum())


def peak_gflops(threads: int | None = None, size: int = 1024, budget_s: float = 1.0) -> float:
    """The machine's float32 throughput on ``threads`` threads: a square matrix product, best of
    as many as fit in ``budget_s``."""
    if threads is not None:
        torch.set_num_threads(threads)
    a = torch.rand(size, size)
    b = torch.rand(size, size)
    a @ b
    best, t_end = float("inf"), time.perf_counter() + budget_s
    while time.perf_counter() < t_end or best == float("inf"):
        t0 = time.perf_counter()
        a @ b
        best = min(best, time.perf_counter() - t0)
    return 2 * size**3 / best / 1e9


def flop_fraction(pairs: int, seconds: float, mode: str, peak: float) -> dict:
    """The render's achieved GFLOP/s and its share of the machine's peak."""
    achieved = pairs * FLOPS_PER_PAIR[mode] / seconds / 1e9
    return {"pairs": pairs, "flops_per_pair": FLOPS_PER_PAIR[mode], "gflops": achieved, "peak_gflops": peak,
            "fraction_of_peak": achieved / peak, "bound_s": pairs * FLOPS_PER_PAIR[mode] / (peak * 1e9)}  # fmt: skip
