"""The entry point ``rasterize`` against its float64 twin (renderers/splat/reference.py):
forward, gradients with random cotangents, batch shapes, named extreme cases, bad input."""

import pytest
import torch

import tests._util
from renderers.splat import OUTPUTS
from renderers.splat import rasterize as _rasterize
from renderers.splat.reference import rasterize_reference
from tests._util import axis_camera, cotangent_loss, on_test_device, random_gaussians, ring_cameras

rasterize = on_test_device(_rasterize)  # pytest --device cuda: on CUDA copies (tests/conftest.py)

IMAGES = ("rgb", "alpha", "depth", "weight_sq")
PARAMS = ("means", "quats", "scales", "opacities", "colors")

# Forward tolerances, float32 fast path vs float64 twin. Measured worst case over seeds 0-4,
# SH degree None and 2, both compositors (python /tmp-style sweep in the PR notes):
# rgb 1.0e-6, alpha 1.6e-6, weight_sq 2.2e-6 (absolute, values in [0, 1]); depth 1.4e-5
# absolute on z ~ 2, i.e. 7e-6 relative. The target is 1e-5.
FWD_TOL = {
    "rgb": dict(atol=1e-5, rtol=0),
    "alpha": dict(atol=1e-5, rtol=0),
    "weight_sq": dict(atol=1e-5, rtol=0),
    "depth": dict(atol=1e-6, rtol=1e-5),
}
# Gradient tolerances, as max |fast - twin| / max |twin| per parameter (float32 fast path).
# Measured worst case on the same sweep: means 1.5e-5, quats 3.3e-5, scales 2.7e-5,
# opacities 1.1e-5, colors 1e-6. The float32 error comes from the conic (inverse of a 2x2
# covariance, relative error ~1e-6 x its condition number), entering means, quats and scales;
# tolerances are about 5x the measured values.
GRAD_TOL = {"means": 1e-4, "quats": 2e-4, "scales": 2e-4, "opacities": 5e-5, "colors": 1e-5}
# float64 fast path vs twin: measured <= 6e-14 everywhere; the fast path is exact up to rounding.
GRAD_TOL_F64 = 1e-11


def _args(gs):
    return [gs[k] for k in PARAMS]


def _compare(gs, cams, compositor, *, sh_degree=None, bg=True, dtype=torch.float32, fwd_only=False):
    W, H = cams.width, cams.height
    params = [p.requires_grad_(True) for p in _args(gs)]
    background = torch.linspace(0.2, 0.9, gs["colors"].shape[-1], dtype=dtype) if bg else None
    kw = dict(sh_degree=sh_degree, background=background, outputs=IMAGES)
    a = rasterize(*params, cams.viewmats, cams.Ks, W, H, backend=compositor, **kw)
    b = rasterize_reference(*params, cams.viewmats, cams.Ks, W, H, **kw)
    assert float(b.alpha.detach().max()) > 0.3, "scene renders (nearly) empty; the comparison would be vacuous"
    for name in IMAGES:
        tol = FWD_TOL[name] if dtype == torch.float32 else dict(atol=1e-12, rtol=1e-12)
        torch.testing.assert_close(getattr(a, name).double(), getattr(b, name).detach(), **tol, msg=name)
    if fwd_only:
        return
    ga = torch.autograd.grad(cotangent_loss(a, IMAGES), params)
    gb = torch.autograd.grad(cotangent_loss(b, IMAGES), params)
    for name, x, y in zip(PARAMS, ga, gb):
        scale = float(y.abs().max())
        assert scale > 0, f"zero gradient for {name}"
        err = float((x.double() - y).abs().max()) / scale
        tol = GRAD_TOL[name] if dtype == torch.float32 else GRAD_TOL_F64
        assert err <= tol, f"d{name}: relative error {err:.2e} > {tol:.0e}"


@pytest.mark.parametrize("seed", [0, 1, 2])
@pytest.mark.parametrize("sh_degree", [None, 0, 1, 3])
def test_matches_twin_float32(compositor, seed, sh_degree):
    gs = random_gaussians(200, seed=seed, sh_degree=sh_degree)
    _compare(gs, ring_cameras(3, 40, 32, seed=seed), compositor, sh_degree=sh_degree)


