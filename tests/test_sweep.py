"""Scores and sweeps (gdbench/metrics/run_scores.py, gdbench/experiments/sweep.py): ``gdbench score`` on a
run folder, the sweep's tables against its own cells, resumability, and the Ray executor
against the local one (same seed, same cell)."""

import json
import math
import shutil
import statistics

import pytest

from gdbench.app.cli import main
from gdbench.app.cmd_scenes import Score
from gdbench.app.cmd_sweep import Sweep
from gdbench.experiments.sweep import CellSpec, SweepConfig, cell_config, run_cell, sweep
from gdbench.metrics.run_scores import score_run
from gdbench.train.run import train
from tests._util import TINY_CELL, csv_rows, strict_json

PROMPT = "a yellow duck"
TINY = TINY_CELL


@pytest.fixture(scope="module")
def tiny_sweep(tmp_path_factory):
    out = tmp_path_factory.mktemp("sweep")
    rows = sweep(
        SweepConfig([PROMPT], ["gd", "sjc-gs"], [0, 1], steps=4, out=out, colmap=False, overrides=TINY, progress=False)
    )
    return out, rows


def test_sweep_writes_every_cell_and_tables_that_summarise_them(tiny_sweep):
    out, rows = tiny_sweep
    assert [(r["preset"], r["seed"]) for r in rows] == [("gd", 0), ("sjc-gs", 0), ("gd", 1), ("sjc-gs", 1)]
    cells = csv_rows(out / "cells.csv")
    assert len(cells) == 4
    for r in rows:
        run = json.loads((CellSpec(PROMPT, r["preset"], r["seed"], 4, str(out)).dir / "run.json").read_text())
        assert (run["preset"], run["seed"], run["steps"]) == (r["preset"], r["seed"], 4)
        assert r["iterations"] == 4 and 5.0 < r["gt_psnr"] < 40.0 and math.isnan(r["var_theta_deg2"])
        # the row's training time is the run's own record of its steps
        assert r["train_time_s"] == pytest.approx(run["timings"]["train_steps_s"])
        scores = json.loads((CellSpec(PROMPT, r["preset"], r["seed"], 4, str(out)).dir / "scores.json").read_text())
        assert r["gt_offset_deg"] == scores["gt"]["offset_deg"] and r["run_id"] == run["run_id"]
        assert r["gt_psnr_unaligned"] == scores["gt"]["psnr_unaligned"] <= r["gt_psnr"]
    # the summary is the mean over seeds of the per-cell values, recomputed here from cells.csv
    summary = {s["preset"]: s for s in csv_rows(out / "summary.csv")}
    for p in ("gd", "sjc-gs"):
        ps = [float(c["gt_psnr"]) for c in cells if c["preset"] == p]
        assert float(summary[p]["gt_psnr_mean"]) == pytest.approx(statistics.mean(ps), rel=1e-9)
        assert float(summary[p]["gt_psnr_std"]) == pytest.approx(statistics.stdev(ps), rel=1e-9)
        assert int(summary[p]["gt_psnr_n"]) == 2 and summary[p]["var_theta_deg2_mean"] == ""  # not measured
    md = (out / "summary.md").read_text()
    assert md.count("\n| easy | gd |") == 1 and md.count("\n| easy | sjc-gs |") == 1


