"""Structured noise (gdbench/mechanisms/noise.py): statistical tests, each able to fail.

Many independent draws are rendered at once as channels (colours [M, D] with D = draws),
since channels are independent standard normals."""

import math

import pytest
import torch
from scipy import stats

from gdbench.core.camera import Cameras, SphericalPoses
from gdbench.mechanisms.noise import (
    NoiseCloud,
    NoiseConfig,
    NoiseRenderer,
    advance_colors,
    autocorrelation_length,
    init_colors,
    make_noise_cloud,
    mix,
    ratio_schedule,
    structured_noise,
)

CFG = NoiseConfig(n_gaussians=3000, scale=0.02)


def _cams(az=(0.0,), res=32) -> Cameras:
    n = len(az)
    return SphericalPoses(
        torch.tensor(az, dtype=torch.float64),
        torch.full((n,), 10.0, dtype=torch.float64),
        torch.ones(n, dtype=torch.float64),
        torch.full((n,), 50.0, dtype=torch.float64),
    ).cameras(res, res)


def _cloud(channels, cfg=CFG, seed=0) -> NoiseCloud:
    return make_noise_cloud(cfg, channels, generator=torch.Generator().manual_seed(seed))


def _draws(cloud, cams, seed=1):
    g = torch.Generator().manual_seed(seed)
    colors = init_colors(cloud, generator=g).colors
    return NoiseRenderer(cloud, v_min=CFG.v_min).render(colors, cams, generator=g)


def test_cloud_follows_the_paper_sampling():
    c = _cloud(3, NoiseConfig(n_gaussians=20000))
    r = c.means.double().norm(dim=-1)
    el = torch.rad2deg(torch.asin(c.means[:, 2].double() / r))
    az = torch.rad2deg(torch.atan2(c.means[:, 1].double(), c.means[:, 0].double()))
    assert float(r.max()) <= 0.5 and float(el.abs().max()) <= 45.0 + 1e-4
    assert stats.kstest(r.numpy(), stats.uniform(0, 0.5).cdf).pvalue > 1e-3
    assert stats.kstest(az.numpy(), stats.uniform(-180, 360).cdf).pvalue > 1e-3
    assert stats.kstest(el.numpy(), stats.uniform(-45, 90).cdf).pvalue > 1e-3


def test_per_pixel_marginal_is_standard_normal():
    """KS test and moment bounds over 2000 draws at the centre, an edge and the lowest-coverage pixel."""
    K = 2000
    cloud = _cloud(K)
    cams = _cams()
    out = _draws(cloud, cams)
    from renderers.splat import composite_features, prepare

    p = prepare(cloud.means, cloud.quats, cloud.scales, cloud.opacities, cams.viewmats, cams.Ks, 32, 32)
    wsq = composite_features(p, torch.zeros(len(cloud), 1), outputs=("weight_sq",)).weight_sq[0, ..., 0]
    covered = wsq >= CFG.v_min
    assert 0.3 < float(covered.float().mean()) < 1.0  # the test sees covered and uncovered pixels
    cov_rows = torch.nonzero(covered[:, 16]).squeeze(1)
    low = torch.nonzero(covered.flatten()).squeeze(1)[wsq.flatten()[covered.flatten()].argmin()]
    pixels = {"centre": (16, 16), "edge": (int(cov_rows.min()), 16), "low": divmod(int(low), 32)}
    for name, (y, x) in pixels.items():
        s = out.noise[0, y, x].double()
        assert float(out.coverage[0, y, x, 0]) == 1.0, name
        assert stats.kstest(s.numpy(), "norm").pvalue > 1e-3, name
        assert abs(float(s.mean())) < 4 / math.sqrt(K), name
        lo, hi = stats.chi2.ppf([1e-4, 1 - 1e-4], K - 1) / (K - 1)
        assert lo < float(s.var()) < hi, name
    # uncovered pixels get iid N(0,1) too
    y, x = divmod(int(torch.nonzero(~covered.flatten())[0]), 32)
    assert stats.kstest(out.noise[0, y, x].double().numpy(), "norm").pvalue > 1e-3


def _weights(cloud: NoiseCloud, cams: Cameras) -> torch.Tensor:
    """Exact per-pixel blending weights w_i(u): render one-hot features. [C, H, W, M]"""
    from renderers.splat import composite_features, prepare

    p = prepare(
        cloud.means, cloud.quats, cloud.scales, cloud.opacities, cams.viewmats, cams.Ks, cams.width, cams.height
    )
    return composite_features(p, torch.eye(len(cloud)), outputs=("rgb",)).rgb