def test_matches_twin_float64(compositor):
    gs = random_gaussians(150, seed=7, dtype=torch.float64, sh_degree=2)
    _compare(gs, ring_cameras(2, 35, 29, dtype=torch.float64), compositor, sh_degree=2, dtype=torch.float64)


def test_feature_channels_and_per_camera_colors(compositor):
    gs = random_gaussians(150, seed=3, d=4)
    cams = ring_cameras(2, 32, 32)
    gs["colors"] = torch.rand(2, 150, 4, generator=torch.Generator().manual_seed(0))  # [C, N, D]
    _compare(gs, cams, compositor)


@pytest.mark.parametrize("batch", [(), (2,), (1, 2)])
def test_batch_dims(compositor, batch):
    gs = random_gaussians(120, seed=4, batch=batch)
    cams = ring_cameras(2, 24, 20)
    vm = cams.viewmats.expand(batch + (2, 4, 4))
    K = cams.Ks.expand(batch + (2, 3, 3))
    out = rasterize(*_args(gs), vm, K, 24, 20, outputs=IMAGES, backend=compositor)
    assert out.rgb.shape == batch + (2, 20, 24, 3)
    flat = {k: v.reshape((-1,) + v.shape[len(batch) :]) for k, v in gs.items()}
    for i in range(flat["means"].shape[0]):
        ref = rasterize_reference(*[flat[k][i] for k in PARAMS], cams.viewmats, cams.Ks, 24, 20, outputs=IMAGES)
        got = out.rgb.reshape((-1, 2, 20, 24, 3))[i]
        torch.testing.assert_close(got.double(), ref.rgb, **FWD_TOL["rgb"])


def test_only_requested_outputs(compositor):
    gs = random_gaussians(50, seed=0)
    cams = ring_cameras(1, 16, 16)
    out = rasterize(*_args(gs), cams.viewmats, cams.Ks, 16, 16, outputs=("alpha",), backend=compositor)
    assert out.rgb is None and out.depth is None and out.weight_sq is None and out.radii is None
    meta = rasterize(*_args(gs), cams.viewmats, cams.Ks, 16, 16, outputs=("radii", "visible", "means2d"))
    assert meta.rgb is None and meta.alpha is None
    assert meta.radii.shape == (1, 50, 2) and meta.visible.shape == (1, 50) and meta.means2d.shape == (1, 50, 2)
    px, _ = cams.project(gs["means"])
    torch.testing.assert_close(meta.means2d, px, rtol=1e-5, atol=1e-4)


def test_same_input_same_output(compositor):
    gs = random_gaussians(300, seed=1)
    cams = ring_cameras(2, 40, 40)
    params = [p.requires_grad_(True) for p in _args(gs)]
    runs = []
    for _ in range(2):
        out = rasterize(*params, cams.viewmats, cams.Ks, 40, 40, outputs=IMAGES, backend=compositor)
        runs.append((out.rgb, torch.autograd.grad(cotangent_loss(out, IMAGES), params)))
    assert torch.equal(runs[0][0], runs[1][0])
    if tests._util.TEST_DEVICE.type == "cuda":  # the backward's scatter-adds are atomics there
        assert all(float((a - b).abs().max()) <= 1e-5 * float(b.abs().max()) for a, b in zip(runs[0][1], runs[1][1]))
        return
    assert all(torch.equal(a, b) for a, b in zip(runs[0][1], runs[1][1]))