def test_figures_are_drawn_on_request_and_a_finished_sweep_draws_them_without_training(tmp_path, monkeypatch):
    """A sweep writes what its tables need (no turntable, curves or ablation.png), and records where
    its time went (timings.json: the phases add up to at most the sweep's time; cell.json: the
    run's steps as the row reports them). Run again with figures it draws them from the finished
    cells: no training step runs (oracle: a step that raises), the rows are the same and run.json
    keeps the provenance and timings of the call that trained the scene."""
    import gdbench.train.run as run_mod

    args = ([PROMPT], ["gd"], [0])
    kw = dict(steps=4, out=tmp_path, colmap=False, overrides=TINY, progress=False)
    rows = sweep(SweepConfig(*args, **kw))
    cell = CellSpec(PROMPT, "gd", 0, 4, str(tmp_path), colmap=False, overrides=TINY).dir
    assert (cell / "scene.ply").is_file() and (tmp_path / "verdict.csv").is_file()
    for name in ("turntable.gif", "turntable.mp4", "turntable_sheet.png", "curves.png"):
        assert not (cell / name).exists(), name
    assert not (tmp_path / "ablation.png").exists()
    t = json.loads((tmp_path / "timings.json").read_text())
    assert t["ran"] == 1 and t["validate_s"] + t["cells_s"] + t["tables_s"] <= t["sweep_s"]
    c = json.loads((cell / "cell.json").read_text())["timings"]
    assert c["steps_s"] == rows[0]["train_time_s"] and c["score_s"] + c["train_call_s"] <= c["cell_s"]

    def no_step(*a, **k):
        raise AssertionError("a finished cell trained again")

    monkeypatch.setattr(run_mod, "train_step", no_step)
    before = json.loads((cell / "run.json").read_text())
    again = sweep(SweepConfig(*args, **kw, figures=True))
    after = json.loads((cell / "run.json").read_text())  # the provenance of the call that trained it stands
    assert {k: after[k] for k in run_mod.PROVENANCE} == {k: before[k] for k in run_mod.PROVENANCE}
    for name in ("turntable.gif", "turntable.mp4", "turntable_sheet.png", "curves.png"):
        assert (cell / name).is_file(), name
    assert (tmp_path / "ablation.png").is_file()
    assert [r["gt_psnr"] for r in again] == [r["gt_psnr"] for r in rows]


def test_seeds_give_different_cells_and_the_same_seed_the_same_cell(tiny_sweep, tmp_path):
    _, rows = tiny_sweep
    by = {(r["preset"], r["seed"]): r for r in rows}
    assert by["gd", 0]["gt_psnr"] != by["gd", 1]["gt_psnr"]
    again = run_cell(CellSpec(PROMPT, "gd", 0, 4, str(tmp_path), colmap=False, overrides=TINY))
    assert again["gt_psnr"] == by["gd", 0]["gt_psnr"]  # same seed on CPU: bit-identical


def test_a_finished_sweep_skips_all_cells_and_an_interrupted_one_continues(tiny_sweep, monkeypatch):
    out, rows = tiny_sweep
    import gdbench.experiments.sweep as sw

    def boom(spec, **kw):
        raise AssertionError(f"cell {spec} should have been skipped")

    monkeypatch.setattr(sw, "run_cell", boom)
    again = sweep(
        SweepConfig([PROMPT], ["gd", "sjc-gs"], [0, 1], steps=4, out=out, colmap=False, overrides=TINY, progress=False)
    )
    assert json.dumps(again) == json.dumps(rows)  # (NaN-safe equality)
    monkeypatch.undo()

    # a cell killed mid-training: only that cell runs again, from its checkpoint, to the same result
    spec = CellSpec(PROMPT, "sjc-gs", 1, 4, str(out), colmap=False, overrides=TINY)
    shutil.rmtree(spec.dir)
    train(cell_config(spec), stop_at=2)
    ran = []
    monkeypatch.setattr(sw, "run_cell", lambda s, **kw: ran.append(s) or run_cell(s, **kw))
    resumed = sweep(
        SweepConfig([PROMPT], ["gd", "sjc-gs"], [0, 1], steps=4, out=out, colmap=False, overrides=TINY, progress=False)
    )
    assert ran == [spec]
    assert json.loads((spec.dir / "run.json").read_text())["resumed_from_step"] == 2
    assert resumed[3]["gt_psnr"] == rows[3]["gt_psnr"]


def test_changing_a_cell_setting_runs_it_again_instead_of_reusing_it(tiny_sweep, monkeypatch):
    out, _ = tiny_sweep
    import gdbench.experiments.sweep as sw

    ran = []
    monkeypatch.setattr(sw, "run_cell", lambda s, **kw: ran.append(s) or {"preset": s.preset})
    monkeypatch.setattr("gdbench.experiments.tables.tables", lambda rows, out, *a, **k: {})
    sweep(SweepConfig([PROMPT], ["gd"], [0], steps=6, out=out, colmap=False, overrides=TINY, progress=False))
    assert [s.steps for s in ran] == [6]


