"""Variational Gaussian splatting (gdbench/mechanisms/variational.py): jitter statistics, the gradient
identity of paper eq. 17, and the blurred mean render."""

import itertools
import math

import pytest
import torch
from scipy import stats

from gdbench.mechanisms.variational import jitter, vp_level
from renderers.splat import rasterize
from tests._util import axis_camera


@pytest.mark.parametrize("sigma", [0.05, 1.0, 20.0])
def test_jitter_std_matches_gamma_s_sigma(sigma):
    n = 20000
    g = torch.Generator().manual_seed(0)
    means, logs = torch.zeros(n, 3, dtype=torch.float64), torch.zeros(n, 3, dtype=torch.float64)
    m, s = jitter(means, logs, sigma, gamma=0.15, scene_radius=0.5, generator=g)
    amp = 0.15 * sigma / math.sqrt(1 + sigma**2)
    lo, hi = stats.chi2.ppf([1e-4, 1 - 1e-4], 3 * n)
    for x, scale in ((m, amp * 0.5), (s, amp)):
        chi = float((x**2).sum()) / scale**2  # sum of 3n squared N(0, scale^2) draws / scale^2
        assert lo < chi < hi
        assert stats.kstest((x.flatten() / scale).numpy(), "norm").pvalue > 1e-3


def test_vp_level_is_bounded_and_monotone():
    xs = [0.0, 0.1, 1.0, 10.0, 1e6]
    ys = [vp_level(x) for x in xs]
    assert ys[0] == 0.0 and ys[2] == pytest.approx(1 / math.sqrt(2)) and ys[-1] < 1.0
    assert all(a < b for a, b in itertools.pairwise(ys))


def test_gradient_reaching_theta_equals_gradient_at_theta_prime():
    g = torch.Generator().manual_seed(1)
    n = 40
    means = (torch.randn(n, 3, generator=g) * 0.2 + torch.tensor([0, 0, 2.0])).requires_grad_(True)
    logs = (torch.log(torch.full((n, 3), 0.05)) + 0.1 * torch.randn(n, 3, generator=g)).requires_grad_(True)
    quats = torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4)
    opac, cols = torch.full((n,), 0.6), torch.rand(n, 3, generator=g)
    vm, K = axis_camera(2.0, 40.0, 24, 24, dtype=torch.float32)

    def loss(m, ls):
        out = rasterize(m, quats, ls.exp(), opac, cols, vm, K, 24, 24)
        return (out.rgb * torch.linspace(-1, 1, 24)[None, :, None, None]).sum()

    mj, lj = jitter(means, logs, 2.0, generator=torch.Generator().manual_seed(5))
    gm, gl = torch.autograd.grad(loss(mj, lj), (means, logs))
    at = (mj.detach().requires_grad_(True), lj.detach().requires_grad_(True))
    gm2, gl2 = torch.autograd.grad(loss(*at), at)
    assert float(gm.abs().max()) > 0
    assert torch.equal(gm, gm2) and torch.equal(gl, gl2)


def test_mean_of_jittered_renders_is_a_blurred_render():
    """One Gaussian, means jittered by tau: E[alpha(u)] = o sqrt(|S|/|S + T|) exp(-1/2 d^T (S+T)^-1 d),
    with S its 2D footprint and T = tau^2 (f/z)^2 I the projected jitter (first order in tau/z)."""
    f, z, s, o, W = 50.0, 2.0, 0.04, 0.5, 33
    K = 4000
    sigma, gamma, R = 1.0, 0.15, 0.5
    tau = gamma * vp_level(sigma) * R
    g = torch.Generator().manual_seed(2)
    mean = torch.tensor([[0.0, 0.0, z]], dtype=torch.float64).expand(K, 1, 3)
    logs = torch.log(torch.full((K, 1, 3), s, dtype=torch.float64))
    mj, _ = jitter(mean, logs, sigma, gamma=gamma, scene_radius=R, generator=g, parts=("means",))
    vm, Km = axis_camera(z, f, W, W)
    out = rasterize(
        mj,
        torch.tensor([1.0, 0, 0, 0], dtype=torch.float64).expand(K, 1, 4),
        logs.exp(),
        torch.full((K, 1), o, dtype=torch.float64),
        torch.ones(K, 1, 3, dtype=torch.float64),
        vm.expand(K, 1, 4, 4),
        Km.expand(K, 1, 3, 3),
        W,
        W,
        outputs=("alpha",),
    )
    mean_alpha = out.alpha.mean(0)[0, ..., 0]
    S = (f * s / z) ** 2 + 0.3
    T = (tau * f / z) ** 2
    ys, xs = torch.meshgrid(torch.arange(W) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    d2 = (xs - W / 2) ** 2 + (ys - W / 2) ** 2
    expected = o * (S / (S + T)) * torch.exp(-0.5 * d2.double() / (S + T))  # isotropic: sqrt(|S|/|S+T|) = S/(S+T)
    assert float(expected.max()) < 0.5 * o  # visibly blurred relative to the unjittered peak o
    err = (mean_alpha - expected).abs()
    assert float(err.max()) < 0.012  # MC error ~ 0.3/sqrt(K) + second-order depth jitter
    sharp = o * torch.exp(-0.5 * d2.double() / S)
    assert float((mean_alpha - sharp).abs().max()) > 0.1  # the blur is real, not within tolerance


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        (dict(sigma=-0.1), "sigma: expected a finite noise level >= 0"),
        (dict(sigma=float("nan")), "sigma"),
        (dict(sigma=1.0, gamma=-1.0), "gamma"),
        (dict(sigma=1.0, scene_radius=0.0), "scene_radius"),
        (dict(sigma=1.0, parts=("opacity",)), "parts"),
    ],
)
def test_bad_input(kwargs, match):
    with pytest.raises(ValueError, match=match):
        jitter(torch.zeros(2, 3), torch.zeros(2, 3), generator=torch.Generator(), **kwargs)
