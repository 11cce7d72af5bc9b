"""Spherical harmonics (renderers/splat/sh.py) against quadrature and scipy."""

import math

import numpy as np
import pytest
import torch

from renderers.splat.sh import eval_sh, num_sh_bases, rgb_to_sh0, sh0_to_rgb, sh_basis


def _sphere_quadrature(n_theta: int = 12, n_phi: int = 24):
    """Gauss-Legendre in cos(theta) x uniform phi: exact for polynomials of degree < 2 n_theta."""
    z, wz = np.polynomial.legendre.leggauss(n_theta)
    phi = np.arange(n_phi) * 2 * np.pi / n_phi
    Z, P = np.meshgrid(z, phi, indexing="ij")
    r = np.sqrt(1 - Z**2)
    dirs = np.stack([r * np.cos(P), r * np.sin(P), Z], -1).reshape(-1, 3)
    w = (wz[:, None] * np.full(n_phi, 2 * np.pi / n_phi)[None, :]).reshape(-1)
    return torch.from_numpy(dirs), torch.from_numpy(w)


def _scipy_real(degree, dirs):
    """scipy's complex Y_l^m (Condon-Shortley phase included) made real, columns m = -l..l."""
    scipy_special = pytest.importorskip("scipy.special")
    theta = torch.arccos(dirs[:, 2].clamp(-1, 1)).numpy()
    phi = torch.atan2(dirs[:, 1], dirs[:, 0]).numpy()
    real = []
    for m in range(-degree, degree + 1):
        Ylm = scipy_special.sph_harm_y(degree, abs(m), theta, phi)
        real.append(math.sqrt(2) * (Ylm.imag if m < 0 else Ylm.real) if m != 0 else Ylm.real)
    return torch.from_numpy(np.stack(real, -1))


def test_basis_is_orthonormal():
    dirs, w = _sphere_quadrature()
    Y = sh_basis(3, dirs)  # [Q, 16]
    gram = (Y * w[:, None]).T @ Y
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=1e-12, rtol=0)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_bands_span_scipy_real_harmonics(degree):
    """Each band of ours is an orthogonal transform of scipy's real SH of that degree."""
    dirs, w = _sphere_quadrature()
    S = _scipy_real(degree, dirs)
    ours = sh_basis(degree, dirs)[:, degree**2 : (degree + 1) ** 2]
    cross = (ours * w[:, None]).T @ S
    torch.testing.assert_close(cross @ cross.T, torch.eye(2 * degree + 1, dtype=torch.float64), atol=1e-10, rtol=0)


@pytest.mark.parametrize("degree", [1, 2, 3])
def test_basis_equals_scipy_real_harmonics_sign_for_sign(degree):
    """The 3DGS basis is exactly scipy's complex Y_l^m (Condon-Shortley phase included) made real:
    sqrt(2) Im Y_l^|m| for m < 0, Y_l^0, sqrt(2) Re Y_l^m for m > 0. Unlike the span test above,
    this sees the sign of every basis function (an oracle independent of sh.py and of gsplat)."""
    g = torch.Generator().manual_seed(0)
    dirs = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    expected = _scipy_real(degree, dirs)
    torch.testing.assert_close(sh_basis(degree, dirs)[:, degree**2 :], expected, atol=1e-12, rtol=0)


def test_degree_one_closed_form():
    d = torch.nn.functional.normalize(torch.tensor([[0.3, -0.5, 0.8]], dtype=torch.float64), dim=-1)
    c1 = math.sqrt(3 / (4 * math.pi))
    expected = torch.tensor(
        [[1 / math.sqrt(4 * math.pi), -c1 * d[0, 1], c1 * d[0, 2], -c1 * d[0, 0]]], dtype=torch.float64
    )
    torch.testing.assert_close(sh_basis(1, d), expected, atol=1e-12, rtol=0)


def test_eval_sh_offset_clamp_and_dc_roundtrip():
    rgb = torch.tensor([[0.1, 0.5, 0.9]], dtype=torch.float64)
    coeffs = torch.zeros(1, num_sh_bases(2), 3, dtype=torch.float64)
    coeffs[:, 0] = rgb_to_sh0(rgb)
    d = torch.tensor([[0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(eval_sh(2, coeffs, d), rgb)
    torch.testing.assert_close(sh0_to_rgb(coeffs[:, 0]), rgb)
    coeffs[:, 0] = -10.0  # far below zero -> clamped
    assert float(eval_sh(0, coeffs, d).max()) == 0.0


def test_bad_degree():
    with pytest.raises(ValueError, match="degree"):
        sh_basis(4, torch.zeros(1, 3))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("per_camera", [False, True])
def test_cpp_sh_without_gradients_equals_the_float64_eval(degree, per_camera, compositor):
    """The C++ SH colour (no-gradient path of rasterize, csrc/sh_cpu.cpp) against eval_sh in
    float64, batched over 2 scenes x 3 cameras, shared or per-camera coefficients, K > (degree+1)^2
    (the extra coefficients are ignored), and against the differentiable torch path."""
    from gdbench.core.camera import SphericalPoses
    from renderers.splat.project import view_dirs
    from renderers.splat.rasterize import sh_colors

    g = torch.Generator().manual_seed(degree)
    B, C, N, K, D = 2, 3, 257, 16, 3
    means = torch.randn(B, N, 3, generator=g)
    cams = SphericalPoses.orbit(C, radius=4.0).cameras(8, 8)
    viewmats = cams.viewmats.expand(B, C, 4, 4).contiguous()
    coeffs = torch.randn((B, C, N, K, D) if per_camera else (B, N, K, D), generator=g) * 0.4

    def per_cam(out):  # degree 0 keeps shared colours shared (no view directions)
        colors, pc = out
        assert pc == (per_camera or degree > 0)
        return colors if pc else colors[:, None].expand(B, C, N, D)

    with torch.no_grad():
        fast = per_cam(sh_colors(degree, coeffs, per_camera, means, viewmats, compositor))
    dirs = view_dirs(means.double(), viewmats.double())
    c64 = coeffs.double() if per_camera else coeffs.double()[:, None].expand(B, C, N, K, D)
    want = eval_sh(degree, c64, dirs)
    assert fast.shape == (B, C, N, D) and float(want.abs().max()) > 0.1  # not a trivially empty comparison
    torch.testing.assert_close(fast.double(), want, atol=2e-6, rtol=0)
    slow = per_cam(sh_colors(degree, coeffs.requires_grad_(True), per_camera, means, viewmats, compositor))
    assert slow.requires_grad
    if degree == 0:  # the shortcut is eval_sh's arithmetic, to the bit
        c32 = coeffs.detach() if per_camera else coeffs.detach()[:, None].expand(B, C, N, K, D)
        assert torch.equal(fast, eval_sh(0, c32, dirs.float()))
    torch.testing.assert_close(fast, slow.detach(), atol=2e-6, rtol=0)
