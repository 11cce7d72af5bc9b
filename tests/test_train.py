"""The trainer on a tiny bank: presets, the update, resume, densification, bad input and
stiff cases. The slow-marked quality test runs the real duck."""

import dataclasses
import itertools
import math

import pytest
import torch

from gdbench.mechanisms.noise import NoiseConfig
from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.adam import OptimConfig
from gdbench.train.config import PRESETS, TrainConfig, preset
from gdbench.train.densify import PARAM_NAMES, DensifyConfig
from gdbench.train.run import train
from gdbench.train.trainer import TrainingDiverged, init_state, make_context, train_step
from tests._util import CAPTION, PACED_RUN, tiny, tiny_bank


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})


def _params(state):
    return {k: v.detach().clone() for k, v in state.params.items()}


@pytest.mark.parametrize("name", sorted(PRESETS))
def test_every_preset_runs_two_steps_and_writes_outputs(name, prior, tmp_path):
    r = train(tiny(name, tmp_path / name, steps=2), prior)
    assert r.state.step == 2 and len(r.state.history) == 2
    for key in ("ply", "turntable_gif", "turntable_sheet", "curves", "run_json"):
        assert r.paths[key].is_file() and r.paths[key].stat().st_size > 0
    import json

    run = json.loads(r.paths["run_json"].read_text())
    assert run["preset"] == name and run["seed"] == 0 and run["versions"]["torch"].startswith("2.")
    assert run["config"]["noise"]["enabled"] == PRESETS[name].noise.enabled


def test_presets_switch_what_the_paper_ablates():
    assert PRESETS["gd"].noise.enabled and PRESETS["gd"].vgs.enabled
    assert not PRESETS["gd-no-sn"].noise.enabled and PRESETS["gd-no-sn"].vgs.enabled
    assert PRESETS["gd-no-vgs"].noise.enabled and not PRESETS["gd-no-vgs"].vgs.enabled
    assert not PRESETS["sjc-gs"].noise.enabled and not PRESETS["sjc-gs"].vgs.enabled
    assert PRESETS["sds-gs"].guidance == "sds"
    # the mechanism's control: gd in every field but the noise colours' redraw
    from dataclasses import replace

    ctrl = PRESETS["gd-redraw-step"]
    assert ctrl.noise.redraw == "step" and PRESETS["gd"].noise.redraw == "run"
    assert replace(ctrl, preset="gd", noise=PRESETS["gd"].noise) == PRESETS["gd"]
    locked = PRESETS["gd-pose-locked"]  # the other control: gd but for the noise's source
    assert locked.noise.source == "pose" and PRESETS["gd"].noise.source == "cloud"
    assert replace(locked, preset="gd", noise=PRESETS["gd"].noise) == PRESETS["gd"]
    d = TrainConfig()
    assert (d.steps, d.init_points, d.init_opacity, d.camera_radius) == (2000, 4096, 0.1, 1.0)
    sched = d.densify.resolve(d.steps)
    assert (d.fovy_range, d.elevation_range, sched.every, sched.start, sched.reset_every) == (
        (40.0, 70.0),
        (-45.0, 45.0),
        50,
        300,
        400,
    )


@pytest.mark.parametrize("name", ["gd", "sjc-gs"])
def test_a_step_lowers_the_denoising_residual(name, prior):
    """Same view, sigma, jitter and noise before and after one update (averaged over steps)."""
    cfg = tiny(name, densify=DensifyConfig(enabled=False))
    cfg = dataclasses.replace(
        cfg, optim=OptimConfig(means=1e-3, colors=0.02, opacities=0.02, scales=1e-3, quats=1e-3), sigma_max=0.5
    )
    ctx = make_context(cfg, prior)
    state = init_state(ctx)
    drops = []
    for _ in range(6):
        g0 = state.rng_state()
        before = train_step(state, ctx)["residual"]
        state.step -= 1  # evaluate the same step's draws with the updated parameters
        state.set_rng_state(g0)
        after = train_step(state, ctx, update=False)["residual"]
        state.step += 1
        drops.append(before - after)
    assert sum(d > 0 for d in drops) >= 5 and sum(drops) > 0


