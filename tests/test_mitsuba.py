"""Mitsuba 3 references: closed forms, gradients against finite differences, the recorded
splat-vs-Mitsuba error per fixture, and the message when the library is missing."""

import pytest
import torch

from gdbench.fixtures import fixture_names, load_fixture
from renderers.mitsuba._lib import available

pytestmark = pytest.mark.skipif(not available()[0], reason=f"Mitsuba unavailable: {available()[1]}")


def _args(fx, cams=None):
    c = cams or fx.cameras
    return dict(**fx.scene.render_args(), viewmats=c.viewmats, Ks=c.Ks, width=c.width, height=c.height)


def test_ellipsoid_peak_alpha_is_the_opacity():
    """Along the central ray the peak response of an isotropic Gaussian is o (box filter over
    the centre pixel changes it by < 1%)."""
    from renderers.mitsuba.ellipsoids import rasterize

    fx = load_fixture("isotropic")
    out = rasterize(**_args(fx, fx.cameras[:1]), spp=256)
    assert float(out.alpha[0, 16, 16, 0]) == pytest.approx(0.8, abs=0.01)
    rgb = torch.tensor([0.9, 0.4, 0.1])
    torch.testing.assert_close(out.rgb[0, 16, 16], 0.8 * rgb, atol=0.01, rtol=0)
    assert float(out.alpha[0, 0, 0, 0]) == 0.0


# Relative tolerance per parameter. Opacity: Monte Carlo noise of the fixed-seed estimate (2%).
# Means: moving a Gaussian also moves the 3-sigma shell where the integrator truncates it (alpha
# jumps by o exp(-4.5) ~ 0.009 there); finite differences see that edge term, the AD gradient of
# volprim_rf_basic does not (measured 6% on this scene), so 10%.
GRAD_REL = {"opacities": 0.02, "means": 0.10}


@pytest.mark.parametrize("param", ["opacities", "means"])
def test_ellipsoid_gradients_match_finite_differences(param):
    from renderers.mitsuba.ellipsoids import rasterize

    fx = load_fixture("isotropic")
    base = _args(fx, fx.cameras[:1])
    w = torch.linspace(0, 1, 33)[None, None, :, None]

    def loss(x):
        a = dict(base, **{param: x})
        return (rasterize(**a, spp=64).rgb * w).sum()

    x = base[param].clone().requires_grad_(True)
    loss(x).backward()
    e = torch.zeros_like(x)
    e.view(-1)[0] = 1.0
    h = 0.01
    fd = (loss(base[param] + h * e) - loss(base[param] - h * e)) / (2 * h)
    assert abs(float(x.grad.view(-1)[0])) > 1.0
    assert float(x.grad.view(-1)[0]) == pytest.approx(float(fd), rel=GRAD_REL[param])


@pytest.mark.parametrize("name", fixture_names())
def test_splat_vs_mitsuba_ellipsoids_error_does_not_grow(name, tmp_path):
    """The recorded splat-vs-ray-traced error (docs/references.md explains each) holds."""
    from gdbench.compare import image_errors
    from gdbench.golden import load_golden
    from renderers.splat import rasterize

    fx = load_fixture(name)
    tol = fx.tolerance("mitsuba_ellipsoids")
    gold = load_golden(name)["mitsuba_ellipsoids"]
    err = image_errors(rasterize(**_args(fx), background=fx.background).rgb, gold)
    assert err["mean_abs"] <= tol["mean_abs"] and err["max_abs"] <= tol["max_abs"], (err, tol)


def test_missing_llvm_names_the_package(monkeypatch):
    import builtins

    from renderers.mitsuba import _lib

    real = builtins.__import__

    def fake(name, *a, **k):
        if name in ("mitsuba", "drjit"):
            raise ImportError("libLLVM.so could not be found")
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    with pytest.raises(ImportError, match=r"libllvm19.*mitsuba==3\.9\.1"):
        _lib.import_mitsuba()