def test_a_render_without_gradients_gives_the_bits_of_one_with_them(compositor):
    """Without anything to differentiate the C++ path calls its kernels without the autograd
    Functions, and a render without alpha, depth or background lays out no transmittance: every
    output must keep the bits of the differentiable render."""
    gs = random_gaussians(300, seed=4)
    cams = ring_cameras(2, 40, 40)
    names = ("rgb", "alpha", "depth", "weight_sq")
    params = [p.requires_grad_(True) for p in _args(gs)]
    ref = rasterize(*params, cams.viewmats, cams.Ks, 40, 40, outputs=names, backend=compositor)
    with torch.no_grad():
        plain = rasterize(*params, cams.viewmats, cams.Ks, 40, 40, outputs=names, backend=compositor)
        lean = rasterize(*params, cams.viewmats, cams.Ks, 40, 40, outputs=("rgb", "weight_sq"), backend=compositor)
    assert float(ref.alpha.detach().max()) > 0.5 and ref.rgb.requires_grad and not plain.rgb.requires_grad
    for n in names:
        assert torch.equal(getattr(plain, n), getattr(ref, n).detach()), n
    assert torch.equal(lean.rgb, ref.rgb.detach()) and torch.equal(lean.weight_sq, ref.weight_sq.detach())
    assert lean.alpha is None and lean.depth is None


# ------------------------------------------------------------------ extreme cases
def _single(z, scale, opacity=0.8, quat=(1.0, 0.0, 0.0, 0.0), n=1, dtype=torch.float32):
    t = lambda x: torch.tensor(x, dtype=dtype).expand(n, -1).clone()  # noqa: E731
    return {
        "means": t([0.0, 0.0, z]),
        "quats": t(list(quat)),
        "scales": t(list(scale) if isinstance(scale, (list, tuple)) else [scale] * 3),
        "opacities": torch.full((n,), opacity, dtype=dtype),
        "colors": t([0.9, 0.5, 0.1]),
    }


def _extreme(gs, W=32, H=32, compositor="auto", twin=True, f=30.0, **kw):
    """Render with gradients; check finiteness; return fast and (optionally) twin outputs."""
    vm, K = axis_camera(1.0, f, W, H, dtype=gs["means"].dtype)
    params = [p.requires_grad_(True) for p in _args(gs)]
    bg = torch.ones(3, dtype=gs["means"].dtype)
    out = rasterize(*params, vm, K, W, H, outputs=IMAGES, backend=compositor, background=bg, **kw)
    for name in IMAGES:
        assert torch.isfinite(getattr(out, name)).all(), name
    grads = torch.autograd.grad(cotangent_loss(out, IMAGES), params, allow_unused=True)
    for name, g in zip(PARAMS, grads):
        assert g is None or torch.isfinite(g).all(), f"non-finite gradient for {name}"
    ref = rasterize_reference(*params, vm, K, W, H, outputs=IMAGES, background=bg, **kw) if twin else None
    return out, ref, grads


def test_behind_the_camera(compositor):
    out, ref, grads = _extreme(_single(-1.0, 0.2), compositor=compositor)
    assert float(out.alpha.abs().max()) == 0.0 and float(ref.alpha.abs().max()) == 0.0
    torch.testing.assert_close(out.rgb, torch.ones_like(out.rgb))
    assert all(float(g.abs().max()) == 0.0 for g in grads)


@pytest.mark.parametrize(("z", "seen"), [(0.01, False), (0.0102, True)])
def test_on_the_near_plane(compositor, z, seen):
    out, ref, _ = _extreme(_single(z, 1e-4, dtype=torch.float64), compositor=compositor)
    assert (float(out.alpha.max()) > 0) == seen
    torch.testing.assert_close(out.alpha, ref.alpha, atol=1e-12, rtol=0)


def test_camera_inside_a_gaussian(compositor):
    out, ref, _ = _extreme(_single(0.3, [1.0, 0.6, 0.8]), compositor=compositor)
    assert float(out.alpha.min()) > 0.5  # fills the view
    torch.testing.assert_close(out.rgb.double(), ref.rgb.detach(), **FWD_TOL["rgb"])


@pytest.mark.parametrize("scale", [1e-8, 1e4])
def test_tiny_and_huge_scales(compositor, scale):
    out, ref, _ = _extreme(_single(2.0, scale), compositor=compositor)
    assert float(out.alpha.max()) > 0.1
    torch.testing.assert_close(out.rgb.double(), ref.rgb.detach(), **FWD_TOL["rgb"])


def test_condition_number_1e8(compositor):
    gs = _single(2.0, [0.3, 3e-5, 0.2], quat=(0.8, 0.4, 0.3, 0.2))
    out, ref, _ = _extreme(gs, compositor=compositor, W=48, H=48)
    assert float(out.alpha.max()) > 0.1
    torch.testing.assert_close(out.rgb.double(), ref.rgb.detach(), atol=1e-4, rtol=0)


