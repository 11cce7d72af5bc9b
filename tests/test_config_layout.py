"""The training config as a tree (the prior a tagged union of its kinds' configs) and the one
converter from the flat run.json layout of earlier commits: every stored run.json loads with
its run id, --help offers only the chosen prior's options, and a prior's option typed for
another prior is one line naming the prior it needs."""

import json
from dataclasses import fields
from pathlib import Path

import pytest

from gdbench.train.checkpoint import RESUME_IGNORES, comparable
from gdbench.train.config import PRESETS, config_from_dict, preset
from gdbench.train.layout import LEGACY_PRIOR_DEFAULTS, flat_config
from gdbench.train.outputs import config_dict
from gdbench.train.run import run_id
from tests._util import cli, help_text, one_line

ROOT = Path(__file__).resolve().parent.parent
STORED = sorted([*(ROOT / "fixtures").rglob("*run.json"), *(ROOT / "docs").rglob("*run.json")])
"""Every run.json in the repository (fixtures/runs holds the flat layout of commit 95ebebe)."""


def test_the_repository_holds_run_json_files_of_every_prior():
    kinds = [json.loads(p.read_text())["config"]["prior"] for p in STORED]
    assert {"empirical", "learned", "sd"} <= {k if isinstance(k, str) else k["kind"] for k in kinds}


@pytest.mark.parametrize("path", STORED, ids=lambda p: p.name)
def test_every_stored_run_json_converts_with_its_run_id_and_back(path):
    """The id the run was written with is the id of the converted config (the ids hash the flat
    layout), and the tree's dict converts back to the same config."""
    stored = json.loads(path.read_text())
    cfg = config_from_dict(stored["config"], what=str(path))
    assert run_id(cfg) == stored["run_id"]
    tree = config_dict(cfg)
    assert isinstance(tree["prior"], dict) and tree["prior"]["kind"] == stored["config"]["prior"]
    assert config_from_dict(tree) == cfg
    flat = flat_config(tree)
    assert set(flat) == set(stored["config"])
    # the flat layout, value for value, but for fields added since at the value that behaves as before
    assert comparable(flat) == comparable(stored["config"])
    kept = RESUME_IGNORES & set(flat)
    assert {k: flat[k] for k in kept} == {k: stored["config"][k] for k in kept}
    assert {k for k, v in flat.items() if v != stored["config"][k]} <= {
        "noise",
        "densify",
    }  # noise.source, densify.min_every and max_growth since


def test_generate_with_a_stored_run_json_makes_the_run_of_the_same_id(tmp_path):
    from gdbench.app.cli import main
    from gdbench.app.cmd_generate import Generate

    stored = ROOT / "fixtures" / "runs" / "empirical_gd.run.json"
    main(Generate(config=stored, out=tmp_path / "again", score=False, progress=False))
    again = json.loads((tmp_path / "again" / "run.json").read_text())
    assert again["run_id"] == json.loads(stored.read_text())["run_id"]
    assert again["config"]["prior"] == {"kind": "empirical", "front_bias": 0.0, "variants": 1,
                                        "depth_conditioning": False, "view_prompting": "window",
                                        "view_window_deg": 45.0}  # fmt: skip


def test_a_flat_file_with_another_priors_setting_off_its_default_is_refused():
    d = json.loads((ROOT / "fixtures" / "runs" / "empirical_gd.run.json").read_text())["config"]
    with pytest.raises(ValueError, match=r"--sd-guidance acts only with --prior sd \(this run: --prior empirical\)"):
        config_from_dict(d | {"sd_guidance": 50.0})
    with pytest.raises(ValueError, match=r"--depth-conditioning acts only with --prior empirical or sd"):
        config_from_dict(d | {"prior": "learned", "depth_conditioning": True})


def test_switching_the_prior_keeps_the_settings_both_kinds_have():
    from gdbench.train.config import apply_overrides

    learned = apply_overrides(preset("gd", front_bias=2.0, variants=3), {"prior": "learned"})
    assert (learned.prior.front_bias, learned.prior.variants) == (2.0, 3)
    assert preset("gd", prior="sd", sd_mode="latent").prior.input_space == "latent"
    assert preset("gd", prior="sd", depth_conditioning=True).prior.input_space == "rgb+depth"
    with pytest.raises(ValueError, match=r"variants: the learned prior takes 1 or 3"):
        preset("gd", variants=2, prior="learned")
    with pytest.raises(ValueError, match=r"prior \(--prior\): expected one of \['empirical', 'learned', 'sd'\]"):
        preset("gd", prior="dalle")