def test_cross_view_correlation_at_shared_noise_gaussians():
    """Two views of one source correlate where they see the same noise Gaussians (theory from
    the exact weights, sum_i w_i(u) w_i(u') / sqrt(V V')); independent sources do not."""
    cfg = NoiseConfig(n_gaussians=400, scale=0.03, opacity=0.9)
    K = 3000
    geo = _cloud(1, cfg)
    cams = _cams((0.0, 25.0), res=24)
    w = _weights(geo, cams)  # [2, H, W, M]
    wn = w / w.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    # pixels at the projections of noise centres that both views see as their strongest weight
    uv, _ = cams.project(geo.means)
    pairs = []
    for i in range(len(geo)):
        (xa, ya), (xb, yb) = uv[0, i].long().tolist(), uv[1, i].long().tolist()
        if 0 <= xa < 24 and 0 <= ya < 24 and 0 <= xb < 24 and 0 <= yb < 24:
            rho = float((wn[0, ya, xa] * wn[1, yb, xb]).sum())
            if rho > 0.6:
                pairs.append((ya, xa, yb, xb, rho))
    assert len(pairs) >= 5
    cloud = NoiseCloud(geo.means, geo.scales, geo.opacities, K)
    g = torch.Generator().manual_seed(3)
    one = NoiseRenderer(cloud).render(init_colors(cloud, generator=g).colors, cams, generator=g).noise
    a = NoiseRenderer(cloud).render(init_colors(cloud, generator=g).colors, cams[:1], generator=g).noise
    b = NoiseRenderer(cloud).render(init_colors(cloud, generator=g).colors, cams[1:], generator=g).noise
    bound = 5 / math.sqrt(K)
    for ya, xa, yb, xb, rho in pairs:
        same = float(torch.corrcoef(torch.stack([one[0, ya, xa], one[1, yb, xb]]))[0, 1])
        indep = float(torch.corrcoef(torch.stack([a[0, ya, xa], b[0, yb, xb]]))[0, 1])
        assert abs(same - rho) < bound, (same, rho)
        assert abs(indep) < bound


def test_autocorrelation_length_of_a_known_field():
    """The estimator against a closed form: iid noise blurred by a Gaussian kernel of std s px has
    correlation exp(-d^2 / (4 s^2)), so its 1/e length is 2 s."""
    s = 2.0
    g = torch.Generator().manual_seed(0)
    x = torch.randn(2000, 1, 48, 48, generator=g, dtype=torch.float64)
    r = torch.arange(-8, 9, dtype=torch.float64)
    k1 = torch.exp(-(r**2) / (2 * s * s))
    kernel = (k1[:, None] * k1[None, :])[None, None]
    field = torch.nn.functional.conv2d(x, kernel)[:, 0].permute(1, 2, 0)  # [32, 32, draws]
    length = autocorrelation_length(field, torch.ones(field.shape[:2]))
    assert length == pytest.approx(2 * s, rel=0.03)


def test_spatial_autocorrelation_length_matches_theory():
    K = 2000
    cloud = _cloud(K)
    cams = _cams()
    out = _draws(cloud, cams)
    emp = autocorrelation_length(out.noise[0], out.coverage[0])
    w = _weights(NoiseCloud(cloud.means, cloud.scales, cloud.opacities, 1), cams)[0]
    theory = autocorrelation_length(w, out.coverage[0], weights=True)
    assert 0.3 < theory < 10
    assert abs(emp - theory) < 0.15 * theory + 0.1


@pytest.mark.parametrize("mode", ["amplitude", "variance"])
@pytest.mark.parametrize("ratio", [0.0, 0.05, 0.3, 0.7, 1.0])
def test_mixing_keeps_unit_variance(ratio, mode):
    K = 4000
    out = _draws(_cloud(K), _cams())
    n = mix(out.noise, ratio, generator=torch.Generator().manual_seed(9), mode=mode)
    s = n[0, 16, 16].double()
    lo, hi = stats.chi2.ppf([1e-4, 1 - 1e-4], K - 1) / (K - 1)
    assert lo < float(s.var()) < hi
    # and the structured part is still there in the right amount: corr(n, n_s) = r read as an
    # amplitude, sqrt(r) read as a share of the variance (the trainer's default)
    c = float(torch.corrcoef(torch.stack([s, out.noise[0, 16, 16].double()]))[0, 1])
    want = ratio if mode == "amplitude" else math.sqrt(ratio)
    assert abs(c - want) < 5 / math.sqrt(K)


