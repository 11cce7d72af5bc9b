"""Densification: the schedule a run resolves (fractions of its length, the rules no schedule
breaks), the per-view screen-space statistic, clone/split/prune/reset on constructed cases, and
a short run that ends with its opacities recovered."""

import math

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.config import TrainConfig, preset
from gdbench.train.densify import PARAM_NAMES, DensifyConfig, DensifyStrategy
from gdbench.train.run import train
from gdbench.train.trainer import init_state, make_context, train_step
from tests._util import tiny_bank

CAPTION = "a test blob"


# -------------------------------------------------------------------- the schedule
def _events(start, stop, every, reset_every, n):
    """Brute force over every step of an n-step run, straight from the definitions: grow at the
    multiples of ``every`` in (start, stop], reset at the multiples of ``reset_every`` up to stop."""
    grows = [s for s in range(1, n + 1) if start < s <= stop and s % every == 0]
    resets = [s for s in range(1, n + 1) if s <= stop and s % reset_every == 0]
    return grows, resets


def test_the_paper_schedule_at_2000_steps_and_the_readme_one_at_1000():
    """The defaults are the paper's numbers at its 2000 steps (densify every 50 after 300 until
    1500, reset every 400) and the hand-scaled 1000-step schedule the README used before."""
    s = DensifyConfig().resolve(2000)
    assert (s.start, s.stop, s.every, s.reset_every) == (300, 1500, 50, 400)
    assert s.grow_steps() == list(range(350, 1501, 50)) and s.reset_steps() == [400, 800, 1200]
    s = DensifyConfig().resolve(1000)
    assert (s.start, s.stop, s.every, s.reset_every) == (150, 750, 25, 200)
    assert s.reset_steps() == [200, 400, 600]
    assert TrainConfig().densify.resolve(TrainConfig().steps) == DensifyConfig().resolve(2000)


explicit = st.one_of(st.none(), st.integers(0, 25000))
positive = st.one_of(st.none(), st.integers(1, 25000))


@settings(max_examples=300, deadline=None)
@given(
    n=st.integers(1, 20000),
    start=explicit,
    stop=explicit,
    every=positive,
    reset_every=positive,
    recover=st.sampled_from([0, 1, 50, 100, 500]),
)
def test_no_schedule_puts_an_event_on_the_last_step_or_a_reset_in_the_final_stretch(
    n, start, stop, every, reset_every, recover
):
    cfg = DensifyConfig(start=start, stop=stop, every=every, reset_every=reset_every, recover_steps=recover)
    limit = n - recover  # the last step a reset may fall on
    start_ = start if start is not None else math.floor(0.15 * n + 0.5)
    every_ = every if every is not None else max(25, math.floor(0.025 * n + 0.5))  # the floor: min_every
    stop_ = stop if stop is not None else min(math.floor(0.75 * n + 0.5), n - 1)
    raw_grows, _ = _events(start_, stop_, every_, 1, n)
    explicit_growth = any(v is not None for v in (start, stop, every))
    try:
        s = cfg.resolve(n)
    except ValueError as e:  # refused only for an explicit setting, when the raw schedule breaks a rule
        msg = str(e)
        assert f"{n}-step run" in msg
        if "--densify-stop)" in msg:
            assert stop is not None and raw_grows and raw_grows[-1] == n and f"at most {n - 1}" in msg
        elif "no step of a" in msg:
            assert explicit_growth and not raw_grows and "--no-densify" in msg
        else:
            assert "--densify-reset-every" in msg and reset_every is not None
            _, resets = _events(0, stop_, reset_every, reset_every, n)
            until = max(0, min(stop_, limit))
            assert resets and resets[-1] > until
            assert (f"at or before step {until}" if until else "too short for one") in msg
        return
    grows, resets = _events(s.start, s.stop, s.every, s.reset_every, n)
    assert s.grow_steps() == grows == raw_grows
    assert all(g < n for g in grows), "a densification on the last step"
    assert grows or not explicit_growth, "an explicit schedule that never densifies"
    assert s.reset_steps() == [r for r in resets if r <= limit]
    assert all(r <= limit for r in s.reset_steps()), "a reset in the final stretch"
    # explicit values keep their meaning as absolute steps; unset ones are fractions of the run
    assert (s.start, s.every) == (start_, every_)
    if stop is not None:
        assert s.stop == stop
    if reset_every is not None:  # an explicit interval is never thinned silently
        assert s.reset_every == reset_every and s.reset_steps() == resets
    else:  # the default interval loses only the resets in the final stretch
        assert s.reset_every == max(1, math.floor(0.2 * n + 0.5))