def test_zero_quaternion(compositor):
    gs = _single(2.0, [0.3, 0.1, 0.05], quat=(0.0, 0.0, 0.0, 0.0))
    out, ref, grads = _extreme(gs, compositor=compositor)
    torch.testing.assert_close(out.rgb.double(), ref.rgb.detach(), **FWD_TOL["rgb"])
    assert float(grads[1].abs().max()) == 0.0  # zero quaternion: identity, zero gradient


@pytest.mark.parametrize("logit", [50.0, -50.0])
def test_opacity_logits_extreme(compositor, logit):
    gs = _single(2.0, 0.2)
    logits = torch.full((1,), logit, requires_grad=True)
    vm, K = axis_camera(1.0, 30.0, 33, 33, dtype=torch.float32)  # odd: a pixel centre on the mean
    out = rasterize(
        gs["means"], gs["quats"], gs["scales"], torch.sigmoid(logits), gs["colors"], vm, K, 33, 33, backend=compositor
    )
    ref = rasterize_reference(
        gs["means"], gs["quats"], gs["scales"], torch.sigmoid(logits), gs["colors"], vm, K, 33, 33
    )
    torch.testing.assert_close(out.alpha.double(), ref.alpha.detach(), **FWD_TOL["alpha"])
    (g,) = torch.autograd.grad(out.rgb.sum(), logits)
    assert torch.isfinite(g).all()
    assert (float(out.alpha.max()) == pytest.approx(0.99)) if logit > 0 else float(out.alpha.max()) == 0.0


def test_empty_scene(compositor):
    gs = {k: v[:0] for k, v in _single(2.0, 0.1).items()}
    out, ref, _ = _extreme(gs, compositor=compositor)
    torch.testing.assert_close(out.rgb, torch.ones_like(out.rgb))
    assert float(out.alpha.abs().max()) == 0.0 and float(ref.alpha.abs().max()) == 0.0


@pytest.mark.parametrize(("W", "H"), [(1, 1), (4096, 1), (1, 4096)])
def test_degenerate_image_sizes(compositor, W, H):
    gs = random_gaussians(60, seed=0, spread=0.05)
    gs["means"][:, 2] += 2.0
    out, ref, _ = _extreme(gs, W=W, H=H, compositor=compositor, f=30.0)
    assert out.rgb.shape == (1, H, W, 3)
    assert float(ref.alpha.max()) > 0.1
    # At pixel coordinate ~2048 float32 resolves 2.4e-4 px; for footprints of ~1 px that moves
    # alpha by up to ~4e-5 (measured 3.5e-5), an error of the float32 pipeline, not of the method.
    tol = FWD_TOL["rgb"] if max(W, H) < 1024 else dict(atol=1e-4, rtol=0)
    torch.testing.assert_close(out.rgb.double(), ref.rgb.detach(), **tol)


def test_10k_gaussians_over_one_pixel(compositor):
    """Transmittance underflow: 10k overlapping Gaussians on a 1x1 image; T stops at t_min."""
    g = torch.Generator().manual_seed(0)
    n = 10_000
    gs = _single(2.0, 0.2, opacity=0.5, n=n)
    gs["means"][:, 2] = 1.0 + torch.rand(n, generator=g) * 3
    out, ref, grads = _extreme(gs, W=1, H=1, compositor=compositor)
    assert 1 - float(out.alpha) >= 1e-4 and 1 - float(out.alpha) < 2e-4
    torch.testing.assert_close(out.rgb.double(), ref.rgb.detach(), **FWD_TOL["rgb"])
    assert float(grads[4].abs().sum()) > 0  # the front Gaussians receive colour gradient
    assert int((grads[4].abs().sum(-1) > 0).sum()) < 50  # and only those in front of the stop


# ------------------------------------------------------------------ bad input
def _good():
    gs = random_gaussians(10, seed=0)
    cams = ring_cameras(2, 16, 16)
    return dict(gs, viewmats=cams.viewmats, Ks=cams.Ks, width=16, height=16)


