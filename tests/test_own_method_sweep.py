"""Your own method in a sweep: presets as named overlays on a built-in one (a guidance written
outside the package entering by reference), claims between any two presets, and a verdict that
reads rater labels when given and the judge otherwise, saying which (experiments/sweep.py,
experiments/outcome.py, docs/training.md "Your own method")."""

import csv
from pathlib import Path

import pytest
import yaml

from gdbench.experiments.sweep import SweepConfig, sweep
from tests._util import TINY_CELL

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "examples" / "my_method.py"
PROMPT = "a yellow duck"
MINE = {"gd-mine": {"base": "gd", "overrides": {"guidance": f"{EXAMPLE}:sjc_again"}}}
CLAIM = {"text": "my guidance cuts Janus results", "a": "gd-mine", "b": "gd", "metric": "janus", "fails_at": 1.0}


def _read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def _sweep(out, **kw):
    cfg = SweepConfig([PROMPT], ["gd", "gd-mine"], [0, 1], steps=4, out=out, colmap=False, overrides=TINY_CELL,
                      progress=False, settings=["janus"], defined_presets=MINE, claims=[CLAIM], **kw)  # fmt: skip
    return sweep(cfg)


@pytest.fixture(scope="module")
def own(tmp_path_factory):
    out = tmp_path_factory.mktemp("own")
    return out, _sweep(out)


def test_a_sweep_file_preset_runs_its_overlay_and_its_claim_reads_the_judge(own):
    out, rows = own
    by = {(r["preset"], r["seed"]): r for r in rows}
    assert sorted(by) == [("gd", 0), ("gd", 1), ("gd-mine", 0), ("gd-mine", 1)]
    for seed in (0, 1):  # SJC written anew: the built-in path's result, bit for bit, under another run id
        a, b = by[("gd-mine", seed)], by[("gd", seed)]
        assert a["gt_psnr"] == b["gt_psnr"] and a["gaussians"] == b["gaussians"] and a["run_id"] != b["run_id"]
    cell = out / "cells" / "janus" / "a_yellow_duck" / "gd-mine" / "seed0" / "run.json"
    assert yaml.safe_load(cell.read_text())["config"]["guidance"] == f"{EXAMPLE}:sjc_again"
    verdicts = _read(out / "verdict.csv")
    mine = [v for v in verdicts if v.get("family") == "sweep"]
    assert len(mine) == 1 and mine[0]["metric"] == "judge_janus" and mine[0]["a"] == "gd-mine"
    assert "read from the shipped judge" in (out / "summary.md").read_text()