@pytest.mark.parametrize(
    ("steps", "kw", "match"),
    [
        (1000, dict(stop=1000), r"densify.stop \(--densify-stop\): 1000 densifies on the last step of a 1000-step "
         r"run .*expected at most 999"),
        (400, dict(stop=1500), r"--densify-stop.*400-step run.*at most 399"),
        (2000, dict(stop=1950, reset_every=650), r"--densify-reset-every\): 650 puts an opacity reset at step 1950 "
         r"of a 2000-step run, 50 steps before its end; the last reset must be at least 100 steps before the end "
         r"\(densify.recover_steps\), so at or before step 1900"),
        (1000, dict(reset_every=475, stop=999), r"--densify-reset-every.*reset at step 950 of a 1000-step run.*"
         r"at or before step 900"),
    ],
)  # fmt: skip
def test_explicit_schedules_that_break_the_rules_fail_before_training(steps, kw, match, tmp_path):
    """The error names the flag, the run's length and the limit, when the config is built (so
    before the prior, the folder or a step)."""
    with pytest.raises(ValueError, match=match):
        preset("gd", steps=steps, out=tmp_path / "x", **{f"densify.{k}": v for k, v in kw.items()})
    assert not (tmp_path / "x").exists()


def test_the_cli_refuses_a_densification_on_the_last_step(tmp_path):
    import subprocess
    import sys

    out = tmp_path / "r"
    argv = ["generate", "a yellow duck", "--steps", "800", "--densify-stop", "800", "--out", str(out)]
    p = subprocess.run([sys.executable, "-m", "gdbench.app.cli", *argv], capture_output=True, text=True)
    assert p.returncode == 2, p.stderr
    assert "gdbench generate: error: densify.stop (--densify-stop): 800" in p.stderr
    assert "800-step run" in p.stderr and "at most 799" in p.stderr and "Traceback" not in p.stderr
    assert not out.exists()


# -------------------------------------------------------------------- the per-view statistic
@pytest.fixture(scope="module")
def one_image_prior():
    """A bank of one image: the posterior mean is that image whatever the query and its noise,
    so the score of a view depends on the render only."""
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION, azimuths=1, elevations=(0.0,))})


@pytest.mark.parametrize("preset_name", ["gd-no-vgs", "sjc-gs"])
def test_a_camera_rendered_b_times_accumulates_the_statistic_of_one_view(preset_name, one_image_prior):
    """Oracle: one step that renders the same camera B = 1, 2, 4 times (fixed pose ranges, no
    jitter, a denoiser that ignores the noise) accumulates the same per-Gaussian average
    screen-space gradient as B = 1, with B times the visibility count."""
    stats = {}
    for b in (1, 2, 4):
        cfg = preset(
            preset_name,
            prompt=CAPTION,
            steps=10,
            densify_every=5,  # a 10-step run densifies by default no more (densify.min_every)
            resolution=16,
            init_points=150,
            views_per_step=b,
            fovy_range=(50.0, 50.0),
            azimuth_range=(30.0, 30.0),
            elevation_range=(10.0, 10.0),
            progress=False,
        )
        ctx = make_context(cfg, one_image_prior)
        state = init_state(ctx)
        assert ctx.strategy.collects(1) and not any(ctx.strategy.is_due(1))
        train_step(state, ctx)
        stats[b] = (state.densify.grad2d.clone(), state.densify.count.clone())
    g1, c1 = stats[1]
    assert float(c1.sum()) > 50 and float(g1.sum()) > 0  # most of the ball is seen, with gradients
    for b in (2, 4):
        g, c = stats[b]
        assert torch.equal(c, b * c1)
        torch.testing.assert_close(g / c.clamp_min(1), g1 / c1.clamp_min(1), rtol=1e-5, atol=1e-12)