@pytest.mark.parametrize(
    ("change", "error", "match"),
    [
        (lambda a: a["means"].__setitem__((0, 0), float("nan")), ValueError, "means: expected finite"),
        (
            lambda a: a.__setitem__("quats", a["quats"][:, :3]),
            ValueError,
            r"quats: expected shape \[10, 4\], got \[10, 3\]",
        ),
        (lambda a: a.__setitem__("means", a["means"][:, :2]), ValueError, r"means: expected shape \[\*B, N, 3\]"),
        (lambda a: a.__setitem__("opacities", a["opacities"][None]), ValueError, "opacities: expected shape"),
        (lambda a: a.__setitem__("Ks", a["Ks"][:1]), ValueError, r"Ks: expected shape \[2, 3, 3\]"),
        (lambda a: a.__setitem__("colors", a["colors"][0]), ValueError, "colors: expected shape"),
        (lambda a: a.__setitem__("scales", a["scales"].half()), TypeError, "scales: expected dtype float32 or float64"),
        (lambda a: a.__setitem__("means", a["means"].long()), TypeError, "means: expected dtype"),
        (lambda a: a.__setitem__("Ks", a["Ks"].double()), TypeError, "Ks: expected dtype torch.float32"),
        (lambda a: a.__setitem__("viewmats", a["viewmats"].to("meta")), ValueError, "viewmats: expected device c"),
        (lambda a: a.__setitem__("means", a["means"].tolist()), TypeError, "means: expected a torch.Tensor"),
        (lambda a: a.__setitem__("scales", -a["scales"]), ValueError, "scales: expected non-negative"),
        (
            lambda a: a.__setitem__("opacities", a["opacities"] + 1),
            ValueError,
            r"opacities: expected values in \[0, 1\]",
        ),
        (lambda a: a.__setitem__("width", 0), ValueError, "width: expected an int >= 1"),
        (lambda a: a.__setitem__("height", 2.5), TypeError, "height: expected an int"),
        (lambda a: a.__setitem__("outputs", ("rgb", "normals")), ValueError, "outputs: unknown names"),
        (lambda a: a.__setitem__("outputs", "rgb"), TypeError, "outputs: expected a tuple"),
        (lambda a: a.__setitem__("sh_degree", 2), ValueError, "colors: expected shape"),
        (lambda a: a.__setitem__("near_plane", -1.0), ValueError, "near_plane"),
        (lambda a: a.__setitem__("alpha_max", 1.0), ValueError, "alpha_max"),
        (lambda a: a.__setitem__("background", torch.ones(4)), ValueError, "background: expected shape"),
        (lambda a: a.__setitem__("backend", "cuda"), ValueError, "backend: expected"),
        (lambda a: a.update(viewmats=a["viewmats"][:0], Ks=a["Ks"][:0]), ValueError, "viewmats: expected at least one"),
        (lambda a: a["Ks"].__setitem__((1, 0, 0), 0.0), ValueError, "Ks: expected positive focal lengths"),
        (lambda a: a["Ks"].__setitem__((0, 1, 1), -5.0), ValueError, "Ks: expected positive focal lengths"),
        (lambda a: a["Ks"].__setitem__((0, 0, 1), 3.0), ValueError, r"Ks: expected pinhole intrinsics .*no skew"),
        (lambda a: a["Ks"].__setitem__((1, 2, 2), 2.0), ValueError, r"Ks: expected pinhole intrinsics"),
        (lambda a: a["Ks"][0, 2].zero_(), ValueError, r"Ks: expected pinhole intrinsics .*third row"),
        (lambda a: a.__setitem__("colors", a["colors"][..., :0]), ValueError, r"colors: expected at least one channel"),
        (lambda a: a["viewmats"][0, :3, :3].mul_(2.0), ValueError, "viewmats: expected world-to-camera rigid"),
        (lambda a: a["viewmats"][1, 0, :3].neg_(), ValueError, r"det R in \[-1"),  # a reflection
        (lambda a: a["viewmats"].__setitem__((0, 3, 0), 0.5), ValueError, r"last row \[0, 0, 0, 1\]"),
    ],
)
def test_bad_input_names_the_argument(change, error, match):
    args = _good()
    change(args)
    with pytest.raises(error, match=match):
        rasterize(**args)


