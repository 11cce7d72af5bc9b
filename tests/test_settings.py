"""Settings: each has one dotted key in the code and one option on the command line, derived; an
"acts only with" rule sits beside its field (``When``) or comes from its group's ``enabled``
switch, and one walker (``core.constraints.inactive``) writes every message. The oracles are this
file's own tables, written by hand from the docs, not read from the code."""

import dataclasses
import inspect
from pathlib import Path

import pytest

from gdbench.train.config import PRESETS, TrainConfig, apply_overrides, key_of, preset, setting_names

CONDITIONAL = {
    "sigma_min", "sigma_max", "anneal", "init_ply", "init_color", "sh_degree", "log_every",
    "views.spread_deg", "noise.ou_beta", "prior.view_window_deg", "prior.front_bias", "prior.semantic_steps",
    "prior.sd_controlnet",
    # the noise cloud's settings: gdbench's own sources only (a user's source replaces the cloud)
    "noise.n_gaussians", "noise.radius", "noise.scale", "noise.opacity", "noise.azimuth_range",
    "noise.elevation_range", "noise.redraw", "noise.v_min",
}  # fmt: skip
"""Fields with a rule of their own (docs/training.md's options table)."""

SWITCHED = {"noise", "vgs", "densify"}
"""Groups switched on and off by their ``enabled`` field: every other field acts only when on."""

EXAMPLES = Path(__file__).resolve().parents[1] / "docs" / "examples"

CASES = [
    # (preset, overrides that make the option inert, the option, the message's words)
    ("gd", {"noise.source": f"{EXAMPLES / 'my_method.py'}:smooth_noise"}, "noise.n_gaussians",
     "--noise-n-gaussians acts only with --noise-source cloud or --noise-source pose (this run: --noise-source /"),
    ("sds-gs", {}, "sigma_min", "--sigma-min acts only with --guidance other than sds (this run: --guidance sds)"),
    ("sds-gs", {}, "anneal", "--anneal acts only with --guidance other than sds (this run: --guidance sds)"),
    ("gd", {}, "init_ply", "--init-ply acts only with --init ply (this run: --init sphere)"),
    ("gd", {"init": "bank-depth"}, "init_color", "--init-color acts only with --init sphere (this run: --init bank"),
    ("gd", {"prior": "sd", "init": "ply", "init_ply": "p"}, "init_color",
     "--init-color acts only with --init sphere or --sd"),
    ("gd", {"prior": "sd", "sd_mode": "latent"}, "sh_degree", "--sh-degree acts only with --sd-mode other than latent"),
    ("gd", {"progress": False}, "log_every", "--log-every acts only with --progress or --log-dir"),
    ("gd", {}, "views_spread_deg", "--views-spread-deg acts only with --views-per-step 2 or more"),
    ("gd", {}, "noise_ou_beta", "--noise-ou-beta acts only with --noise-redraw ou (this run: --noise-redraw run)"),
    ("gd-no-sn", {}, "noise_ou_beta", "--noise-ou-beta acts only with --structured-noise (this run: --no-"),
    ("gd-no-sn", {}, "noise_redraw", "--noise-redraw acts only with --structured-noise"),
    ("gd-no-vgs", {}, "vgs_gamma", "--vgs-gamma acts only with --vgs (this run: --no-vgs)"),
    ("gd", {"densify": False}, "densify_every", "--densify-every acts only with --densify (this run: --no-densify)"),
    ("gd", {"view_prompting": "none"}, "view_window_deg", "--view-window-deg acts only with --view-prompting window"),
    ("gd", {"prior": "learned", "learned_model": "front"}, "front_bias", "--front-bias acts only with --learned-model"),
    ("gd", {"prior": "sd"}, "semantic_steps", "--semantic-steps acts only with --semantic-code"),
    ("gd", {"prior": "sd", "depth_conditioning": True}, "sd_controlnet", "--sd-controlnet acts only with --sd-model"),
]  # fmt: skip
"""Each rule broken once, and the message a user reads."""

