"""The 'gsplat' backend (renderers/splat/gsplat_backend.py): ``rasterize`` on gsplat's CUDA kernels.

On every machine: the choice is checked (one line naming ``backend``), the rules for what gsplat
cannot render, and the opacity cap that stands in for our alpha clamp, checked on the float64
twin (the cap's residual bound is a closed form). With a CUDA GPU (``-m cuda``): the backend
against the float64 twin (images and gradients), against our torch path on the same GPU
(densification's screen-space gradients, radii, visibility), 'auto' choosing it, and its
refusals."""

import pytest
import torch

from renderers.splat import RasterSettings, rasterize
from renderers.splat.autograd import resolve_backend
from renderers.splat.gsplat_backend import GSPLAT_ALPHA_MAX, cap_opacities, gsplat_status, unsupported
from renderers.splat.reference import rasterize_reference
from tests._util import cotangent_loss, random_gaussians, ring_cameras

CUDA = torch.cuda.is_available()
PARAMS = ("means", "quats", "scales", "opacities", "colors")
IMAGES = ("rgb", "alpha", "depth")


def _args(gs):
    return [gs[k] for k in PARAMS]


# ------------------------------------------------------------------ every machine
def test_gsplat_on_cpu_tensors_is_one_line_naming_backend():
    with pytest.raises(ValueError, match=r"backend: 'gsplat' runs on CUDA tensors only, got tensors on cpu"):
        resolve_backend("gsplat", torch.device("cpu"))
    gs = random_gaussians(10)
    cams = ring_cameras(1, 8, 8)
    with pytest.raises(ValueError, match=r"backend: 'gsplat' runs on CUDA tensors only"):
        rasterize(*_args(gs), cams.viewmats, cams.Ks, 8, 8, backend="gsplat")
    with pytest.raises(ValueError, match=r"backend: expected 'auto', 'torch', 'cpp' or 'gsplat', got 'cuda'"):
        RasterSettings(backend="cuda")
    assert resolve_backend("auto", torch.device("cpu")) in ("cpp", "torch")  # never gsplat on the CPU


def test_status_gives_a_reason_where_it_cannot_run(monkeypatch):
    gsplat_status.cache_clear()
    monkeypatch.setenv("GDBENCH_NO_GSPLAT", "1")
    try:
        assert gsplat_status() == (False, "GDBENCH_NO_GSPLAT is set")
        monkeypatch.delenv("GDBENCH_NO_GSPLAT")
        gsplat_status.cache_clear()
        if not CUDA:
            assert gsplat_status() == (False, "torch sees no CUDA device")
    finally:
        gsplat_status.cache_clear()


@pytest.mark.parametrize(
    ("change", "why"),
    [
        ({"want": {"rgb", "weight_sq"}}, "weight_sq"),
        ({"dtype": torch.float64}, "float64"),
        ({"settings": RasterSettings(alpha_min=0.01)}, "alpha_min or t_min"),
        ({"settings": RasterSettings(t_min=1e-3)}, "alpha_min or t_min"),
        ({"settings": RasterSettings(alpha_max=0.9995)}, "clamp alpha outside [0.99, 0.999]"),
        ({"settings": RasterSettings(alpha_max=0.9)}, "clamp alpha outside [0.99, 0.999]"),
        ({"sh": (1, 4)}, "SH other than 3 channels"),
        ({"sh": (5, 3)}, "up to degree 4"),
        ({"ks_grad": True}, "gradients for Ks"),
    ],
)
def test_what_gsplat_cannot_render_is_named(change, why):
    """Each case 'auto' hands to the torch compositor (and an explicit 'gsplat' refuses), and the
    plain call that gsplat renders."""
    means = torch.zeros(5, 3, dtype=change.get("dtype", torch.float32))
    degree, d = change.get("sh", (None, 3))
    colors = torch.zeros((5, (degree + 1) ** 2, d) if degree is not None else (5, d))
    Ks = torch.eye(3)[None].requires_grad_(change.get("ks_grad", False))
    settings, want = change.get("settings", RasterSettings()), change.get("want", {"rgb"})
    plain = (torch.zeros(5, 3), torch.zeros(5, 3), torch.eye(3)[None], None)
    assert unsupported(RasterSettings(), {"rgb", "alpha"}, *plain) is None
    got = unsupported(settings, want, means, colors, Ks, degree)
    assert got is not None and why in got, got
    if change.get("ks_grad"):
        with torch.no_grad():  # without autograd no gradient is asked for
            assert unsupported(settings, want, torch.zeros(5, 3), colors, Ks, degree) is None