@pytest.mark.parametrize(
    ("features", "fill", "error", "match"),
    [
        (lambda f: f[:, :2], lambda x: x, ValueError, r"features, fill: expected \[10\] \+ \[D\]"),
        (lambda f: f, lambda x: x[:1], ValueError, r"features, fill: expected .* got \[10, 3\] and \[1, 16, 16, 3\]"),
        (lambda f: f.double(), lambda x: x, TypeError, "features: expected dtype torch.float32"),
        (lambda f: f.tolist(), lambda x: x, TypeError, "features: expected a torch.Tensor"),
        (lambda f: f, lambda x: x.numpy(), TypeError, "fill: expected a torch.Tensor"),
    ],
)
def test_normalised_features_bad_input(features, fill, error, match):
    """The noise's last pass names what is wrong on every backend (here the default one)."""
    from renderers.splat import normalised_features, prepare

    a = _good()
    colors = a.pop("colors")
    p = prepare(a["means"], a["quats"], a["scales"], a["opacities"], a["viewmats"], a["Ks"], 16, 16)
    with pytest.raises(error, match=match):
        normalised_features(p, features(colors), fill(torch.zeros(2, 16, 16, 3)))


def test_value_checks_of_differentiable_inputs_raise_no_warnings():
    """The value checks read scalars from inputs that require gradients (cameras included):
    they must detach first, or torch warns on every call. A fresh process with warnings as
    errors, since torch may warn only once per process."""
    import subprocess
    import sys

    code = (
        "import torch\n"
        "from renderers.splat import rasterize\n"
        "from tests.test_rasterize import _good\n"
        "a = {k: (v.requires_grad_(True) if isinstance(v, torch.Tensor) and v.is_floating_point() else v)"
        " for k, v in _good().items()}\n"
        "out = rasterize(**a)\n"
        "(out.rgb.sum() + out.alpha.sum()).backward()\n"
        "assert float(a['means'].grad.abs().sum()) > 0\n"
    )
    r = subprocess.run([sys.executable, "-W", "error", "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]


def test_sh_degree_needs_enough_coefficients():
    args = _good()
    args["colors"] = torch.zeros(10, 4, 3)
    args["sh_degree"] = 2
    with pytest.raises(ValueError, match="sh_degree=2 needs K >= 9"):
        rasterize(**args)


def test_outputs_constant_lists_every_field():
    from renderers.splat import RenderOutput

    assert set(OUTPUTS) == set(RenderOutput._fields)


# ------------------------------------------------------------------ oracles the mutation run asked for
def test_needle_gaussians_match_the_twin(compositor):
    """Needles (scales like (1, 1e-4, 1e-4)) project to 2D covariances with a c ~ b^2: a
    determinant formed as a c - b^2 cancels catastrophically in float32 (every "condition
    number" case above is a flat disc, which projects well-conditioned)."""
    n = 6
    g = torch.Generator().manual_seed(3)
    gs = _single(2.0, [0.6, 1e-4, 1e-4], opacity=0.9, n=n)
    gs["means"][:, :2] = (torch.rand(n, 2, generator=g) - 0.5) * 0.8
    gs["quats"] = torch.nn.functional.normalize(torch.randn(n, 4, generator=g), dim=-1)
    out, ref, _ = _extreme(gs, compositor=compositor, W=64, H=64, f=60.0)
    assert float(ref.alpha.max()) > 0.5 and float((ref.alpha > 0.1).float().mean()) > 0.01
    torch.testing.assert_close(out.alpha.double(), ref.alpha.detach(), atol=2e-3, rtol=0)


def test_no_gradient_through_the_alpha_max_clamp(compositor):
    """A Gaussian whose alpha saturates at alpha_max on some pixels: d(image)/d(opacity) from
    those pixels is zero (min has zero derivative there). Oracle: central differences of the
    float64 render, which sees the clamp exactly."""
    gs = _single(2.0, 0.15, opacity=0.999, dtype=torch.float64)
    vm, K = axis_camera(1.0, 30.0, 33, 33, dtype=torch.float64)  # pixel centre on the mean: clamped
    op = gs["opacities"].clone().requires_grad_(True)

    def render(o):
        return rasterize(gs["means"], gs["quats"], gs["scales"], o, gs["colors"], vm, K, 33, 33, backend=compositor)

    out = render(op)
    assert int((out.alpha >= 0.99 - 1e-12).sum()) >= 1  # some pixels sit on the clamp
    r = torch.randn(out.rgb.shape, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    (g,) = torch.autograd.grad((out.rgb * r).sum(), op)
    h = 1e-7
    fd = ((render(op.detach() + h).rgb * r).sum() - (render(op.detach() - h).rgb * r).sum()) / (2 * h)
    assert float(g) == pytest.approx(float(fd), rel=1e-6, abs=1e-9)


def test_gradients_through_early_termination_match_the_twin(compositor):
    """Many opaque layers: T falls below t_min and pixels stop; the gradients of the fast path
    (which recomputes the stop in its backward) against the twin's autograd, in float64."""
    g = torch.Generator().manual_seed(1)
    n = 40
    gs = _single(2.0, 0.25, opacity=0.95, n=n, dtype=torch.float64)
    gs["means"][:, 2] = 1.5 + torch.rand(n, generator=g, dtype=torch.float64)
    gs["means"][:, :2] = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 0.3
    gs["colors"] = torch.rand(n, 3, generator=g, dtype=torch.float64)
    out, ref, grads = _extreme(gs, compositor=compositor, W=24, H=24)
    assert float((1 - out.alpha).min()) < 1e-3  # pixels reached the stop
    ref_grads = torch.autograd.grad(cotangent_loss(ref, IMAGES), [gs[k] for k in PARAMS])
    for name, a, b in zip(PARAMS, grads, ref_grads):
        torch.testing.assert_close(a, b, rtol=1e-9, atol=1e-11, msg=name)


def test_chunked_backward_matches_the_twin():
    """The torch compositor's backward in the smallest chunks (one tile each) against the twin."""
    gs = random_gaussians(80, seed=4, dtype=torch.float64)
    cams = ring_cameras(2, 40, 30, dtype=torch.float64)
    params = [p.requires_grad_(True) for p in _args(gs)]
    a = rasterize(*params, cams.viewmats, cams.Ks, 40, 30, outputs=IMAGES, backend="torch", chunk_budget=1)
    b = rasterize_reference(*params, cams.viewmats, cams.Ks, 40, 30, outputs=IMAGES)
    for name, x, y in zip(PARAMS, torch.autograd.grad(cotangent_loss(a, IMAGES), params),
                          torch.autograd.grad(cotangent_loss(b, IMAGES), params)):  # fmt: skip
        torch.testing.assert_close(x, y, rtol=1e-9, atol=1e-11, msg=name)


def test_settings_object_and_keywords_are_one_thing():
    from renderers.splat import RasterSettings

    gs = random_gaussians(50, seed=6)
    cams = ring_cameras(2, 24, 20)
    args = (*_args(gs), cams.viewmats, cams.Ks, 24, 20)
    s = RasterSettings(alpha_max=0.9, eps2d=0.5, tile_size=8)
    a = rasterize(*args, settings=s)
    b = rasterize(*args, alpha_max=0.9, eps2d=0.5, tile_size=8)
    c = rasterize(*args, settings=RasterSettings(alpha_max=0.9), eps2d=0.5, tile_size=8)  # keywords override
    d = rasterize(*args)
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.rgb, c.rgb) and not torch.equal(a.rgb, d.rgb)
    ref = rasterize_reference(*args, settings=s)
    torch.testing.assert_close(a.rgb.double(), ref.rgb, **FWD_TOL["rgb"])
    with pytest.raises(TypeError, match=r"unexpected keyword arguments \['alpha_maximum'\]"):
        rasterize(*args, alpha_maximum=0.9)
    with pytest.raises(ValueError, match="t_min"):
        RasterSettings(t_min=2.0)