@pytest.mark.parametrize(("redraw", "beta"), [("ou", 0.1), ("ou", 0.5), ("step", 0.1), ("run", 0.1)])
def test_temporal_autocorrelation_of_redraw_modes(redraw, beta):
    T = 400
    cloud = _cloud(1)
    cams = _cams()
    r = NoiseRenderer(cloud)
    g = torch.Generator().manual_seed(4)
    st = init_colors(cloud, generator=g)
    frames = []
    for _ in range(T):
        frames.append(r.render(st.colors, cams, generator=g).noise[0, ..., 0])
        st = advance_colors(st, redraw, beta=beta, generator=g)
    x = torch.stack(frames).double()  # [T, H, W]
    cov = r.render(st.colors, cams, generator=g).coverage[0, ..., 0].bool()
    x = x[:, cov]  # covered pixels only: [T, P]
    if redraw == "run":  # one source for the whole run: identical structured noise at every step
        assert float(x.std(0).max()) == 0.0 and float(x.std(1).min()) > 0.5
        return
    x = (x - x.mean(0)) / x.std(0)
    for k in (1, 3, 8):
        emp = float((x[:-k] * x[k:]).mean())
        theory = {"ou": (1 - beta) ** (k / 2), "step": 0.0}[redraw]
        tol = 0.12 if redraw == "ou" else 4 / math.sqrt(T * 5)
        assert abs(emp - theory) < tol, (k, emp, theory)


def test_same_seed_same_noise():
    cloud = _cloud(4)
    cams = _cams((0.0, 90.0))
    a = _draws(cloud, cams, seed=7).noise
    b = _draws(cloud, cams, seed=7).noise
    c = _draws(cloud, cams, seed=8).noise
    assert torch.equal(a, b) and not torch.equal(a, c)
    assert torch.equal(_cloud(4, seed=2).means, _cloud(4, seed=2).means)


def test_projection_is_reused_for_repeated_cameras():
    cloud = _cloud(3)
    r = NoiseRenderer(cloud)
    g = torch.Generator().manual_seed(0)
    cams = _cams()
    first = r.prepared(cams)
    assert r.prepared(_cams()) is first
    assert r.prepared(_cams((40.0,))) is not first
    # and the cached path gives the same noise as a fresh render
    colors = init_colors(cloud, generator=torch.Generator().manual_seed(1)).colors
    a = r.render(colors, cams, generator=torch.Generator().manual_seed(2)).noise
    b = structured_noise(cloud, colors, cams, generator=torch.Generator().manual_seed(2)).noise
    assert torch.equal(a, b)
    del g


def _torch_chain(cloud, colors, cams, g, v_min):
    """The noise as composite_features' images and torch operations give it (the oracle of the
    C++ last pass, which must give the same bits)."""
    from gdbench.core.rand import randn
    from renderers.splat import composite_features, prepare

    p = prepare(cloud.means, cloud.quats, cloud.scales, cloud.opacities, cams.viewmats, cams.Ks, cams.width,
                cams.height)  # fmt: skip
    out = composite_features(p, colors.to(cams.viewmats), outputs=("rgb", "weight_sq"))
    V = out.weight_sq
    covered = V >= v_min if v_min > 0 else V > 0
    n = out.rgb / torch.sqrt(torch.where(covered, V, torch.ones_like(V)))
    iid = randn(out.rgb.shape, generator=g).to(n)
    return torch.where(covered, n, iid), covered.to(n.dtype)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("res", [32, 40])  # 40: tiles past the image's edge
def test_last_pass_is_the_torch_chain_bit_for_bit(dtype, res):
    cloud = _cloud(3, NoiseConfig(n_gaussians=800, radius=0.25, scale=0.03)).to(dtype)
    cams = _cams((0.0, 70.0, 200.0), res=res)
    cams = Cameras(cams.viewmats.to(dtype), cams.Ks.to(dtype), cams.width, cams.height)
    colors = init_colors(cloud, generator=torch.Generator().manual_seed(3)).colors
    ref_cov = _torch_chain(cloud, colors, cams, torch.Generator().manual_seed(4), CFG.v_min)[1]
    assert 0.05 < float(ref_cov.mean()) < 0.95  # covered and uncovered pixels both
    # v_min as configured, at a pixel's own weight (>= takes that pixel), and 0, negative or NaN (> 0)
    from renderers.splat import composite_features, prepare

    p = prepare(cloud.means, cloud.quats, cloud.scales, cloud.opacities, cams.viewmats, cams.Ks, res, res)
    w = composite_features(p, colors, outputs=("weight_sq",)).weight_sq
    edge = float(w[w > 0].median())
    for v_min in (CFG.v_min, edge, 0.0, -1.0, float("nan")):
        r = NoiseRenderer(cloud, v_min=v_min, cache_size=0)
        got = r.render(colors, cams, generator=torch.Generator().manual_seed(4), check_values=v_min > 0)
        want, want_cov = _torch_chain(cloud, colors, cams, torch.Generator().manual_seed(4), v_min)
        assert got.noise.dtype == dtype and torch.equal(got.noise, want) and torch.equal(got.coverage, want_cov)
    assert float((w == edge).sum()) >= 1  # the edge case was met