# -------------------------------------------------------------------- clone, split, prune, reset
def test_densify_constructed_case():
    """3 hot Gaussians (one small: clone; one large: split; one transparent: pruned) + 1 cold."""
    n = 4
    params = {
        "means": torch.zeros(n, 3),
        "quats": torch.tensor([[1.0, 0, 0, 0]] * n),
        "log_scales": torch.log(torch.tensor([[0.001] * 3, [0.1] * 3, [0.001] * 3, [0.001] * 3])),
        "opacity_logits": torch.logit(torch.tensor([0.5, 0.5, 0.001, 0.5])),
        "sh": torch.arange(n, dtype=torch.float32)[:, None, None].expand(n, 1, 3).clone(),
        "sh_rest": torch.arange(n, dtype=torch.float32)[:, None, None].expand(n, 3, 3).clone() + 10,
    }
    params = {k: v.requires_grad_(True) for k, v in params.items()}
    opt = torch.optim.Adam([{"params": [params[k]], "lr": 0.1, "name": k} for k in PARAM_NAMES])
    sum(v.sum() for v in params.values()).backward()
    opt.step()
    with torch.no_grad():  # identify rows by their colour (and the higher bands by colour + 10)
        params["sh"][:] = torch.arange(n, dtype=torch.float32)[:, None, None]
        params["sh_rest"][:] = torch.arange(n, dtype=torch.float32)[:, None, None] + 10
    old_m = opt.state[params["sh"]]["exp_avg"].clone()
    scale1 = params["log_scales"].detach()[1].exp()
    cfg = DensifyConfig(start=0, every=1, grad_threshold=0.5, percent_dense=0.01, prune_opacity=0.01, max_growth=1.0)
    strat = DensifyStrategy(cfg, steps=10)
    st = strat.init_state(n)
    st.grad2d[:] = torch.tensor([1.0, 1.0, 1.0, 0.0])
    st.count[:] = 1
    st, info = strat.step(params, opt, st, step=1, generator=torch.Generator().manual_seed(0))
    # 0 and 2 are cloned, 1 is split in two, and the transparent 2 is pruned with its clone (3DGS order)
    assert (info["cloned"], info["split"], info["pruned"]) == (2, 1, 2)
    sh = params["sh"][:, 0, 0].tolist()
    assert (params["sh_rest"][:, :, :] == params["sh"][:, :1, :] + 10).all()  # every band moves with its row
    assert sh == [0.0, 3.0, 0.0, 1.0, 1.0]  # kept rows first, then clones, then split halves
    halves = params["log_scales"][torch.tensor(sh) == 1.0].exp()
    torch.testing.assert_close(halves, (scale1 / 1.6).expand_as(halves))
    m = opt.state[params["sh"]]["exp_avg"]
    torch.testing.assert_close(m[:2], old_m[[0, 3]])  # kept rows keep their moments
    assert float(m[2:].abs().sum()) == 0.0  # new rows start at zero
    assert st.grad2d.shape == (5,) and float(st.grad2d.sum()) == 0


@pytest.mark.parametrize(("max_growth", "grown"), [(0.3, 3), (0.45, 4), (1.0, 6)])
def test_one_densification_grows_at_most_max_growth_of_the_scene_hottest_first(max_growth, grown):
    """10 small opaque Gaussians, 6 above the threshold with distinct statistics: a densification
    clones floor(max_growth * 10) of them (all 6 when that is more), the hottest, and no other."""
    n = 10
    params = {
        "means": torch.arange(n, dtype=torch.float32)[:, None].expand(n, 3).clone(),
        "quats": torch.tensor([[1.0, 0, 0, 0]] * n),
        "log_scales": torch.full((n, 3), math.log(0.001)),
        "opacity_logits": torch.zeros(n),
        "sh": torch.zeros(n, 1, 3),
        "sh_rest": torch.zeros(n, 0, 3),
    }
    params = {k: v.requires_grad_(True) for k, v in params.items()}
    opt = torch.optim.Adam([{"params": [params[k]], "lr": 0.1, "name": k} for k in PARAM_NAMES])
    cfg = DensifyConfig(start=0, every=1, grad_threshold=0.5, max_growth=max_growth)
    strat = DensifyStrategy(cfg, steps=10)
    st = strat.init_state(n)
    heat = torch.tensor([0.9, 0.1, 3.0, 0.6, 0.2, 2.0, 0.3, 1.5, 0.7, 0.0])  # hot: 2 > 5 > 7 > 0 > 8 > 3
    st.grad2d[:] = heat
    st.count[:] = 1
    _, info = strat.step(params, opt, st, step=1, generator=torch.Generator().manual_seed(0))
    assert (info["cloned"], info["split"], info["pruned"]) == (grown, 0, 0)
    clones = params["means"][n:, 0].tolist()  # a clone keeps its original's mean: x = its index
    assert sorted(clones) == sorted([2.0, 5.0, 7.0, 0.0, 8.0, 3.0][:grown])


