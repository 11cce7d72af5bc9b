"""Stage 3, compositing: closed-form images, the thresholds at their edges, and the two
compositor backends (C++ and torch) against each other."""

import math

import pytest
import torch

from renderers.splat import rasterize
from tests._util import axis_camera, cotangent_loss, random_gaussians, ring_cameras

W = H = 33  # odd: the image centre (cx = 16.5) is a pixel centre, pixel (16, 16)
F = 100.0


def _gaussians(specs, dtype=torch.float64):
    """specs: list of (z, xy_offset, sigma_px_2d, opacity, rgb). Isotropic on the optical axis.

    sigma_px_2d is the standard deviation of the projected footprint *including* eps2d=0.3.
    """
    means, scales, opac, cols = [], [], [], []
    for z, xy, sig, o, rgb in specs:
        s = z * math.sqrt(sig**2 - 0.3) / F
        means.append([xy[0] * z / F, xy[1] * z / F, z])
        scales.append([s, s, s])
        opac.append(o)
        cols.append(rgb)
    t = lambda x: torch.tensor(x, dtype=dtype)  # noqa: E731
    n = len(specs)
    return t(means), t([[1.0, 0, 0, 0]] * n), t(scales), t(opac), t(cols)


def _render(specs, compositor, **kw):
    m, q, s, o, c = _gaussians(specs)
    vm, K = axis_camera(1.0, F, W, H)
    return rasterize(m, q, s, o, c, vm, K, W, H, backend=compositor, **kw)


def test_single_gaussian_peak_and_one_sigma(compositor):
    o, rgb = 0.7, [0.2, 0.4, 0.9]
    out = _render([(2.0, (0, 0), 2.0, o, rgb)], compositor, outputs=("rgb", "alpha", "depth"))
    torch.testing.assert_close(out.rgb[0, 16, 16], o * torch.tensor(rgb, dtype=torch.float64))
    torch.testing.assert_close(out.alpha[0, 16, 16, 0], torch.tensor(o, dtype=torch.float64))
    # two pixels right = one standard deviation of the 2D footprint
    torch.testing.assert_close(out.alpha[0, 16, 18, 0], torch.tensor(o * math.exp(-0.5), dtype=torch.float64))
    torch.testing.assert_close(out.alpha[0, 18, 16, 0], torch.tensor(o * math.exp(-0.5), dtype=torch.float64))
    torch.testing.assert_close(out.depth[0, 16, 16, 0], torch.tensor(2.0, dtype=torch.float64))


def test_front_to_back_order(compositor):
    red, blue = [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]
    a = _render([(2.0, (0, 0), 2.0, 0.8, red), (3.0, (0, 0), 2.0, 0.5, blue)], compositor)
    b = _render([(3.0, (0, 0), 2.0, 0.8, red), (2.0, (0, 0), 2.0, 0.5, blue)], compositor)
    torch.testing.assert_close(a.rgb[0, 16, 16], torch.tensor([0.8, 0.0, 0.2 * 0.5], dtype=torch.float64))
    torch.testing.assert_close(b.rgb[0, 16, 16], torch.tensor([0.5 * 0.8, 0.0, 0.5], dtype=torch.float64))
    torch.testing.assert_close(a.alpha, b.alpha)  # transmittance does not depend on the order


def test_background_blending(compositor):
    bg = torch.tensor([0.1, 0.6, 0.3], dtype=torch.float64)
    out = _render([(2.0, (0, 0), 1.5, 0.6, [1.0, 1.0, 1.0])], compositor, background=bg)
    torch.testing.assert_close(out.rgb[0, 16, 16], 0.6 + 0.4 * bg)
    torch.testing.assert_close(out.rgb[0, 0, 0], bg)  # far corner: nothing but background
    torch.testing.assert_close(out.rgb, out.alpha * 1.0 + (1 - out.alpha) * bg)


def test_alpha_max_clamp(compositor):
    out = _render([(2.0, (0, 0), 2.0, 1.0, [1.0, 1.0, 1.0])], compositor, outputs=("alpha",))
    assert float(out.alpha[0, 16, 16, 0]) == pytest.approx(0.99, abs=1e-12)
    out = _render([(2.0, (0, 0), 2.0, 1.0, [1.0, 1.0, 1.0])], compositor, outputs=("alpha",), alpha_max=0.5)
    assert float(out.alpha[0, 16, 16, 0]) == pytest.approx(0.5, abs=1e-12)