def test_the_opacity_cap_stands_in_for_the_clamp_within_its_bound():
    """gsplat clamps alpha at 0.999; for our 0.99 the backend caps opacities at 0.99 first. On the
    float64 twin: opacities at or below the cap give the clamp's images exactly; above it, a
    Gaussian's alpha differs by at most (o - 0.99) g <= 0.01, so rgb and alpha by at most 0.01 per
    Gaussian along a ray (a closed-form bound, checked on a scene with opaque cores). The
    gradient goes straight through the cap."""
    cams = ring_cameras(2, 32, 32, dtype=torch.float64)
    low = random_gaussians(150, seed=5, dtype=torch.float64, opacity=(0.05, 0.99))
    ours = rasterize_reference(*_args(low), cams.viewmats, cams.Ks, 32, 32, outputs=IMAGES, alpha_max=0.99)
    capped = dict(low, opacities=cap_opacities(low["opacities"], 0.99))
    theirs = rasterize_reference(*_args(capped), cams.viewmats, cams.Ks, 32, 32, outputs=IMAGES, alpha_max=0.999)
    for k in IMAGES:
        torch.testing.assert_close(getattr(theirs, k), getattr(ours, k), rtol=0, atol=1e-12)
    high = random_gaussians(150, seed=5, dtype=torch.float64, opacity=(0.995, 1.0), scale=(0.03, 0.09))
    ours = rasterize_reference(*_args(high), cams.viewmats, cams.Ks, 32, 32, outputs=IMAGES, alpha_max=0.99)
    capped = dict(high, opacities=cap_opacities(high["opacities"], 0.99))
    theirs = rasterize_reference(*_args(capped), cams.viewmats, cams.Ks, 32, 32, outputs=IMAGES, alpha_max=0.999)
    raw = rasterize_reference(*_args(high), cams.viewmats, cams.Ks, 32, 32, outputs=IMAGES, alpha_max=0.999)
    assert float(ours.alpha.max()) > 0.99
    cap_err = float((theirs.alpha - ours.alpha).abs().max())
    assert 0 < cap_err <= 0.01
    assert cap_err < float((raw.alpha - ours.alpha).abs().max())  # nearer than gsplat's own clamp
    o = torch.tensor([0.5, 0.99, 0.995, 1.0], requires_grad=True)
    c = cap_opacities(o, 0.99)
    assert c.tolist() == pytest.approx([0.5, 0.99, 0.99, 0.99])
    (g,) = torch.autograd.grad(c.sum(), o)
    assert g.tolist() == [1.0] * 4
    assert cap_opacities(o, GSPLAT_ALPHA_MAX) is o