ACTS = [
    ("sjc-gs", {}, "sigma_min"),
    ("gd", {"init": "ply", "init_ply": "x.ply"}, "init_ply"),
    ("gd", {"prior": "sd", "sd_mode": "latent", "init": "ply", "init_ply": "x.ply"}, "init_color"),
    ("gd", {"progress": False, "log_dir": "tb"}, "log_every"),
    ("gd", {"views_per_step": 2}, "views_spread_deg"),
    ("gd", {"noise_redraw": "ou"}, "noise_ou_beta"),
    ("gd", {"prior": "learned"}, "front_bias"),
    ("gd", {"prior": "sd", "depth_conditioning": True, "sd_model": "some/folder"}, "sd_controlnet"),
]
"""The same rules met: no message."""


def _tree(cls, prefix=""):
    """(dotted key, class holding it, field) over TrainConfig, its groups and every prior's config."""
    from gdbench.priors.factory import PRIOR_CONFIGS
    from gdbench.train.config import NESTED

    for f in dataclasses.fields(cls):
        if cls is TrainConfig and f.name in NESTED:
            yield from _tree(NESTED[f.name], f.name + ".")
        elif cls is TrainConfig and f.name == "prior":
            for c in PRIOR_CONFIGS.values():
                yield from _tree(c, "prior.")
        else:
            yield prefix + f.name, cls, f


def test_every_rule_sits_beside_its_field():
    from gdbench.core.constraints import When, _markers

    marked = {key for key, cls, f in _tree(TrainConfig) if _markers(cls, f.name, When)}
    assert marked == CONDITIONAL
    switched = {key.split(".")[0] for key, _, f in _tree(TrainConfig) if f.name == "enabled"}
    assert switched == SWITCHED


@pytest.mark.parametrize(("name", "overrides", "option", "message"), CASES)
def test_an_inert_option_is_named_with_what_it_needs(name, overrides, option, message):
    from gdbench.train.options import inert_options

    cfg = preset(name, **overrides)
    lines = inert_options(cfg, [option])
    assert len(lines) == 1 and lines[0].startswith(message), lines


@pytest.mark.parametrize(("name", "overrides", "option"), ACTS)
def test_an_option_that_acts_is_taken(name, overrides, option):
    from gdbench.train.options import inert_options

    assert inert_options(preset(name, **overrides), [option]) == []


def test_one_name_per_setting_and_one_option_derived_from_it():
    """Every option the command line offers is a setting's name (``key_of`` reads it back to its
    key), no two keys share an option, and the renamed ones stay as aliases."""
    from gdbench.core.constraints import flag
    from gdbench.priors.factory import PRIOR_CONFIGS
    from gdbench.train.options import train_options

    keys = {key for key, _, _ in _tree(TrainConfig)}
    options = {}
    for key in keys:
        options.setdefault(flag(key, TrainConfig), set()).add(key)
    assert all(len(v) == 1 for v in options.values()), {k: v for k, v in options.items() if len(v) > 1}
    assert flag("noise.enabled", TrainConfig) == "--structured-noise" and flag("noise.ratio") == "--noise-ratio"
    for kind in PRIOR_CONFIGS:
        for f in dataclasses.fields(train_options((), kind)):
            if f.name != "prior":
                assert key_of(f.name) in keys, f.name
    for old, new in {"structured_noise": "noise.enabled", "noise.ratio_mode": "noise.ratio",
                     "view_prompting": "prior.view_prompting", "vgs_gamma": "vgs.gamma",
                     "views_per_step": "views.per_step", "prior.sd_model": "prior.sd_model"}.items():  # fmt: skip
        assert key_of(old) == new
    assert set(setting_names().values()) == keys
    with pytest.raises(ValueError, match="unknown setting 'noise_colour'"):
        key_of("noise_colour")


def test_old_names_make_the_same_configs():
    """A preset with its switch set by the old names is the preset itself (run ids included)."""
    from gdbench.train.run import run_id

    old = apply_overrides(PRESETS["gd"], {"structured_noise": False, "preset": "gd-no-sn"})
    assert old == PRESETS["gd-no-sn"] and run_id(old) == run_id(PRESETS["gd-no-sn"])
    a = preset("gd", **{"noise.ratio_mode": "amplitude", "view_prompting": "none"})
    b = preset("gd", noise_ratio="amplitude", **{"prior.view_prompting": "none"})
    assert a == b and a.noise.ratio == "amplitude" and a.prior.view_prompting == "none"


def test_the_mixing_default_is_the_configs():
    from gdbench.mechanisms.noise import NoiseConfig, mix, structured_amplitude

    for fn in (mix, structured_amplitude):
        assert inspect.signature(fn).parameters["mode"].default == NoiseConfig().ratio