def test_alpha_min_edge(compositor):
    """A Gaussian whose peak alpha is just below 1/255 leaves no trace; just above, it does."""
    below = _render([(2.0, (0, 0), 2.0, 0.999 / 255, [1.0, 1.0, 1.0])], compositor, outputs=("alpha",))
    above = _render([(2.0, (0, 0), 2.0, 1.001 / 255, [1.0, 1.0, 1.0])], compositor, outputs=("alpha",))
    assert float(below.alpha.abs().max()) == 0.0
    assert float(above.alpha[0, 16, 16, 0]) == pytest.approx(1.001 / 255, rel=1e-9)
    assert int((above.alpha > 0).sum()) == 1  # only the peak pixel reaches 1/255


@pytest.mark.parametrize(("t_min", "kept"), [(0.99e-4, 4), (1.01e-4, 3), (0.99e-3, 3), (1.01e-3, 2), (0.0, 20)])
def test_early_termination(compositor, t_min, kept):
    """20 stacked Gaussians of alpha 0.9: T after k of them is 0.1^k; the one that would take T
    below t_min is not added and the pixel stops there. Thresholds sit 1% either side of 0.1^k."""
    specs = [(2.0 + 0.01 * i, (0, 0), 2.0, 0.9, [1.0, 1.0, 1.0]) for i in range(20)]
    out = _render(specs, compositor, outputs=("alpha", "weight_sq"), t_min=t_min)
    T = float(1 - out.alpha[0, 16, 16, 0])
    assert T == pytest.approx(0.1**kept, rel=1e-6)
    wsq = sum((0.9 * 0.1**k) ** 2 for k in range(kept))
    assert float(out.weight_sq[0, 16, 16, 0]) == pytest.approx(wsq, rel=1e-9)