def _gsplat_on_cpu(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, near_plane, far_plane,
                   eps2d, sh_degree, packed, tile_size, backgrounds, render_mode, rasterize_mode):  # fmt: skip
    """A stand-in for ``gsplat.rasterization`` (its contract for what the backend asks: classic, not
    packed, the render modes RGB, ED and RGB+ED, expected depth, radii [C, N, 2], culled means2d
    left unset) built on gsplat's own torch stages (``renderers.gsplat_torch``), so the backend's
    mapping runs on CPU."""
    from renderers.gsplat_torch import rasterize as gsplat_torch

    assert not packed and rasterize_mode == "classic" and tile_size <= 32
    q = quats / quats.norm(dim=-1, keepdim=True)  # the CUDA kernel's normalisation: NaN for a zero quaternion
    out = gsplat_torch(means, q, scales, opacities, colors, viewmats, Ks, width, height, sh_degree=sh_degree,
                       background=None if render_mode == "ED" else backgrounds, near_plane=near_plane,
                       far_plane=far_plane, eps2d=eps2d, tile_size=tile_size,
                       outputs=("rgb", "alpha", "depth", "means2d", "radii"))  # fmt: skip
    images = {"RGB": out.rgb, "ED": out.depth, "RGB+ED": torch.cat([out.rgb, out.depth], -1)}[render_mode]
    radii = out.radii if out.radii.dim() == 3 else out.radii[..., None].expand(*out.radii.shape, 2)
    unset = 1000.0 * (radii == 0).any(-1, keepdim=True)  # garbage where culled, as the CUDA kernel leaves it
    out.means2d.data.add_(unset)  # in place: meta's means2d is, as gsplat's, the one the images came from
    return images, out.alpha, {"radii": radii, "means2d": out.means2d}


def _screen_gradients_agree(a, b):
    """Densification's screen-space gradients: the backend's ``means2d`` keeps the gradient of a
    loss of its images (it is the tensor they were rasterised from), equal to the torch path's on
    the Gaussians both see."""
    for r in (a, b):
        r.means2d.retain_grad()
    w = torch.linspace(0.5, 1.5, a.alpha.numel()).reshape(a.alpha.shape)
    (a.alpha * w).sum().backward(retain_graph=True)
    (b.alpha * w).sum().backward(retain_graph=True)
    assert a.means2d.grad is not None, "the backend's means2d lies off the images' graph"
    both = a.visible & b.visible
    scale = float(b.means2d.grad[both].abs().max())
    assert scale > 0
    torch.testing.assert_close(a.means2d.grad[both], b.means2d.grad[both], rtol=1e-4, atol=1e-5 * scale)


@pytest.mark.parametrize("sh_degree", [None, 2])
def test_the_backend_maps_outputs_modes_and_background_as_the_torch_path(sh_degree, monkeypatch):
    """The backend's own work on the CPU, with ``gsplat.rasterization`` stood in by gsplat's torch
    stages (``_gsplat_on_cpu``):
    every output set and its render mode, the background beside the depth channel, the clamp's
    cap, a zero quaternion, and culled means2d zeroed, against our torch path given what the
    backend gives gsplat (capped opacities at its clamp), and within the cap's bound of ours."""
    import importlib

    import gsplat

    rz = importlib.import_module("renderers.splat.rasterize")  # the module (the package exports the function)
    monkeypatch.setattr(gsplat, "rasterization", _gsplat_on_cpu)
    monkeypatch.setattr(rz, "resolve_backend", lambda b, d: "gsplat" if b == "auto" else resolve_backend(b, d))
    gs = random_gaussians(120, seed=1, sh_degree=sh_degree, opacity=(0.3, 1.0))
    gs["quats"][:5] = 0.0
    gs["means"][5] = torch.tensor([0.0, 0.0, 5.0])  # behind the first camera: culled there
    gs = {k: v.requires_grad_(True) for k, v in gs.items()}  # the screen-space gradients
    cams = ring_cameras(2, 32, 24)
    bg = torch.tensor([0.2, 0.5, 0.9])
    for outputs in [("rgb", "alpha", "depth"), ("rgb",), ("alpha",), ("depth",), ("alpha", "means2d", "visible")]:
        for alpha_max in (0.999, 0.99):
            kw = dict(sh_degree=sh_degree, background=bg, outputs=outputs)
            a = rasterize(*_args(gs), cams.viewmats, cams.Ks, 32, 24, alpha_max=alpha_max, **kw)
            capped = dict(gs, opacities=cap_opacities(gs["opacities"], alpha_max))  # what gsplat is given
            b = rasterize(*_args(capped), cams.viewmats, cams.Ks, 32, 24, backend="torch", alpha_max=0.999, **kw)
            ours = rasterize(*_args(gs), cams.viewmats, cams.Ks, 32, 24, backend="torch", alpha_max=alpha_max, **kw)
            for k in outputs:
                x, y = getattr(a, k), getattr(b, k)
                assert x is not None and x.shape == y.shape, (k, outputs)
                if k == "visible":
                    assert float((x != y).float().mean()) <= 0.02 and not bool(x[0, 5])
                elif k == "means2d":
                    torch.testing.assert_close(x[a.visible], y[a.visible], rtol=1e-5, atol=1e-3)
                    assert float(x[~a.visible].abs().max()) == 0.0
                    _screen_gradients_agree(a, b)
                else:  # float rounding against the cap's own image; the cap's residual against ours
                    assert float((x - y).abs().max()) <= 1e-4, (k, outputs, alpha_max)
                    if k in ("rgb", "alpha"):
                        assert float((x - getattr(ours, k)).abs().max()) <= (1 - alpha_max) + 1e-3
    assert float(b.alpha.max()) > 0.3