def test_resume_gives_the_uninterrupted_result(prior, tmp_path):
    """Killed at step 5 (checkpoint every 2, densify and opacity resets on the way) and resumed."""
    a = train(tiny("gd", tmp_path / "a", steps=9), prior, write_outputs=False)
    b1 = train(tiny("gd", tmp_path / "b", steps=9), prior, stop_at=5, write_outputs=False)
    assert b1.state.step == 5
    b2 = train(tiny("gd", tmp_path / "b", steps=9), prior, write_outputs=False)
    assert b2.resumed_from == 5
    assert any(h.get("cloned") or h.get("split") for h in a.state.history)  # densification happened
    for k in PARAM_NAMES:
        assert torch.equal(a.state.params[k], b2.state.params[k]), k
    assert [h["residual"] for h in a.state.history] == [h["residual"] for h in b2.state.history]


def test_resume_refuses_a_different_config(prior, tmp_path):
    train(tiny("gd", tmp_path, steps=2), prior, write_outputs=False)
    with pytest.raises(ValueError, match=r"out: .* different config \(fields \['seed'\]\)"):
        train(tiny("gd", tmp_path, steps=2, seed=1), prior)


@pytest.mark.parametrize(
    ("kw", "error", "match"),
    [
        (dict(steps=0), ValueError, r"steps \(--steps\): expected an int >= 1, got 0"),
        (dict(sigma_min=2.0, sigma_max=1.0), ValueError, "sigma_min"),
        (dict(init="ply"), ValueError, "init_ply: init='ply' needs a PLY path"),
        (dict(guidance="dds"), ValueError, "guidance"),
        (dict(init_opacity=1.5), ValueError, "init_opacity"),
        (dict(elevation_range=(-90.0, 45.0)), ValueError, r"elevation_range \(--elevation-range\): .* in \(-90, 90\)"),
        (dict(vgs={"unit": "pixels"}), ValueError, r"vgs.unit \(--vgs-unit\): expected one of \[.scene"),
        (dict(views={"per_step": 0}), ValueError, r"views.per_step \(--views-per-step\): expected an int >= 1"),
        (dict(noise={"ratio": "both"}), ValueError, r"noise.ratio \(--noise-ratio\): expected one of"),
        (dict(seed=True), ValueError, r"seed \(--seed\): expected an int"),
    ],
)
def test_bad_configs(kw, error, match):
    """A group's bad field (given as a dict here) fails where the group is made, naming its flag."""
    from gdbench.train.config import NESTED

    with pytest.raises(error, match=match):
        TrainConfig(**{k: NESTED[k](**v) if isinstance(v, dict) else v for k, v in kw.items()})


def test_bad_prompt_and_paths(prior, tmp_path):
    with pytest.raises(ValueError, match="preset: unknown 'best'"):
        preset("best")
    with pytest.raises(ValueError, match=r"prompt: .*matches no known asset.*; nearest: .*gdbench prompts"):
        train(tiny("gd", tmp_path, prompt="a nuclear submarine in a storm"), prior)
    assert not (tmp_path / "checkpoint.pt").exists()  # nothing written for a bad prompt
    with pytest.raises(FileNotFoundError, match="init_ply: no file"):
        train(tiny("gd", tmp_path, init="ply", init_ply=tmp_path / "missing.ply"), prior)


def test_init_from_a_point_cloud_ply(prior, tmp_path):
    o3d = pytest.importorskip("open3d")
    pts = torch.rand(500, 3) - 0.5
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.double().numpy()))
    pc.colors = o3d.utility.Vector3dVector(torch.rand(500, 3).double().numpy())
    o3d.io.write_point_cloud(str(tmp_path / "pc.ply"), pc)
    ctx = make_context(tiny("gd", init="ply", init_ply=tmp_path / "pc.ply"), prior)
    st = init_state(ctx)
    means = st.params["means"].detach()
    d = (means[:, None] - pts[None]).norm(dim=-1).min(1).values
    assert float(d.max()) < 1e-5 and means.shape[0] == 150