def test_weight_sq_closed_form(compositor):
    out = _render(
        [(2.0, (0, 0), 2.0, 0.6, [1, 1, 1]), (3.0, (0, 0), 2.0, 0.5, [1, 1, 1])], compositor, outputs=("weight_sq",)
    )
    assert float(out.weight_sq[0, 16, 16, 0]) == pytest.approx(0.6**2 + (0.4 * 0.5) ** 2, rel=1e-12)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_cpp_and_torch_compositors_agree(dtype, cpp_extension):
    gs = random_gaussians(400, seed=5, dtype=dtype)
    cams = ring_cameras(3, 50, 37, dtype=dtype)
    params = [gs[k].requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")]
    names = ("rgb", "alpha", "depth", "weight_sq")
    res = {}
    for backend in ("cpp", "torch"):
        out = rasterize(
            *params,
            cams.viewmats,
            cams.Ks,
            50,
            37,
            outputs=names,
            backend=backend,
            background=torch.tensor([0.3, 0.2, 0.1], dtype=dtype),
        )
        res[backend] = (out, torch.autograd.grad(cotangent_loss(out, names), params))
    tol = {torch.float32: dict(rtol=1e-4, atol=1e-5), torch.float64: dict(rtol=1e-10, atol=1e-11)}[dtype]
    assert float(res["cpp"][0].alpha.detach().max()) > 0.5
    for n in names:
        torch.testing.assert_close(getattr(res["cpp"][0], n), getattr(res["torch"][0], n), **tol)
    if dtype == torch.float64:
        for a, b in zip(res["cpp"][1], res["torch"][1]):
            scale = float(b.abs().max())
            torch.testing.assert_close(a / scale, b / scale, **tol)
        return
    # float32: the C++ and torch projections round differently, so each path's gradients are held
    # against the float64 result (both measured ~2e-5 of the largest entry)
    p64 = [gs[k].double().requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")]
    c64 = ring_cameras(3, 50, 37, dtype=torch.float64)
    bg = torch.tensor([0.3, 0.2, 0.1], dtype=torch.float64)
    out = rasterize(*p64, c64.viewmats, c64.Ks, 50, 37, outputs=names, backend="torch", background=bg)
    ref = torch.autograd.grad(cotangent_loss(out, names), p64)
    for backend in ("cpp", "torch"):
        for a, b in zip(res[backend][1], ref):
            scale = float(b.abs().max())
            torch.testing.assert_close(a.double() / scale, b / scale, rtol=0, atol=6e-5)


def test_backward_sums_the_same_on_one_and_two_threads(cpp_extension):
    """The C++ backward cuts each Gaussian's gradient sum into max(2, threads) chunks of tiles:
    one thread sums as two do, so a sweep's one-thread workers and a two-thread run agree bit for
    bit (the previous rule, one chunk per thread, fails this)."""
    gs = random_gaussians(3000, seed=7)
    cams = ring_cameras(2, 64, 64)
    names = ("rgb", "alpha", "depth")
    keys = ("means", "quats", "scales", "opacities", "colors")
    grads, before = {}, torch.get_num_threads()
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            params = [gs[k].clone().requires_grad_(True) for k in keys]
            out = rasterize(*params, cams.viewmats, cams.Ks, 64, 64, outputs=names, backend="cpp")
            grads[threads] = torch.autograd.grad(cotangent_loss(out, names), params)
    finally:
        torch.set_num_threads(before)
    assert float(out.alpha.detach().mean()) > 0.2  # the cloud covers many of the 2 x 16 tiles
    for k, a, b in zip(keys, grads[1], grads[2]):
        assert float(a.abs().max()) > 0 and torch.equal(a, b), k


def test_chunk_budget_does_not_change_the_image():
    gs = random_gaussians(300, seed=2)
    cams = ring_cameras(2, 40, 40)
    args = [gs[k] for k in ("means", "quats", "scales", "opacities", "colors")]
    a = rasterize(*args, cams.viewmats, cams.Ks, 40, 40, backend="torch")
    b = rasterize(*args, cams.viewmats, cams.Ks, 40, 40, backend="torch", chunk_budget=1)
    torch.testing.assert_close(a.rgb, b.rgb, rtol=0, atol=0)


def test_the_kernels_exp_is_accurate_over_its_range(cpp_extension):
    """The C++ compositor's vectorisable exp against torch.exp on [-80, 0] (its whole domain: powers
    at or above the cut, > -10, are used; lower inputs are clamped): within 2 ulp in float32 and
    4 ulp in float64."""
    ext = cpp_extension
    for dtype, ulps in ((torch.float32, 2), (torch.float64, 4)):
        x = torch.cat([torch.linspace(-80, 0, 200_001, dtype=dtype), -torch.rand(10_000, dtype=dtype) * 10])
        got, want = ext.fast_exp(x), torch.exp(x.double())
        eps = torch.finfo(dtype).eps
        rel = ((got.double() - want) / want).abs()
        assert float(rel.max()) <= ulps * eps, (dtype, float(rel.max()) / eps)


def test_work_counters_match_the_pairs_each_tile_visits(cpp_extension):
    """The compositor's work counters (read by bm_render's work fit) against the stop indices:
    the forward runs a tile's list until every pixel has stopped, min(n, max stop + 1) entries,
    and the backward walks back from the deepest stop, min(n, max stop) entries."""
    from renderers.splat import prepare

    ext = cpp_extension
    gs = random_gaussians(500, seed=11)
    gs["opacities"] = torch.full_like(gs["opacities"], 0.95)  # large and opaque: tiles stop early
    gs["scales"] = gs["scales"] * 4
    cams = ring_cameras(2, 48, 40)
    p = prepare(gs["means"], gs["quats"], gs["scales"], gs["opacities"], cams.viewmats, cams.Ks, 48, 40)
    proj, bins = p.projection, p.bins
    I, N = len(cams), gs["means"].shape[0]
    args = (
        proj.means2d.detach().reshape(I * N, 2).contiguous(),
        proj.conics.detach().reshape(I * N, 3).contiguous(),
        p.opacities.contiguous(),
        gs["colors"].repeat(I, 1).contiguous(),
        proj.depths.detach().reshape(I * N).contiguous(),
        bins.gauss_ids,
        bins.tile_start,
        bins.tiles_x,
        bins.tiles_y,
        bins.tile_size,
        *p.settings.blend,
    )
    ext.work_counters(True)
    feat, trans, _, _, last = ext.composite_forward(*args, True, False, False)
    fwd_pairs, fwd_blocks, _, _ = ext.work_counters(True)
    empty = feat.new_zeros(0)
    ext.composite_backward(*args, trans, last, torch.ones_like(feat), torch.ones_like(trans), empty, empty)
    _, _, bwd_pairs, bwd_blocks = ext.work_counters(True)
    n = (bins.tile_start[1:] - bins.tile_start[:-1]).long()
    deepest = last.reshape(len(n), -1).amax(1).long()
    assert fwd_pairs == int(torch.minimum(n, deepest + 1).sum()) > 0
    assert bwd_pairs == int(torch.minimum(n, deepest).sum()) > 0
    assert fwd_blocks >= fwd_pairs and bwd_blocks >= bwd_pairs  # every visited pair covers a pixel
    assert fwd_pairs < int(n.sum())  # early termination skipped some: the case exercises it