def test_the_frozen_flat_defaults_are_the_prior_configs_defaults():
    """The flat layout's defaults (run ids depend on them) are what each prior's config defaults
    to: a default changed in a config would silently rename every run of the other priors."""
    from gdbench.priors.factory import PRIOR_CONFIGS
    from gdbench.train.layout import RENAMED

    moved = {new.removeprefix("prior.") for new in RENAMED.values()}  # view_prompting: every prior has it
    for kind, cls in PRIOR_CONFIGS.items():
        for f in fields(cls):
            if f.name not in moved:
                assert getattr(cls(), f.name) == LEGACY_PRIOR_DEFAULTS[f.name], (kind, f.name)
    names = {f.name for cls in PRIOR_CONFIGS.values() for f in fields(cls)}
    assert set(LEGACY_PRIOR_DEFAULTS) == names - moved
    assert all(any(f.name == name for f in fields(cls)) for cls in PRIOR_CONFIGS.values() for name in moved & names)
    assert all(c.prior == PRESETS["gd"].prior for c in PRESETS.values())


def test_sweep_files_of_the_flat_layout_load_with_their_priors_options():
    from gdbench.app.cmd_generate import load_mapping
    from gdbench.app.cmd_sweep import sweep_from_mapping, sweep_mapping

    cmd = sweep_from_mapping(load_mapping(ROOT / "fixtures" / "runs" / "sweep_learned.yaml"))
    assert cmd.train.prior == "learned" and cmd.train.learned_guidance == 2.0 and not hasattr(cmd.train, "sd_model")
    assert cmd.train.noise_redraw == "ou" and cmd.settings == ("easy", "janus")
    assert sweep_from_mapping(sweep_mapping(cmd)) == cmd
    plain = sweep_from_mapping(load_mapping(ROOT / "fixtures" / "runs" / "sweep_default.yaml"))
    assert plain.presets == ("gd", "sjc-gs") and plain.steps == 60 and hasattr(plain.train, "view_window_deg")


def _options(text: str) -> set[str]:
    import re

    return set(re.findall(r"(--[a-z][a-z0-9-]+)", text))


@pytest.mark.parametrize("command", ["generate", "sweep"])
def test_help_offers_only_the_chosen_priors_options(command):
    own = {
        "empirical": {"--front-bias", "--variants", "--depth-conditioning", "--view-window-deg"},
        "learned": {"--learned-model", "--learned-guidance", "--front-bias", "--variants"},
        "sd": {"--sd-model", "--sd-mode", "--sd-guidance", "--sd-controlnet", "--sd-dtype", "--semantic-code",
               "--semantic-steps", "--depth-conditioning"},
    }  # fmt: skip
    every = set().union(*own.values())
    for kind, mine in own.items():
        shown = _options(help_text(command, kind))
        assert mine <= shown and not (every - mine) & shown, (kind, (every - mine) & shown)
        assert {"--prior", "--steps" if command == "generate" else "--seeds", "--noise-redraw"} <= shown


def test_a_prior_option_typed_for_another_prior_is_one_line(monkeypatch, capsys, tmp_path):
    code, _, err = cli(monkeypatch, capsys, "generate", "a yellow duck", "--sd-guidance", "7", "--out", tmp_path / "x")
    line = one_line(err)
    want = "gdbench generate: error: --sd-guidance acts only with --prior sd (this run: --prior empirical)"
    assert code == 2 and line == want
    code, _, err = cli(monkeypatch, capsys, "sweep", "--prior", "learned", "--no-depth-conditioning", "--out", tmp_path)
    assert code == 2 and "--no-depth-conditioning acts only with --prior empirical or sd" in one_line(err)
    assert not (tmp_path / "x").exists() and not (tmp_path / "sweep.yaml").exists()


def test_a_run_json_names_the_prior_whose_options_its_command_line_takes(monkeypatch, capsys, tmp_path):
    """``generate --config`` of a learned run takes --learned-guidance without --prior learned."""
    stored = ROOT / "fixtures" / "runs" / "learned_front.run.json"
    out = tmp_path / "again"
    code, _, err = cli(monkeypatch, capsys, "generate", "--config", stored, "--learned-guidance", "1.5", "--steps", "2",
                       "--resolution", "32", "--out", out, "--no-score", "--no-progress")  # fmt: skip
    assert code == 0, err
    prior = json.loads((out / "run.json").read_text())["config"]["prior"]
    assert prior == {"kind": "learned", "learned_model": "front", "learned_guidance": 1.5, "front_bias": 0.0,
                     "variants": 3, "view_prompting": "window"}  # fmt: skip