def test_world_sizes_follow_the_init_clouds_extent(prior, tmp_path):
    """A PLY init of points uniform in a ball of radius 2 (centred at (1, 0, 0)): the extent is the
    99th percentile of their distances from the centroid, R 0.99^(1/3) in closed form, and the
    clone/split and prune thresholds, the VGS unit and the means' learning rate (3DGS scales its
    position rate by its extent) all use it; the paper's sphere keeps 0.5 exactly."""
    o3d = pytest.importorskip("open3d")
    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(20000, 3, generator=g), dim=-1)
    pts = d * 2.0 * torch.rand(20000, 1, generator=g) ** (1 / 3) + torch.tensor([1.0, 0.0, 0.0])
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts.double().numpy()))
    o3d.io.write_point_cloud(str(tmp_path / "ball.ply"), pc)
    cfg = tiny("gd", init="ply", init_ply=tmp_path / "ball.ply", init_points=4000, densify=DensifyConfig(enabled=False))
    ctx = make_context(cfg, prior)
    assert ctx.extent == pytest.approx(2.0 * 0.99 ** (1 / 3), rel=0.02)
    assert ctx.strategy.extent == ctx.extent == ctx.jitter_length
    state = init_state(ctx)
    train_step(state, ctx)
    lr = {gr["name"]: gr["lr"] for gr in state.optimizer.param_groups}
    assert lr["means"] == pytest.approx(cfg.optim.means * ctx.extent / 0.5, rel=1e-12)
    sphere = make_context(tiny("gd"), prior)
    assert sphere.extent == 0.5 == sphere.strategy.extent