# ------------------------------------------------------------------ CUDA
def _gsplat_or_skip():
    ok, why = gsplat_status()
    if not ok:
        pytest.skip(f"gsplat's CUDA kernels: {why}")


def _cuda(gs):
    return {k: v.to("cuda").requires_grad_(True) for k, v in gs.items()}


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU (torch sees none)")
@pytest.mark.parametrize("sh_degree", [None, 0, 1, 3])
@pytest.mark.parametrize("seed", [0, 1])
def test_gsplat_matches_the_twin(seed, sh_degree):
    """gsplat's kernels with our conventions against the float64 twin at gsplat's clamp: images to
    2e-4, gradients (a random linear loss of rgb, alpha and depth, with a background) to 2e-3 of
    each parameter's largest (float32 with fast math, sums in another order)."""
    _gsplat_or_skip()
    gs = random_gaussians(200, seed=seed, sh_degree=sh_degree)
    cams = ring_cameras(3, 40, 32, seed=seed)
    bg = torch.tensor([0.2, 0.5, 0.9])
    kw = dict(sh_degree=sh_degree, outputs=IMAGES, alpha_max=GSPLAT_ALPHA_MAX)
    cg = _cuda(gs)
    vm, K = cams.viewmats, cams.Ks
    a = rasterize(*_args(cg), vm.cuda(), K.cuda(), 40, 32, background=bg.cuda(), backend="gsplat", **kw)
    ref = {k: v.double().requires_grad_(True) for k, v in gs.items()}
    b = rasterize_reference(*_args(ref), vm.double(), K.double(), 40, 32, background=bg.double(), **kw)
    assert float(b.alpha.max()) > 0.3
    for k in IMAGES:
        torch.testing.assert_close(getattr(a, k).double().cpu(), getattr(b, k).detach(), rtol=0, atol=2e-4, msg=k)
    ga = torch.autograd.grad(cotangent_loss(a, IMAGES), _args(cg))
    gb = torch.autograd.grad(cotangent_loss(b, IMAGES), _args(ref))
    for name, x, y in zip(PARAMS, ga, gb):
        scale = float(y.abs().max())
        assert scale > 0, name
        err = float((x.double().cpu() - y).abs().max()) / scale
        assert err <= 2e-3, (name, err)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU (torch sees none)")
