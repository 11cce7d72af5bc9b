"""Methods written outside gdbench, entering a run or a sweep by reference (docs/training.md,
"Your own method"); it imports nothing of gdbench but the request's type.

    gdbench generate "a yellow duck" --guidance docs/examples/my_method.py:sjc_again
    gdbench generate "a yellow duck" --noise-source docs/examples/my_method.py:smooth_noise

``sjc_again`` is SJC's gradient written anew: a run with it gives the parameters of ``--guidance
sjc`` bit for bit (tests/test_methods.py checks this). ``smooth_noise`` is a structured noise
without 3D: a box-blurred white field per view, renormalised to unit variance, drawn from the
run's noise stream (so the run reproduces from its seed).
"""

from __future__ import annotations

import torch


def sjc_again(denoised, x, sigma, step, steps):
    """SJC: (D(x + sigma n) - x) / sigma."""
    return (denoised - x) / sigma


def smooth_noise(request, width: int = 5):
    """Unit-variance noise, correlated over ``width`` pixels, independent between views."""
    b, h, w, c = request.shape
    white = torch.randn((b, c, h, w), generator=request.generator)
    box = torch.ones(c, 1, width, width) / width
    smooth = torch.nn.functional.conv2d(white, box, padding=width // 2, groups=c)  # variance 1 inside
    smooth = smooth / smooth.flatten(1).std(dim=1).view(b, 1, 1, 1)
    return smooth.permute(0, 2, 3, 1).contiguous()