def test_opacity_reset_caps_opacities():
    params = {
        k: v.requires_grad_(True)
        for k, v in {
            "means": torch.zeros(2, 3),
            "quats": torch.tensor([[1.0, 0, 0, 0]] * 2),
            "log_scales": torch.zeros(2, 3),
            "opacity_logits": torch.logit(torch.tensor([0.9, 0.01])),
            "sh": torch.zeros(2, 1, 3),
            "sh_rest": torch.zeros(2, 0, 3),
        }.items()
    }
    opt = torch.optim.Adam([{"params": [params[k]], "lr": 0.1, "name": k} for k in PARAM_NAMES])
    strat = DensifyStrategy(DensifyConfig(reset_every=10, reset_value=0.05, start=100), steps=1000)
    strat.step(params, opt, strat.init_state(2), step=10, generator=torch.Generator())
    torch.testing.assert_close(torch.sigmoid(params["opacity_logits"].detach()), torch.tensor([0.05, 0.01]))


# -------------------------------------------------------------------- a run ends trained
def test_a_run_that_used_to_end_on_a_reset_ends_with_trained_opacities(tmp_path):
    """The default duck at 400 steps: the absolute schedule (reset every 400 steps) capped every
    opacity at 0.05 on the last step, a pale ghost (mean opacity of the Gaussians the held-out
    views see: 0.040). Now the last reset sits well before the end: the opacities the scene shows
    are well above the reset value, and the scene holds no two identical Gaussians (a clone on
    the last step left ~70 exact duplicates at 600 steps)."""
    from gdbench.metrics.gt import heldout_poses
    from renderers.splat import rasterize

    cfg = preset("gd", steps=400, out=tmp_path, progress=False)
    sched = cfg.densify.resolve(cfg.steps)
    assert sched.reset_steps()[-1] <= 300 and sched.grow_steps()[-1] < 400
    r = train(cfg, write_outputs=False)
    assert any(h.get("reset") for h in r.state.history) and any(h.get("cloned") for h in r.state.history)
    scene = r.state.scene()
    cams = heldout_poses(12).cameras(64, 64)
    with torch.no_grad():
        out = rasterize(**scene.render_args(), viewmats=cams.viewmats, Ks=cams.Ks, width=64, height=64,
                        outputs=("rgb", "visible"))  # fmt: skip
    seen = out.visible.any(0)
    opacity = torch.sigmoid(scene.opacity_logits)[seen]
    assert seen.sum() > 1000 and float(opacity.mean()) > 2 * cfg.densify.reset_value, float(opacity.mean())
    rows = torch.cat([scene.means, scene.log_scales, scene.opacity_logits[:, None], scene.sh.flatten(1)], 1)
    assert torch.unique(rows, dim=0).shape[0] == rows.shape[0]


def test_a_quantile_threshold_grows_the_top_share_whatever_the_scale():
    """grad_quantile 0.9 over 100 seen Gaussians (and 20 unseen, which do not count): the 10 with
    the largest statistic grow, and scaling every gradient by 1000 changes nothing (a fixed
    threshold grows all of them, or none)."""
    g = torch.Generator().manual_seed(1)
    n = 120
    stat = torch.rand(n, generator=g) * 1e-4
    count = torch.cat([torch.ones(100), torch.zeros(20)])
    grown = {}
    for scale in (1.0, 1000.0):
        params = {
            "means": torch.zeros(n, 3),
            "quats": torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).clone(),
            "log_scales": torch.full((n, 3), math.log(1e-3)),
            "opacity_logits": torch.zeros(n),
            "sh": torch.zeros(n, 1, 3),
            "sh_rest": torch.zeros(n, 0, 3),
        }
        params = {k: v.requires_grad_(True) for k, v in params.items()}
        opt = torch.optim.Adam([{"params": [params[k]], "lr": 0.1, "name": k} for k in PARAM_NAMES])
        strat = DensifyStrategy(DensifyConfig(start=0, every=1, grad_quantile=0.9), steps=10)
        st = strat.init_state(n)
        st.grad2d[:] = stat * count * scale
        st.count[:] = count
        _, info = strat.step(params, opt, st, step=1, generator=torch.Generator())
        grown[scale] = info["cloned"] + info["split"]
    want = int((stat[:100] > torch.quantile(stat[:100].double(), 0.9).float()).sum())
    assert grown[1.0] == grown[1000.0] == want == 10
    fixed = DensifyStrategy(DensifyConfig(start=0, every=1), steps=10)
    assert fixed.threshold(stat, count) == 2e-4 and float((stat > 2e-4).sum()) == 0  # none would grow