def test_the_means_rate_decays_over_at_least_the_papers_2000_steps():
    """Closed form: lr(s) = means (means_final / means)^(s / (T - 1)) with T = max(steps, 2000): a
    short run stops partway down the 2000-step decay, a long one stretches it, and the default run
    keeps its rates."""
    from gdbench.train.update import _means_lr

    for steps, T in ((800, 2000), (2000, 2000), (4000, 4000)):
        cfg = preset("gd", steps=steps)
        for s in (0, steps // 2, steps - 1):
            assert _means_lr(cfg, s) == pytest.approx(1e-3 * 0.02 ** (s / (T - 1)), rel=1e-12)
    assert _means_lr(preset("gd", steps=800), 799) == pytest.approx(2.09e-4, rel=3e-3)
    assert _means_lr(preset("gd"), 1999) == pytest.approx(2e-5, rel=1e-12)


def test_init_from_bank_depth_lies_on_the_surface(prior):
    ctx = make_context(tiny("gd", init="bank-depth"), prior)
    means = init_state(ctx).params["means"].detach()
    assert float(means.norm(dim=-1).max()) < 0.5 and float(means.norm(dim=-1).mean()) > 0.15


# -------------------------------------------------------------------- stiff and extreme cases
@pytest.mark.parametrize(
    "kw",
    [
        dict(sigma_min=0.0292, sigma_max=0.03),  # the lowest tick only
        dict(sigma_min=14.0, sigma_max=15.0),  # the highest ticks only
        dict(optim=OptimConfig(means=1e-2, means_final=2e-4, colors=0.1, opacities=0.5, scales=0.05, quats=0.05)),
        dict(weight=10.0),
        dict(densify=DensifyConfig(start=1, every=1, prune_opacity=1.0)),  # every Gaussian pruned
    ],
    ids=["sigma-min", "sigma-max", "lr-x10", "guidance-x10", "prune-all"],
)
def test_stiff_cases_keep_parameters_finite(kw, prior, tmp_path):
    r = train(tiny("gd", tmp_path, steps=6, **kw), prior, write_outputs=False)
    for k in PARAM_NAMES:
        assert torch.isfinite(r.state.params[k]).all(), k
    assert r.state.params["means"].shape[0] >= 1


def test_bank_of_one_image(tmp_path):
    one = tiny_bank(CAPTION, azimuths=1, elevations=(0.0,))
    r = train(tiny("gd", tmp_path, steps=4), EmpiricalPrior(banks={CAPTION: one}), write_outputs=False)
    assert all(torch.isfinite(v).all() for v in r.state.params.values())


def test_non_finite_gradients_are_skipped_then_stop_the_run(prior, tmp_path, monkeypatch):
    calls = {"n": 0}
    real = prior.denoise

    def flaky(x, sigma, cond, **kw):
        calls["n"] += 1
        out = real(x, sigma, cond, **kw)
        return out * float("nan") if calls["n"] in (2, 3) else out

    monkeypatch.setattr(prior, "denoise", flaky)
    r = train(tiny("gd", tmp_path / "a", steps=5, max_bad_steps=5), prior, write_outputs=False)
    assert [h.get("skipped", 0) for h in r.state.history] == [0, 1, 1, 0, 0]
    assert all(torch.isfinite(v).all() for v in r.state.params.values())
    monkeypatch.setattr(prior, "denoise", lambda x, *a, **k: x * float("nan"))
    with pytest.raises(TrainingDiverged, match="consecutive steps had non-finite gradients"):
        train(tiny("gd", tmp_path / "b", steps=10, max_bad_steps=3), prior)
    assert not (tmp_path / "b" / "scene.ply").exists()


# -------------------------------------------------------------------- quality (slow)
@pytest.mark.slow
def test_short_duck_run_beats_the_initial_sphere_by_3db(tmp_path):
    from gdbench.core.scene import sphere_init
    from gdbench.metrics.gt import asset_views, heldout_poses, score_against_asset

    cfg = preset("gd", steps=600, out=tmp_path, progress=False, turntable_frames=4)
    r = train(cfg)
    ref = asset_views("a yellow duck", heldout_poses(12), 64)
    trained = score_against_asset(r.state.scene(), "a yellow duck", reference=ref)
    init = score_against_asset(
        sphere_init(4096, generator=torch.Generator().manual_seed(0)), "a yellow duck", reference=ref
    )
    assert trained.psnr >= init.psnr + 3.0, (trained, init)


@pytest.mark.slow
def test_sh_degree_3_scores_within_1db_of_degree_0_on_the_duck(tmp_path):
    """The higher bands train at a twentieth of the base colour's rate (3DGS's rule): at the base
    rate they absorbed each view's noise and degree 3 lost 4.8 dB (a pale duck speckled with
    colours). Oracle: the asset itself, at the held-out views."""
    from gdbench.metrics.gt import asset_views, heldout_poses, score_against_asset

    ref = asset_views("a yellow duck", heldout_poses(12), 64)
    psnr = {}
    for degree in (0, 3):
        cfg = preset("gd", sh_degree=degree, out=tmp_path / str(degree), progress=False, turntable_frames=4)
        r = train(cfg, write_outputs=False)
        assert r.state.params["sh_rest"].shape[1] == (degree + 1) ** 2 - 1
        psnr[degree] = score_against_asset(r.state.scene(), "a yellow duck", reference=ref).psnr
    assert psnr[0] > 26 and psnr[3] > psnr[0] - 1.0, psnr


def test_the_higher_sh_bands_train_at_their_own_rate(prior):
    """Two Adam groups: the base colour at ``optim.colors``, the higher bands at ``optim.sh_rest``;
    one step moves each by about its rate (Adam's first step is lr * sign(grad))."""
    cfg = tiny("sjc-gs", sh_degree=2, densify=DensifyConfig(enabled=False), weight=10.0)
    ctx = make_context(cfg, prior)
    state = init_state(ctx)
    lr = {g["name"]: g["lr"] for g in state.optimizer.param_groups}
    assert (lr["sh"], lr["sh_rest"]) == (cfg.optim.colors, cfg.optim.sh_rest) and lr["sh_rest"] == lr["sh"] / 20
    before = {k: state.params[k].detach().clone() for k in ("sh", "sh_rest")}
    train_step(state, ctx)
    for k in ("sh", "sh_rest"):
        step = (state.params[k].detach() - before[k]).abs()
        moved = step[step > 0]
        assert moved.numel() > 100
        torch.testing.assert_close(moved.max(), torch.tensor(lr[k]), rtol=1e-3, atol=0)


_KILL_SCRIPT = (
    PACED_RUN
    + """
run.train(tiny("gd", sys.argv[1], steps=int(sys.argv[2]), checkpoint_every=3), prior, write_outputs=False)
"""
)


def test_sigkilled_run_resumes_to_the_uninterrupted_result(prior, tmp_path):
    import os
    import signal
    import subprocess
    import sys
    import time

    steps = 60
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.Popen([sys.executable, "-c", _KILL_SCRIPT, str(tmp_path / "k"), str(steps)], cwd=root)
    ckpt = tmp_path / "k" / "checkpoint.pt"
    deadline = time.time() + 120
    while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
        time.sleep(0.05)
    time.sleep(0.3)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    assert proc.returncode == -signal.SIGKILL, "the run finished before it could be killed"
    torch.load(ckpt, weights_only=True)  # whatever the kill interrupted, the checkpoint on disk is whole
    resumed = train(tiny("gd", tmp_path / "k", steps=steps, checkpoint_every=3), prior, write_outputs=False)
    assert 0 < resumed.resumed_from < steps
    full = train(tiny("gd", tmp_path / "full", steps=steps, checkpoint_every=3), prior, write_outputs=False)
    for k in PARAM_NAMES:
        assert torch.equal(full.state.params[k], resumed.state.params[k]), k


# -------------------------------------------------------------------- paired random streams
def test_presets_with_one_seed_draw_the_same_views_sigmas_and_iid_noise(prior, tmp_path, monkeypatch):
    """gd and sjc-gs differ only in what they ablate: same initial scene, same views and noise
    levels at every step, and gd's iid noise part is sjc-gs's whole noise."""
    from gdbench.train.distill import _noise_fields
    from gdbench.train.views import sample_views

    ctx_gd = make_context(tiny("gd", views_per_step=2), prior)
    ctx_sjc = make_context(tiny("sjc-gs", views_per_step=2), prior)
    a, b = init_state(ctx_gd), init_state(ctx_sjc)
    for k in PARAM_NAMES:
        assert torch.equal(a.params[k], b.params[k]), k
    for _ in range(3):
        va, vb = sample_views(ctx_gd, a), sample_views(ctx_sjc, b)
        assert torch.equal(va.poses.azimuth, vb.poses.azimuth) and torch.equal(va.poses.fovy, vb.poses.fovy)
        assert torch.equal(va.poses.elevation, vb.poses.elevation) and va.sigma == vb.sigma
        shape = (2, 16, 16, 3)
        n_gd = _noise_fields(ctx_gd, a, va, shape, update=True)[0]
        n_sjc = _noise_fields(ctx_sjc, b, vb, shape, update=True)[0]
        # gd: n = a n_s + sqrt(1 - a^2) n_iid, with n_iid the very field sjc-gs uses
        from gdbench.mechanisms.noise import structured_amplitude

        r = structured_amplitude(0.3, ctx_gd.cfg.noise.ratio)  # the proportion at step 0
        ns = ctx_gd.noise.render(a.noise_colors, va.prior_cams, generator=torch.Generator())
        cov = ns.coverage.bool().expand(shape)  # where the cloud covers nothing, n_s is an iid fill
        assert cov.float().mean() > 0.5
        want = r * ns.noise + math.sqrt(1 - r * r) * n_sjc
        torch.testing.assert_close(n_gd[cov], want[cov], atol=1e-5, rtol=0)
    # whole runs with and without VGS (whose jitter draws from its own stream): the prior sees the
    # same cameras and noise levels at every step (captured by wrapping it)
    seen = {}
    denoise = prior.denoise

    for name in ("gd", "gd-no-vgs"):
        calls = seen.setdefault(name, [])

        def capture(x, sig, cond, *, calls=calls, **kw):
            calls.append(torch.cat([sig, kw["azimuth"], kw["elevation"], kw["fovy"]]))
            return denoise(x, sig, cond, **kw)

        monkeypatch.setattr(prior, "denoise", capture)
        r = train(tiny(name, tmp_path / name, steps=5, views_per_step=2), prior, write_outputs=False)
        assert len(calls) == 5 and len(r.state.history) == 5
    assert all(torch.equal(a, b) for a, b in zip(seen["gd"], seen["gd-no-vgs"], strict=True))


def test_another_seed_draws_other_views():
    from gdbench.train.streams import STREAMS, stream_seed

    seeds = {stream_seed(s, n) for s in (0, 1) for n in STREAMS}
    assert len(seeds) == 2 * len(STREAMS)
    with pytest.raises(ValueError, match="unknown stream"):
        stream_seed(0, "colour")


def test_checkpoint_refuses_pickled_code_and_foreign_files(prior, tmp_path):
    """weights_only loading: a checkpoint carrying a pickled callable is refused, not run."""
    from gdbench.train.checkpoint import CheckpointError

    class Boom:
        def __reduce__(self):
            return (print, ("pwned",))

    train(tiny("gd", tmp_path / "a", steps=2), prior, write_outputs=False)
    ckpt = tmp_path / "a" / "checkpoint.pt"
    blob = torch.load(ckpt, weights_only=True)
    blob["history"].append(Boom())
    torch.save(blob, ckpt)
    with pytest.raises(CheckpointError, match=r"checkpoint: .* objects other than tensors"):
        train(tiny("gd", tmp_path / "a", steps=4), prior)
    for content in (b"", b"PK\x03\x04 truncated"):
        ckpt.write_bytes(content)
        with pytest.raises(CheckpointError, match="unreadable"):
            train(tiny("gd", tmp_path / "a", steps=4), prior)
    torch.save({"weights": torch.zeros(2)}, ckpt)
    with pytest.raises(CheckpointError, match="not a gdbench checkpoint"):
        train(tiny("gd", tmp_path / "a", steps=4), prior)


def test_resume_refuses_other_steps_with_the_reason(prior, tmp_path):
    train(tiny("gd", tmp_path, steps=4), prior, stop_at=2, write_outputs=False)
    with pytest.raises(ValueError, match=r"fields \['steps'\]\) \(the sigma, noise and learning-rate schedules"):
        train(tiny("gd", tmp_path, steps=6), prior)


def test_sigma_draws_are_the_ticks_in_the_annealed_range(prior):
    """Oracle: the ticks selected by tensor comparison (float32, as the prior stores them) and
    the draw's frequency: every tick of the range is drawn, none outside it, about uniformly."""
    from gdbench.train.views import sample_sigma

    cfg = tiny("gd", steps=100, sigma_min=0.05, sigma_max=2.0)
    ctx = make_context(cfg, prior)
    s = ctx.sigmas
    g = torch.Generator().manual_seed(2)
    for step in (0, 50, 90):
        hi = 2.0 + (0.05 - 2.0) * step / 99
        ticks = set(s[(s >= 0.05) & (s <= max(hi, 0.05))].tolist())
        draws = [sample_sigma(ctx, step, g)[0] for _ in range(40 * len(ticks))]
        assert set(draws) == ticks
        counts = [draws.count(t) for t in ticks]
        assert max(counts) < 3 * min(counts)
    # a range holding no tick: the tick nearest sigma_min
    ctx = make_context(tiny("gd", sigma_min=float(s[3] + s[4]) / 2, sigma_max=float(s[3] + s[4]) / 2 + 1e-9), prior)
    want = float(s[torch.argmin((s - ctx.cfg.sigma_min).abs())])
    assert sample_sigma(ctx, 0, g) == (want, 1.0)


# -------------------------------------------------------------------- the mechanisms as wired
@pytest.mark.parametrize("redraw", ["run", "ou", "step"])
def test_train_step_redraws_the_noise_colours_as_configured(prior, redraw):
    """What reaches the noise renderer, captured by wrapping it: with redraw 'run' every step
    renders the initial draw of the colours (drawn here on its own from the seed's stream); with
    'ou' (beta 0.2) successive steps' colours correlate sqrt(1 - beta); with 'step' they do not."""
    from gdbench.mechanisms.noise import init_colors
    from gdbench.train.streams import make_streams

    cfg = tiny("gd", noise=NoiseConfig(n_gaussians=400, scale=0.05, redraw=redraw, ou_beta=0.2), steps=6)
    ctx = make_context(cfg, prior)
    seen = []
    render = ctx.noise.render

    def capture(colors, cams, *, generator, **kw):
        seen.append(colors.detach().clone())
        return render(colors, cams, generator=generator, **kw)

    ctx.noise.render = capture
    state = init_state(ctx)
    for _ in range(5):
        train_step(state, ctx)
    assert len(seen) == 5
    first = init_colors(ctx.noise.cloud, generator=make_streams(cfg.seed)["noise_colors"]).colors
    n = first.numel()
    corr = [float(torch.corrcoef(torch.stack([a.flatten(), b.flatten()]))[0, 1]) for a, b in itertools.pairwise(seen)]
    if redraw == "run":
        assert all(torch.equal(c, first) for c in seen)
    elif redraw == "ou":
        assert torch.equal(seen[0], first)
        assert all(abs(r - math.sqrt(0.8)) < 5 * 0.2 / math.sqrt(n) + 0.01 for r in corr), corr
        # the drift is stationary: unit variance at every step (5 standard errors of a variance)
        assert all(abs(float(c.var()) - 1) < 5 * math.sqrt(2 / n) for c in seen), [float(c.var()) for c in seen]
    else:
        assert all(abs(r) < 5 / math.sqrt(n) for r in corr), corr


def test_views_spread_reaches_the_noise_renderer(prior):
    """--views-per-step 4 --views-spread-deg 10: every step hands the noise renderer four cameras
    whose azimuth and elevation (read back from the camera centres) lie within 10 degrees of the
    first's; without the spread the same steps' views lie far apart."""
    widest = {}
    for spread in (10.0, None):
        cfg = tiny("gd", views_per_step=4, views_spread_deg=spread, steps=8)
        ctx = make_context(cfg, prior)
        seen = []
        render = ctx.noise.render

        def capture(colors, cams, *, generator, render=render, seen=seen, **kw):
            seen.append(cams.centers.detach().double().clone())
            return render(colors, cams, generator=generator, **kw)

        ctx.noise.render = capture
        state = init_state(ctx)
        for _ in range(6):
            train_step(state, ctx)
        assert len(seen) == 6 and all(len(c) == 4 for c in seen)
        off = []
        for c in seen:
            az = torch.rad2deg(torch.atan2(c[:, 1], c[:, 0]))
            el = torch.rad2deg(torch.asin(c[:, 2] / c.norm(dim=-1)))
            off.append(torch.cat([((az[1:] - az[0] + 180) % 360 - 180).abs(), (el[1:] - el[0]).abs()]))
        widest[spread] = float(torch.cat(off).max())
    assert widest[10.0] <= 10.0 + 1e-3, widest
    assert widest[None] > 45, widest


def test_train_step_hands_the_renderer_the_jittered_gaussians_and_the_paired_views(prior, monkeypatch):
    """What reaches the rasterizer, captured by wrapping it: under VGS the means and log-scales
    depart from the parameters with the standard deviations of the jitter formula, gamma s(sigma)
    (times the length unit for the means), s(sigma) = sigma / sqrt(1 + sigma^2) (within 5%, 2000
    Gaussians); without VGS they are the parameters themselves; and gd and gd-no-vgs render the
    same cameras at every step (the jitter draws from its own stream)."""
    import renderers.splat as splat

    calls = []
    rasterize = splat.rasterize

    def capture(means, quats, scales, *args, **kw):
        calls.append((means.detach().clone(), scales.detach().log().clone(), args[2].clone()))
        return rasterize(means, quats, scales, *args, **kw)

    monkeypatch.setattr(splat, "rasterize", capture)
    cams = {}
    for name in ("gd", "gd-no-vgs"):
        cfg = tiny(name, init_points=2000, steps=8, vgs_gamma=0.2)
        ctx = make_context(cfg, prior)
        state = init_state(ctx)
        cams[name] = []
        for _ in range(3):
            before = state.params["means"].detach().clone(), state.params["log_scales"].detach().clone()
            calls.clear()
            m = train_step(state, ctx)
            means, log_scales, viewmats = calls[0]
            cams[name].append(viewmats)
            if name == "gd-no-vgs":
                assert torch.equal(means, before[0]) and torch.allclose(log_scales, before[1], atol=1e-6)
                continue
            amp = 0.2 * m["sigma"] / math.sqrt(1 + m["sigma"] ** 2)
            assert float((means - before[0]).std()) == pytest.approx(amp * ctx.jitter_length, rel=0.05)
            assert float((log_scales - before[1]).std()) == pytest.approx(amp, rel=0.05)
    for a, b in zip(cams["gd"], cams["gd-no-vgs"]):
        assert torch.equal(a, b)