def test_a_running_sweep_writes_its_tables_on_a_clock_and_once_at_the_end(tmp_path, monkeypatch):
    """The tables are rewritten while cells finish only every TABLES_EVERY_S seconds (at 1000 cells
    each rewrite cost 5 s), always at the end, from every cell: the same files either way."""
    from gdbench.experiments import sweep as sweep_module
    from gdbench.experiments import tables as sweep_tables

    calls = []
    real = sweep_tables.tables
    monkeypatch.setattr(
        sweep_tables, "tables", lambda rows, out, *a, **k: calls.append(len(rows)) or real(rows, out, *a, **k)
    )
    kw = dict(steps=4, colmap=False, overrides=TINY, progress=False)
    rows = sweep(SweepConfig([PROMPT], ["gd"], [0, 1, 2], out=tmp_path / "a", **kw))
    assert calls == [3]  # the default clock: one write, at the end, with every cell
    monkeypatch.setattr(sweep_module, "TABLES_EVERY_S", 0.0)
    calls.clear()
    sweep(SweepConfig([PROMPT], ["gd"], [0, 1, 2], out=tmp_path / "b", **kw))
    assert calls == [1, 2, 3, 3]  # after each cell, then the end
    untimed = lambda path: [{k: v for k, v in r.items() if not k.endswith("_s")} for r in csv_rows(path)]  # noqa: E731
    assert untimed(tmp_path / "a" / "cells.csv") == untimed(tmp_path / "b" / "cells.csv") and len(rows) == 3


def test_sweep_rejects_bad_arguments(tmp_path):
    with pytest.raises(ValueError, match="presets: unknown"):
        sweep(SweepConfig([PROMPT], ["gd", "best"], [0], out=tmp_path))
    with pytest.raises(ValueError, match="prompts, presets, seeds"):
        sweep(SweepConfig([], ["gd"], [0], out=tmp_path))
    with pytest.raises(ValueError, match=r"seeds: \[1\] listed more than once"):
        sweep(SweepConfig([PROMPT], ["gd"], [0, 1, 1], out=tmp_path))
    with pytest.raises(ValueError, match="executor"):
        sweep(SweepConfig([PROMPT], ["gd"], [0], out=tmp_path, executor="slurm", steps=1, colmap=False, progress=False))