def test_non_finite_colours_are_refused_unless_unchecked():
    """Refused before the iid draw (the generator is where it was); unchecked, a NaN colour
    reaches the pixels that see its Gaussian (the C++ pass scans nothing; torch's always does)."""
    from renderers.splat.autograd import resolve_backend

    cloud = _cloud(3)
    colors = init_colors(cloud, generator=torch.Generator().manual_seed(1)).colors.clone()
    colors[:, 1] = float("nan")
    g = torch.Generator().manual_seed(5)
    with pytest.raises(ValueError, match="colors: expected finite values"):
        NoiseRenderer(cloud).render(colors, _cams(), generator=g)
    assert torch.equal(g.get_state(), torch.Generator().manual_seed(5).get_state())
    if resolve_backend("auto", torch.device("cpu")) == "cpp":
        out = NoiseRenderer(cloud).render(colors, _cams(), generator=g, check_values=False)
        covered = out.coverage[..., 0] > 0
        assert bool(out.noise[..., 1][covered].isnan().all()) and not bool(out.noise[..., 0].isnan().any())


def test_any_resolution_and_batch_of_views():
    cloud = _cloud(4)
    out = _draws(cloud, _cams((0.0, 90.0, 180.0), res=48))
    assert out.noise.shape == (3, 48, 48, 4) and 0 < out.coverage_fraction <= 1


def test_ratio_schedule():
    assert ratio_schedule(0, 2000) == pytest.approx(0.3)
    assert ratio_schedule(1999, 2000) == pytest.approx(0.05)
    assert ratio_schedule(1000, 2001) == pytest.approx(0.175)


@pytest.mark.parametrize(
    ("build", "match"),
    [
        (lambda: NoiseConfig(n_gaussians=0), "n_gaussians"),
        (lambda: NoiseConfig(redraw="sometimes"), "redraw"),
        (lambda: NoiseConfig(ou_beta=0.0), "ou_beta"),
        (lambda: NoiseConfig(ratio_start=1.5), "ratio_start"),
        (lambda: make_noise_cloud(CFG, 0, generator=torch.Generator()), "channels"),
        (lambda: mix(torch.zeros(3), 1.2, generator=torch.Generator()), "ratio"),
        (lambda: ratio_schedule(0, 0), "total_steps"),
        (
            lambda: NoiseRenderer(_cloud(3)).render(
                torch.zeros(len(_cloud(3)), 4), _cams(), generator=torch.Generator()
            ),
            r"colors: expected shape \[3000, 3\]",
        ),
    ],
)
def test_bad_input(build, match):
    with pytest.raises(ValueError, match=match):
        build()


def test_view_coupling_matches_empirical_correlation_of_two_views():
    """Theory (weights) against an independent estimate: many colour draws rendered in two views
    30 degrees apart, correlation of the noise at each pixel of view 0 and its best match in view 1."""
    from gdbench.mechanisms.noise import view_coupling

    cloud = make_noise_cloud(NoiseConfig(n_gaussians=400, scale=0.04), 1, generator=torch.Generator().manual_seed(3))
    poses = SphericalPoses(
        torch.tensor([0.0, 30.0, 180.0], dtype=torch.float64),
        torch.full((3,), 15.0, dtype=torch.float64),
        torch.ones(3, dtype=torch.float64),
        torch.full((3,), 55.0, dtype=torch.float64),
    )
    cams = poses.cameras(20, 20)
    theory = view_coupling(cloud, cams)
    assert float(theory[0]) == pytest.approx(1.0, abs=1e-6)
    assert 0.3 < float(theory[1]) < 0.95 and float(theory[2]) < float(theory[1])
    # empirical: K independent colour sets (as K channels of one render)
    K = 4000
    many = NoiseCloud(cloud.means, cloud.scales, cloud.opacities, K)
    colors = torch.randn(len(cloud), K, generator=torch.Generator().manual_seed(4), dtype=torch.float64).float()
    n = NoiseRenderer(many).render(colors, cams[:2], generator=torch.Generator().manual_seed(5))
    x = n.noise.reshape(2, -1, K).double()
    x = (x - x.mean(-1, keepdim=True)) / x.std(-1, keepdim=True)
    corr = x[0] @ x[1].T / (K - 1)  # [P0, P1] sample correlations
    covered = n.coverage[0].reshape(-1).bool()
    empirical = corr[covered].amax(1).mean()
    # sample correlations have sd ~ 1/sqrt(K) = 0.016; the max over a pixel's neighbours is barely biased
    assert float(empirical) == pytest.approx(float(theory[1]), abs=0.03)