@pytest.mark.parametrize(("when", "step", "pruned"), [("start", 4, True), ("reset", 4, False), ("reset", 12, True)])
def test_the_world_size_prune_starts_when_configured(when, step, pruned):
    """A Gaussian larger than prune_scale x extent goes at the first densification ('start'), or
    only after the first opacity reset at step 10 ('reset', as 3DGS and gsplat do)."""
    n = 3
    params = {
        "means": torch.zeros(n, 3),
        "quats": torch.tensor([[1.0, 0, 0, 0]]).expand(n, 4).clone(),
        "log_scales": torch.log(torch.tensor([[0.3] * 3, [0.01] * 3, [0.01] * 3])),  # 0.3 > 0.5 x 0.5
        "opacity_logits": torch.zeros(n),
        "sh": torch.zeros(n, 1, 3),
        "sh_rest": torch.zeros(n, 0, 3),
    }
    params = {k: v.requires_grad_(True) for k, v in params.items()}
    opt = torch.optim.Adam([{"params": [params[k]], "lr": 0.1, "name": k} for k in PARAM_NAMES])
    strat = DensifyStrategy(DensifyConfig(start=0, every=4, reset_every=10, prune_scale_from=when), steps=1000)
    _, info = strat.step(params, opt, strat.init_state(n), step=step, generator=torch.Generator())
    assert info["pruned"] == int(pruned) and params["means"].shape[0] == n - int(pruned)


def test_densify_false_on_the_command_line_trains_without_densification(tmp_path):
    """--no-densify reaches the config: run.json records a schedule with no step, and a
    densification flag beside it is refused as doing nothing."""
    import json

    from gdbench.app.cli import main
    from gdbench.app.cmd_generate import Generate, GenerateTrain

    out = tmp_path / "r"
    main(Generate("a yellow duck", out=out, score=False, progress=False,
                  train=GenerateTrain(steps=40, resolution=16, densify=False)))  # fmt: skip
    run = json.loads((out / "run.json").read_text())
    assert run["densify_schedule"]["enabled"] is False and run["densify_schedule"]["grow_steps"] == []
    assert run["gaussians"] == 4096  # nothing cloned, split or pruned
    with pytest.raises(ValueError, match=r"--densify-every acts only with --densify \(this run: --no-densify\)"):
        main(Generate("a yellow duck", out=tmp_path / "x", train=GenerateTrain(densify=False, densify_every=5)))


def test_a_render_without_screen_gradients_is_named_not_silently_counted():
    """The statistic is |d loss / d means2d| per view in units of half the image (the closed form
    below), summed over views with their counts; a ``means2d`` that lies off the loss's graph (the
    gsplat backend's bug of 9ca308a: a copy, whose retained gradient stays None) leaves the state as
    it was and says so in a warning, instead of letting no Gaussian grow without a word."""
    strat = DensifyStrategy(DensifyConfig(start=0, every=1), steps=10)
    state = strat.init_state(3)
    leaf = torch.zeros(2, 3, 2, requires_grad=True)
    m2d = leaf * 1.0
    m2d.retain_grad()
    (m2d * torch.tensor([[1.0, 2.0]]).expand(2, 3, 2)).sum().backward()
    visible = torch.tensor([[True, True, False], [True, False, False]])
    got = strat.accumulate(state, m2d, visible, 8, 4)
    per_view = ((1.0 * 4 * 2) ** 2 + (2.0 * 2 * 2) ** 2) ** 0.5  # grad (1, 2) scaled by (W/2, H/2) and C = 2
    assert got.grad2d.tolist() == pytest.approx([2 * per_view, per_view, 0.0])
    assert got.count.tolist() == [2.0, 1.0, 0.0]
    off = leaf * 1.0
    off.retain_grad()
    (m2d.detach() * leaf).sum().backward()  # the loss does not pass through ``off``
    with pytest.warns(RuntimeWarning, match="no gradient, so no Gaussian can grow"):
        same = strat.accumulate(state, off, visible, 8, 4)
    assert same is state