def test_default_clamp_matches_the_twin_of_the_cap():
    """At our default alpha_max 0.99 the backend equals the twin of capped opacities at gsplat's
    clamp (what it computes), and stays within the cap's bound of the twin at 0.99."""
    _gsplat_or_skip()
    gs = random_gaussians(200, seed=3, opacity=(0.5, 1.0))
    cams = ring_cameras(2, 32, 32)
    a = rasterize(*_args(_cuda(gs)), cams.viewmats.cuda(), cams.Ks.cuda(), 32, 32, outputs=IMAGES)
    ref = {k: v.double() for k, v in gs.items()}
    capped = dict(ref, opacities=cap_opacities(ref["opacities"], 0.99))
    b = rasterize_reference(*_args(capped), cams.viewmats.double(), cams.Ks.double(), 32, 32, outputs=IMAGES,
                            alpha_max=GSPLAT_ALPHA_MAX)  # fmt: skip
    ours = rasterize_reference(*_args(ref), cams.viewmats.double(), cams.Ks.double(), 32, 32, outputs=IMAGES)
    for k in ("rgb", "alpha"):
        torch.testing.assert_close(getattr(a, k).double().cpu(), getattr(b, k), rtol=0, atol=2e-4, msg=k)
        assert float((getattr(a, k).double().cpu() - getattr(ours, k)).abs().max()) <= 0.01 + 2e-4


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU (torch sees none)")
def test_densification_sees_the_same_screen_gradients_radii_and_visibility():
    """means2d's gradient (what densification accumulates), radii and visibility of gsplat against
    our torch path on the same GPU and inputs."""
    _gsplat_or_skip()
    gs = random_gaussians(300, seed=2)
    cams = ring_cameras(2, 48, 40)
    out = {}
    for backend in ("gsplat", "torch"):
        cg = _cuda(gs)
        r = rasterize(*_args(cg), cams.viewmats.cuda(), cams.Ks.cuda(), 48, 40, backend=backend, alpha_max=0.999,
                      outputs=("rgb", "alpha", "means2d", "radii", "visible"))  # fmt: skip
        r.means2d.retain_grad()
        cotangent_loss(r, ("rgb", "alpha")).backward()
        out[backend] = r
    g, t = out["gsplat"], out["torch"]
    assert g.means2d.shape == t.means2d.shape == (2, 300, 2)
    agree = (g.visible == t.visible).float().mean()
    assert agree >= 0.99, float(agree)  # the two opacity-aware radii may differ at the screen's edge
    both = g.visible & t.visible  # gsplat leaves the culled ones' means2d unset
    assert int(both.sum()) > 300
    torch.testing.assert_close(g.means2d[both], t.means2d[both], rtol=1e-5, atol=1e-3)
    scale = float(t.means2d.grad.abs().max())
    assert scale > 0
    assert float((g.means2d.grad - t.means2d.grad)[both].abs().max()) <= 2e-3 * scale
    torch.testing.assert_close(g.radii[both], t.radii[both], rtol=0.2, atol=1.0)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason="needs a CUDA GPU (torch sees none)")
def test_auto_takes_gsplat_on_cuda_and_torch_for_what_it_cannot():
    _gsplat_or_skip()
    gs = {k: v.cuda() for k, v in random_gaussians(100, seed=4).items()}
    cams = ring_cameras(2, 24, 24).to("cuda")
    assert resolve_backend("auto", torch.device("cuda")) == "gsplat"
    args = (*_args(gs), cams.viewmats, cams.Ks, 24, 24)
    assert torch.equal(rasterize(*args).rgb, rasterize(*args, backend="gsplat").rgb)
    with_wsq = rasterize(*args, outputs=("rgb", "weight_sq"))
    assert torch.equal(with_wsq.weight_sq, rasterize(*args, outputs=("rgb", "weight_sq"), backend="torch").weight_sq)
    with pytest.raises(ValueError, match=r"backend: 'gsplat' cannot give weight_sq"):
        rasterize(*args, outputs=("rgb", "weight_sq"), backend="gsplat")
    zero = dict(gs, quats=torch.zeros_like(gs["quats"]))
    ident = dict(gs, quats=torch.tensor([1.0, 0, 0, 0], device="cuda").expand(100, 4))
    a = rasterize(*_args(zero), cams.viewmats, cams.Ks, 24, 24, backend="gsplat").rgb
    b = rasterize(*_args(ident), cams.viewmats, cams.Ks, 24, 24, backend="gsplat").rgb
    assert torch.isfinite(a).all() and torch.equal(a, b)