def test_a_sweep_file_takes_every_name_a_setting_had():
    """The sweep-file keys of today and of older files (run.json's nested form, the renamed ones)
    give the same options."""
    from gdbench.app.cmd_sweep import sweep_from_mapping

    old = {"presets": ["gd-no-sn"], "overrides": {"structured_noise": True, "noise": {"ratio_mode": "amplitude"},
                                                  "view_prompting": "none", "views_per_step": 2}}  # fmt: skip
    new = {"presets": ["gd-no-sn"], "overrides": {"noise.enabled": True, "noise_ratio": "amplitude",
                                                  "prior.view_prompting": "none", "views.per_step": 2}}  # fmt: skip
    a, b = (sweep_from_mapping(d, what="sweep.yaml").train.overrides() for d in (old, new))
    assert a == b == {"noise.enabled": True, "noise.ratio": "amplitude", "view_prompting": "none", "views.per_step": 2}
    with pytest.raises(ValueError, match="unknown training option 'noise_colour'"):
        sweep_from_mapping({"overrides": {"noise_colour": 1}}, what="sweep.yaml")


def test_a_group_passed_whole_keeps_what_moved_into_it():
    """Before the move a NoiseConfig did not hold the structured-noise switch, nor a prior's config
    view prompting: passing one whole keeps the run's (the same config, the same run id), unless it
    sets them or an override names them."""
    from gdbench.mechanisms.noise import NoiseConfig
    from gdbench.priors.learned.prior import LearnedPriorConfig
    from gdbench.train.run import run_id

    a = preset("sjc-gs", noise=NoiseConfig(n_gaussians=500))
    b = preset("sjc-gs", **{"noise.n_gaussians": 500})
    assert a == b and not a.noise.enabled and run_id(a) == run_id(b)
    assert preset("gd", noise=NoiseConfig(enabled=False)).noise.enabled is False
    assert preset("sjc-gs", noise=NoiseConfig(), structured_noise=True).noise.enabled is True
    c = apply_overrides(preset("gd", view_prompting="none"), {"prior": LearnedPriorConfig()})
    assert c.prior.kind == "learned" and c.prior.view_prompting == "none"
    d = apply_overrides(preset("gd", view_prompting="none"), {"prior": LearnedPriorConfig(view_prompting="buckets")})
    assert d.prior.view_prompting == "buckets"


def test_names_that_are_no_setting_are_refused():
    from gdbench.train.options import inert_options

    for bad in ("prior.steps", "prior.structured_noise", "noise.colour"):
        with pytest.raises(ValueError, match=r"unknown setting"):
            key_of(bad)
    assert key_of("views-per-step") == "views.per_step" and key_of("noise-ratio") == "noise.ratio"
    assert inert_options(preset("gd"), ["noise", "views", "vgs"]) == []  # groups (and switches) always act


def test_every_unmet_rule_is_named_and_only_the_prior_own_alternatives():
    from gdbench.train.options import inert_options

    line = inert_options(preset("gd", prior="sd"), ["sd_controlnet"])[0]
    assert line == ("--sd-controlnet acts only with --depth-conditioning and --sd-model other than tiny "
                    "(this run: --no-depth-conditioning, --sd-model tiny)")  # fmt: skip
    line = inert_options(preset("gd", init="ply", init_ply="x.ply"), ["init_color"])[0]
    assert line == "--init-color acts only with --init sphere (this run: --init ply)"


def test_each_group_checks_its_own_fields_once():
    """A group's bad value fails where the group is made, naming its flag (the config that holds
    it no longer walks it again)."""
    from gdbench.train.adam import OptimConfig

    with pytest.raises(ValueError, match=r"optim.colors \(--optim-colors\): expected a finite number"):
        OptimConfig(colors=True)
    with pytest.raises(ValueError, match=r"views\.spread_deg"):
        preset("gd", views_spread_deg=200.0)


def test_the_flat_layout_names_a_setting_added_to_a_flat_group():
    from gdbench.train.layout import flat_config

    flat = flat_config({"views": {"per_step": 2, "spread_deg": None, "jitter_deg": 0.0}, "vgs": {"enabled": True}})
    assert flat == {"views_per_step": 2, "views_spread_deg": None, "views_jitter_deg": 0.0, "vgs": True}