def test_local_workers_run_cells_on_their_share_of_the_cores(tiny_sweep, tmp_path):
    """--workers 2: cells run in fresh worker processes on cpu_count // 2 threads each (the row
    records it), with the one-worker sweep's results (same seed; up to the reduction order of
    another thread count)."""
    import os

    _, rows = tiny_sweep
    got = sweep(SweepConfig([PROMPT], ["gd", "sjc-gs"], [1], steps=4, out=tmp_path, colmap=False, overrides=TINY,
                progress=False, workers=2))  # fmt: skip
    assert [r["threads"] for r in got] == [max(1, (os.cpu_count() or 1) // 2)] * 2
    for r in got:
        local = next(x for x in rows if (x["preset"], x["seed"]) == (r["preset"], 1))
        assert r["gt_psnr"] == pytest.approx(local["gt_psnr"], abs=1e-3) and r["gaussians"] == local["gaussians"]


def test_groups_cross_the_grid_and_claims_pair_within_a_group(tiny_sweep, tmp_path, monkeypatch):
    """groups: each named set of overrides runs every cell in its own folder with its overrides
    (the views per step reach run.json and the row); a group whose overrides equal the plain
    sweep's gives its cells bit for bit; claims pair cells of one group only; the Janus failure
    rate is the featureless plus the multi-face rate (disjoint: featureless views never count a
    second face)."""
    from gdbench.experiments.claims import evaluate

    _, plain = tiny_sweep
    groups = {"v1": {}, "v2": {"views_per_step": 2, "views_spread_deg": 10.0}}
    rows = sweep(SweepConfig([PROMPT], ["gd", "gd-no-sn"], [0], steps=4, out=tmp_path, colmap=False, overrides=TINY,
                 progress=False, groups=groups))  # fmt: skip
    assert [(r["group"], r["preset"]) for r in rows] == [(g, p) for g in ("v1", "v2") for p in ("gd", "gd-no-sn")]
    for r in rows:
        spec = CellSpec(PROMPT, r["preset"], 0, 4, str(tmp_path), group=r["group"])
        assert spec.dir.parts[-5] == r["group"] and (spec.dir / "cell.json").is_file()
        run = json.loads((spec.dir / "run.json").read_text())
        assert run["config"]["views"]["per_step"] == r["views_per_step"] == (2 if r["group"] == "v2" else 1)
        assert r["janus_failure_rate"] == r["featureless_rate"] + r["multi_face_rate"]
    assert rows[0]["gt_psnr"] == next(p["gt_psnr"] for p in plain if (p["preset"], p["seed"]) == ("gd", 0))
    assert rows[2]["gt_psnr"] != rows[0]["gt_psnr"]  # two views per step: another run
    # the verdict pairs within a group: v1's gd against v1's sjc-gs, v2's against v2's
    verdicts = evaluate(rows)
    assert {v["group"] for v in verdicts} == {"v1", "v2"}
    faces = [v for v in verdicts if v["metric"] == "multi_face_rate"]  # (COLMAP's claims: not measured, 0 pairs)
    assert len(faces) == 2 and all(v["pairs"] == 1 for v in faces)
    assert "| v2 / easy | gd |" in (tmp_path / "summary.md").read_text()
    with pytest.raises(ValueError, match="groups: expected names"):
        sweep(SweepConfig([PROMPT], ["gd"], [0], out=tmp_path, groups={"../x": {}}, colmap=False, progress=False))
    with pytest.raises(ValueError, match="views-spread-deg acts only with --views-per-step 2 or more"):
        sweep(SweepConfig([PROMPT], ["gd"], [0], out=tmp_path, groups={"a": {"views_spread_deg": 5.0}}, colmap=False))


def test_ray_executor_gives_the_local_rows(tiny_sweep, tmp_path):
    ray = pytest.importorskip("ray")
    _, rows = tiny_sweep
    got = sweep(
        SweepConfig(
            [PROMPT], ["gd"], [1], steps=4, out=tmp_path, executor="ray", colmap=False, overrides=TINY, progress=False
        )
    )
    assert not ray.is_initialized()  # the sweep shut down the instance it started
    local = next(r for r in rows if (r["preset"], r["seed"]) == ("gd", 1))
    # a Ray worker may run with another thread count: same cell up to float reduction order
    assert got[0]["gt_psnr"] == pytest.approx(local["gt_psnr"], abs=1e-3)
    assert got[0]["gaussians"] == local["gaussians"] and got[0]["iterations"] == 4


def test_score_cli_writes_scores_next_to_the_run_and_keeps_earlier_ones(tiny_sweep, capsys):
    out, rows = tiny_sweep
    run = CellSpec(PROMPT, "gd", 0, 4, str(out)).dir
    before = json.loads((run / "scores.json").read_text())
    s = main(Score(run=run, gt=True, colmap=True, views=12, size=64))
    after = json.loads((run / "scores.json").read_text())
    # the PLY written by the run scores as the in-memory scene did
    assert after["gt"]["psnr"] == pytest.approx(rows[0]["gt_psnr"], abs=1e-4)
    assert 0.0 <= after["colmap"]["registration_rate"] <= 1.0 and after["colmap"]["views"] == 12
    assert set(before) <= set(after) and s["gaussians"] == rows[0]["gaussians"]
    assert "PSNR" in capsys.readouterr().out


def test_score_names_the_missing_scene(tmp_path):
    with pytest.raises(FileNotFoundError, match=r"run: no scene\.ply"):
        score_run(tmp_path)
    with pytest.raises(FileNotFoundError, match="run: expected a run folder"):
        main(Score(run=tmp_path / "nope"))


def test_sweep_cli_prints_the_table(tmp_path, capsys):
    res = main(Sweep(prompts=(PROMPT,), presets=("sjc-gs",), seeds=(0,), steps=2, out=tmp_path, colmap=False))
    assert res["cells"] == 1 and (tmp_path / "cells.csv").is_file()
    assert "| easy | sjc-gs | 1 |" in capsys.readouterr().out


def test_command_line_errors_are_one_line_with_exit_code_2(monkeypatch, capsys):
    from gdbench.app.cli import entrypoint

    monkeypatch.delenv("GDBENCH_DEBUG", raising=False)
    monkeypatch.setattr("sys.argv", ["gdbench", "sweep", "--presets", "gd", "nope"])
    with pytest.raises(SystemExit) as e:
        entrypoint()
    err = capsys.readouterr().err
    assert e.value.code == 2 and err.startswith("gdbench sweep: error: presets: unknown ['nope']")
    assert "Traceback" not in err
    monkeypatch.setenv("GDBENCH_DEBUG", "1")
    with pytest.raises(ValueError, match="presets: unknown"):
        entrypoint()


def test_sweep_cli_overrides_method_options_for_every_cell(tmp_path, capsys):
    from gdbench.app.cmd_sweep import SweepTrain

    train = SweepTrain(view_prompting="none", views_per_step=2, noise_redraw="ou", noise_ratio="variance")
    res = main(
        Sweep(
            prompts=(PROMPT,),
            presets=("gd",),
            seeds=(0,),
            steps=2,
            out=tmp_path,
            colmap=False,
            train=train,
        )
    )
    cell = tmp_path / "cells" / "easy" / "a_yellow_duck" / "gd" / "seed0"
    assert res["cells"] == 1 and json.loads((cell / "cell.json").read_text())["spec"]["overrides"] == {
        "view_prompting": "none",
        "views.per_step": 2,
        "noise.redraw": "ou",
        "noise.ratio": "variance",
    }
    config = json.loads((cell / "run.json").read_text())["config"]
    assert config["prior"]["view_prompting"] == "none" and config["views"]["per_step"] == 2
    assert config["noise"]["redraw"] == "ou" and config["noise"]["ratio"] == "variance"
    assert "No claim is decidable here" in capsys.readouterr().out


def test_settings_dial_the_prior_and_pair_cells(tmp_path):
    """janus: no view prompting and a front-heavy bank; instance: three variants; every cell
    scored with the view metrics, and each claim about two presets that ran is in verdict.csv."""
    rows = sweep(
        SweepConfig(
            [PROMPT],
            ["gd", "gd-no-sn", "sjc-gs"],
            [0],
            steps=2,
            out=tmp_path,
            colmap=False,
            overrides=TINY,
            progress=False,
            settings=["easy", "janus", "instance"],
            setting_presets={"janus": ["gd", "gd-no-sn"], "instance": ["gd", "gd-no-sn"]},
        ),
    )
    assert [(r["setting"], r["preset"]) for r in rows] == [
        ("easy", "gd"), ("easy", "gd-no-sn"), ("easy", "sjc-gs"),
        ("janus", "gd"), ("janus", "gd-no-sn"), ("instance", "gd"), ("instance", "gd-no-sn"),
    ]  # fmt: skip
    cfg = json.loads((CellSpec(PROMPT, "gd", 0, 2, str(tmp_path), setting="janus").dir / "run.json").read_text())
    assert cfg["config"]["prior"]["view_prompting"] == "none" and cfg["config"]["prior"]["front_bias"] == 1.0
    cfg = json.loads((CellSpec(PROMPT, "gd", 0, 2, str(tmp_path), setting="instance").dir / "run.json").read_text())
    assert cfg["config"]["prior"]["variants"] == 3 and cfg["config"]["prior"]["view_prompting"] == "window"
    for r in rows:
        assert 0 <= r["multi_face_rate"] <= 1 and 0 <= r["instance_inconsistency"] <= 1 and 0 <= r["floaters"] <= 1
    verdicts = csv_rows(tmp_path / "verdict.csv")
    assert {(v["setting"], v["a"], v["b"]) for v in verdicts} >= {("janus", "gd", "gd-no-sn"), ("easy", "gd", "sjc-gs")}
    with pytest.raises(ValueError, match="settings: expected distinct names"):
        sweep(SweepConfig([PROMPT], ["gd"], [0], out=tmp_path, settings=["hard"]))


def test_sweep_notes_options_some_cells_ignore_and_refuses_those_all_ignore():
    from gdbench.experiments.sweep import CellSpec, inert_overrides

    def specs(presets, overrides, group=""):
        return [CellSpec(PROMPT, p, 0, 10, "/tmp/never", overrides=overrides, group=group) for p in presets]

    lines = inert_overrides(specs(["gd", "sjc-gs", "sds-gs"], {"vgs_gamma": 0.1}))
    assert lines == ["--vgs-gamma does nothing in sds-gs (easy), sjc-gs (easy): it acts only with --vgs "
                     "(this run: --no-vgs)"]  # fmt: skip
    with pytest.raises(ValueError, match=r"--vgs-gamma acts only with --vgs .*in every cell of the sweep"):
        inert_overrides(specs(["sjc-gs"], {"vgs_gamma": 0.1}))
    assert inert_overrides(specs(["gd"], {"vgs_gamma": 0.1})) == []
    # a group's option is judged in the cells given it, and the note names the group
    spread = {"views_per_step": 1, "views_spread_deg": 5.0}
    mixed = specs(["gd"], {"views_per_step": 4, "views_spread_deg": 5.0}, "v4") + specs(["gd"], spread, "v1")
    assert inert_overrides(mixed) == ["--views-spread-deg does nothing in gd (v1 / easy): it acts only with "
                                      "--views-per-step 2 or more (this run: --views-per-step 1)"]  # fmt: skip
    assert inert_overrides(specs(["gd"], {})) == []


# ------------------------------------------------------------ provenance and strict files
def _stub_colmap(monkeypatch, calls, registered=0):
    """COLMAP's scorer replaced by a stub that counts its calls (registering nothing by default:
    NaN variance, failure rate 1)."""
    from gdbench.metrics import colmap_consistency as cc

    def fake(scene, *, views, size, background, log=None, phase=None):
        calls.append((views, size))
        nan = float("nan")
        var = nan if registered < 3 else 0.5
        return cc.ColmapScore(views, registered, registered / views, var, nan, nan, 0, 0.01, 1.0)

    monkeypatch.setattr(cc, "score_scene", fake)


def test_a_stale_or_foreign_block_is_never_shown_as_current(tiny_sweep, monkeypatch, tmp_path, capsys):
    from gdbench.core.provenance import code_commit

    out, _ = tiny_sweep
    run = tmp_path / "run"
    shutil.copytree(CellSpec(PROMPT, "gd", 0, 4, str(out)).dir, run)
    calls = []
    _stub_colmap(monkeypatch, calls)
    s = score_run(run, colmap=True, views=9, size=48)
    # the sweep's own GT and judge blocks, same code: reused; COLMAP at parameters never scored: computed
    assert calls == [(9, 48)] and s["reused"] == ["gt", "views", "judge"]
    made = s["colmap"]["made"]
    assert made["params"] == {"views": 9, "size": 48, "background": [1.0, 1.0, 1.0]}
    assert made["commit"] == code_commit() and made["utc"].endswith("Z")
    # same parameters: reused, and said so; other parameters: computed again
    s = score_run(run, gt=False, colmap=True, views=9, size=48)
    assert calls == [(9, 48)] and s["reused"] == ["colmap"]
    from gdbench.metrics.run_scores import report

    assert "COLMAP: registered 0.00" in report(s) and "(reused: made" in report(s)
    s = score_run(run, gt=False, colmap=True, views=7, size=48)
    assert calls == [(9, 48), (7, 48)] and s["reused"] == [] and "reused" not in report(s)
    # GT blocks made under other parameters (here: another background) are computed again
    blob = strict_json(run / "scores.json")
    for name in ("gt", "views"):
        blob[name]["made"]["params"]["background"] = [0.0, 0.0, 0.0]
    (run / "scores.json").write_text(json.dumps(blob))
    s = score_run(run, colmap=False)
    assert s["reused"] == ["judge"] and s["gt"]["made"]["params"]["background"] == [1.0, 1.0, 1.0]
    assert s["gt"]["psnr"] == blob["gt"]["psnr"]  # the same scene and parameters: the same score
    # a block made by other code (or planted with made-up numbers) is dropped, never printed
    blob = strict_json(run / "scores.json")
    blob["colmap"] = {"registration_rate": 0.93, "var_theta_deg2": 1.5, "failure_rate": 0.1,
                      "translation_dir_err_deg": 2.0, "made": dict(made, commit="0123456789ab")}  # fmt: skip
    (run / "scores.json").write_text(json.dumps(blob))
    s = score_run(run, gt=False, colmap=False)
    assert "colmap" not in s and "colmap" not in strict_json(run / "scores.json")
    text = report(s)
    assert "0.93" not in text and "COLMAP" not in text and "GT:" not in text
    assert "nothing scored" in text and "also keeps, not recomputed now: gt, judge, views" in text
    del blob["colmap"]["made"]  # from before blocks recorded their provenance
    (run / "scores.json").write_text(json.dumps(blob))
    assert "colmap" not in score_run(run, gt=False, colmap=False)
    # --no-gt --no-colmap through the CLI prints no score at all
    main(Score(run=run, gt=False, colmap=False))
    printed = capsys.readouterr().out
    assert "PSNR" not in printed and "COLMAP:" not in printed and "nothing scored" in printed


def test_a_cell_holds_only_what_the_sweep_asked_for(tiny_sweep, monkeypatch, tmp_path):
    """A COLMAP block the cell's scores.json holds from an earlier pass stays out of a row whose
    cell is outside --colmap-presets; a cell inside gets strict files with null for the variance
    COLMAP could not measure."""
    out, rows = tiny_sweep
    src = CellSpec(PROMPT, "sjc-gs", 0, 4, str(out), colmap=False, overrides=TINY)
    spec = CellSpec(PROMPT, "sjc-gs", 0, 4, str(tmp_path), colmap=True, overrides=TINY, colmap_views=8)
    shutil.copytree(src.dir, spec.dir)
    calls = []
    _stub_colmap(monkeypatch, calls)
    row = run_cell(spec)
    assert calls == [(8, 256)] and row["colmap_failure_rate"] == 1.0 and math.isnan(row["var_theta_deg2"])
    for name in ("scores.json", "cell.json", "run.json"):
        strict_json(spec.dir / name)  # NaN written as null
    assert strict_json(spec.dir / "scores.json")["colmap"]["var_theta_deg2"] is None
    assert strict_json(spec.dir / "cell.json")["row"]["var_theta_deg2"] is None
    asked_less = CellSpec(PROMPT, "sjc-gs", 0, 4, str(tmp_path), colmap=False, overrides=TINY)
    row = run_cell(asked_less)
    assert "colmap" in strict_json(spec.dir / "scores.json")  # kept in the file (same scene and code) ...
    assert math.isnan(row["colmap_failure_rate"]) and math.isnan(row["registration_rate"])  # ... not in the row
    assert row["gt_psnr"] == rows[1]["gt_psnr"] and row["score_commit"] == row["train_commit"]
    assert "torch " in row["versions"] and "pycolmap " in row["versions"]  # the packages that made it
    from gdbench.experiments.tables import commits

    assert "MIXED" not in commits([row, row])
    assert "MIXED package versions" in commits([row, dict(row, versions="torch 0")])


def test_every_json_a_sweep_writes_is_strict_and_tables_are_numeric(tiny_sweep):
    out, _ = tiny_sweep
    files = sorted(out.rglob("*.json"))
    assert {f.name for f in files} >= {"run.json", "scores.json", "cell.json"}
    for f in files:
        strict_json(f)
    summary = csv_rows(out / "summary.csv")
    for row in summary:
        for key, value in row.items():
            if key.endswith(("_mean", "_std", "_median", "_n")):
                assert value == "" or math.isfinite(float(value)), (key, value)
    for row in csv_rows(out / "cells.csv") + csv_rows(out / "verdict.csv"):
        assert "nan" not in {v.lower() for v in row.values()} and "n/a" not in row.values()
