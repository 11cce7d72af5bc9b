"""float64 torch.autograd.gradcheck of the fast path on tiny scenes, for every parameter and
both compositors, after checking the image is not trivially empty (STYLE rule 6)."""

import pytest
import torch

from renderers.splat import rasterize
from tests._util import random_gaussians, ring_cameras

pytestmark = pytest.mark.gradcheck
OUTS = ("rgb", "alpha", "depth", "weight_sq")


@pytest.mark.parametrize("param", ["means", "quats", "scales", "opacities", "colors", "background"])
@pytest.mark.parametrize("sh_degree", [None, 1])
def test_gradcheck(compositor, param, sh_degree):
    gs = random_gaussians(
        6, seed=11, dtype=torch.float64, spread=0.15, scale=(0.05, 0.15), opacity=(0.3, 0.8), sh_degree=sh_degree
    )
    cams = ring_cameras(2, 10, 8, dtype=torch.float64, fovy=40.0)
    bg = torch.tensor([0.3, 0.6, 0.2], dtype=torch.float64)
    inputs = dict(gs, background=bg)

    def f(x):
        args = dict(inputs, **{param: x})
        bgx = args.pop("background")
        out = rasterize(
            **args,
            viewmats=cams.viewmats,
            Ks=cams.Ks,
            width=10,
            height=8,
            sh_degree=sh_degree,
            background=bgx,
            outputs=OUTS,
            backend=compositor,
        )
        return tuple(getattr(out, k) for k in OUTS)

    base = f(inputs[param])
    assert float(base[1].max()) > 0.3 and float((base[1] > 0).float().mean()) > 0.2  # a real image
    x = inputs[param].clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (x,), eps=1e-6, atol=1e-6, rtol=1e-4)