def test_given_labels_the_same_sweep_reads_them_without_training_again(own, tmp_path):
    out, rows = own
    files = []
    for rater in ("a", "b"):  # both passes call gd's results Janus and the overlay's fine
        path = tmp_path / f"{rater}.csv"
        with open(path, "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["run_id", "label"])
            for r in rows:
                w.writerow([r["run_id"], "fine" if r["preset"] == "gd-mine" else "front_everywhere"])
        files.append(str(path))
    before = {p: p.stat().st_mtime_ns for p in out.rglob("scene.ply")}
    again = _sweep(out, labels=files)
    assert {p: p.stat().st_mtime_ns for p in out.rglob("scene.ply")} == before  # nothing trained again
    assert all(r["label_janus"] == (0.0 if r["preset"] == "gd-mine" else 1.0) for r in again if "label_janus" in r)
    mine = [v for v in _read(out / "verdict.csv") if v.get("family") == "sweep"]
    assert mine[0]["metric"] == "label_janus" and float(mine[0]["mean_a"]) == 0 and float(mine[0]["mean_b"]) == 1
    assert "read from rater labels (2 file(s)" in (out / "summary.md").read_text()


@pytest.mark.parametrize(
    "defined, claims, message",
    [
        ({"gd": {"base": "gd"}}, [], "define_presets: gd: expected a new name"),
        ({"gd-x": {"base": "nope"}}, [], "define_presets: gd-x: expected {base: one of"),
        ({"gd-x": {"base": "gd", "overrides": {"guidance": "nope"}}}, [], r"gd-x: guidance \(--guidance\)"),
        (MINE, [CLAIM | {"b": "sjc-gs"}], "must be two different presets of the sweep"),
        (MINE, [CLAIM | {"metric": "psnr"}], "metric: expected one of"),
        (MINE, [{"text": "t", "a": "gd"}], r"claims\[0\]: expected text, a, b, metric"),
    ],
)
def test_a_bad_preset_or_claim_is_refused_before_any_cell(tmp_path, defined, claims, message):
    cfg = SweepConfig([PROMPT], ["gd", "gd-mine"], [0], steps=4, out=tmp_path / "s", colmap=False,
                      overrides=TINY_CELL, progress=False, defined_presets=defined, claims=claims)  # fmt: skip
    with pytest.raises(ValueError, match=message):
        sweep(cfg)
    assert not (tmp_path / "s" / "cells").exists()


def test_the_sweep_file_carries_presets_and_claims_and_reads_back(tmp_path):
    from gdbench.app.cmd_sweep import sweep_from_mapping, sweep_mapping

    d = {"prompts": [PROMPT], "presets": ["gd", "gd-mine"], "define_presets": MINE, "claims": [CLAIM],
         "labels": ["a.csv"]}  # fmt: skip
    cmd = sweep_from_mapping(d)
    assert cmd.define_presets == MINE and cmd.claims == (CLAIM,) and cmd.labels == (Path("a.csv"),)
    back = sweep_mapping(cmd)
    assert back["define_presets"] == MINE and back["claims"] == [CLAIM]
    assert sweep_from_mapping(yaml.safe_load(yaml.safe_dump(back))).define_presets == MINE
    with pytest.raises(ValueError, match="define_presets: expected a mapping"):
        sweep_from_mapping({"define_presets": ["gd"]})


def test_a_cell_of_the_sweeps_own_preset_reproduces_from_its_run_json(own, tmp_path, monkeypatch, capsys):
    """The documented way to re-run a cell: `gdbench generate --config <cell>/run.json` gives the
    same run id and the same scene, bit for bit, though the preset is the sweep's own."""
    import json

    from tests._util import cli

    out, _ = own
    cell = out / "cells" / "janus" / "a_yellow_duck" / "gd-mine" / "seed1" / "run.json"
    code, _, err = cli(monkeypatch, capsys, "generate", "--config", str(cell), "--out", str(tmp_path / "again"))
    assert code == 0, err
    a, b = json.loads(cell.read_text()), json.loads((tmp_path / "again" / "run.json").read_text())
    assert a["run_id"] == b["run_id"] and a["scene_sha256"] == b["scene_sha256"] and b["preset"] == "gd-mine"
    partial = tmp_path / "partial.json"
    partial.write_text(json.dumps({"preset": "gd-mine", "steps": 3}))
    code, _, err = cli(monkeypatch, capsys, "generate", "--config", str(partial), "--out", str(tmp_path / "p"))
    assert code != 0 and "preset: unknown 'gd-mine'" in err and "known to its sweep" in err


def test_the_documented_sweep_file_is_a_valid_grid():
    """docs/training.md's example sweep file reads, and its grid (presets, claim) is accepted."""
    import re

    from gdbench.app.cmd_sweep import sweep_from_mapping
    from gdbench.experiments.sweep import grid

    doc = (Path(__file__).resolve().parents[1] / "docs" / "training.md").read_text()
    block = re.search(r"```yaml\n(# sweep.yaml.*?)```", doc, re.S).group(1)
    cmd = sweep_from_mapping(yaml.safe_load(block))
    cfg = SweepConfig(list(cmd.prompts), list(cmd.presets), list(cmd.seeds), settings=list(cmd.settings),
                      defined_presets=cmd.define_presets, claims=list(cmd.claims))  # fmt: skip
    specs, families, defined = grid(cfg)
    assert len(specs) == 3 * 2 * 6 and set(defined) == {"gd-smooth"} and len(families["sweep"]) == 1


def test_the_ablation_notebook_draws_the_sweeps_own_presets_and_claim(own, monkeypatch, tmp_path):
    """The notebook takes a sweep's own preset and claim like the built-in ones: its figure of the
    cells and a forest row for the claim (drawn, or named where it has no interval)."""
    import json
    import re

    from tests.test_notebooks import _execute

    out, _ = own
    text = _execute("ablation", out, tmp_path, monkeypatch)
    check = json.loads(re.search(r"^FOREST_CHECK (.*)$", text, re.M).group(1))
    assert check["sweep"] == str(out) and check["forest"]["rows"] == 1
    assert check["errorbars"] >= 1 or "gd-mine vs gd" in " ".join(check["forest"]["without_interval"])


def test_a_sweep_preset_that_picks_the_learned_prior_gets_its_janus_setting(tmp_path):
    """The janus setting's front bias follows the prior a sweep's own preset sets (2 on the learned
    prior, which ships no kappa-1 model), as it follows the sweep's overrides."""
    from gdbench.experiments.sweep import cell_config, grid

    defined = {"gd-learned": {"base": "gd", "overrides": {"prior": "learned"}}}
    cfg = SweepConfig([PROMPT], ["gd-learned"], [0], out=tmp_path, settings=["janus"], defined_presets=defined)
    (spec,), _, _ = grid(cfg)
    c = cell_config(spec)
    assert c.prior.kind == "learned" and c.prior.front_bias == 2.0 and c.prior.view_prompting == "none"


def test_labels_that_name_no_cell_are_refused(own, tmp_path):
    out, _ = own
    other = tmp_path / "other.csv"
    other.write_text("run_id,label\nnot-a-cell,fine\n")
    with pytest.raises(ValueError, match="labels: none of the cells' run ids is labelled"):
        _sweep(out, labels=[str(other)])
