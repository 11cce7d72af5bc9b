"""Run folders and the command line under bad input and faults (docs/reliability.md): nothing is
lost, mixed or silently changed, and every error is one line with exit code 2 naming what to fix."""

import errno
import json
import os
import signal
import sys

import pytest
import torch

from gdbench.io import FolderBusy, FolderLock
from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.densify import PARAM_NAMES
from gdbench.train.run import RunInterrupted, train
from tests._util import tiny_bank
from tests.test_train import CAPTION, tiny


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})


def cli(monkeypatch, capsys, *argv):
    """Run ``gdbench *argv`` in-process; returns (exit code, stdout, stderr)."""
    from gdbench.cli import entrypoint

    monkeypatch.setattr(sys, "argv", ["gdbench", *map(str, argv)])
    monkeypatch.delenv("GDBENCH_DEBUG", raising=False)
    code = 0
    try:
        entrypoint()
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def one_line(err: str) -> str:
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


# ------------------------------------------------------------------ 1. run folders
def test_a_second_writer_is_refused_with_the_holder(prior, tmp_path):
    with FolderLock(tmp_path / "run"):
        with pytest.raises(
            FolderBusy, match=rf"out: {tmp_path / 'run'} is in use by another gdbench run \(pid {os.getpid()}"
        ):
            train(tiny("gd", tmp_path / "run", steps=2), prior)
    # the lock file stays behind, but its lock went with the holder: the next run proceeds
    assert (tmp_path / "run" / FolderLock.NAME).is_file()
    assert train(tiny("gd", tmp_path / "run", steps=2), prior).state.step == 2


def test_a_second_process_is_refused_while_a_run_holds_the_folder(prior, tmp_path):
    import subprocess
    import time

    code = (
        "from gdbench.io import FolderLock; import time\n"
        f"with FolderLock({str(tmp_path / 'run')!r}):\n    print('held', flush=True); time.sleep(30)"
    )
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == "held"
        with pytest.raises(FolderBusy, match=f"pid {proc.pid}"):
            train(tiny("gd", tmp_path / "run", steps=2), prior)
    finally:
        proc.kill()
        proc.wait()
    time.sleep(0.1)
    assert train(tiny("gd", tmp_path / "run", steps=2), prior).state.step == 2  # killed holder: lock gone


def test_a_finished_run_is_never_overwritten_without_the_flag(prior, tmp_path):
    out = tmp_path / "run"
    train(tiny("gd", out, steps=2), prior)
    (out / "scores.json").write_text(json.dumps({"scene_sha256": "old", "gt": {"psnr": 30.0}}))
    (out / "checkpoint.pt").unlink()
    with pytest.raises(FileExistsError, match=r"holds a finished run of 'a test blob' \(preset gd, seed 0"):
        train(tiny("gd", out, steps=2, seed=1), prior)
    with pytest.raises(FileExistsError, match="pass --overwrite"):
        train(tiny("gd", out, steps=2), prior)  # same config, but nothing to resume from
    r = train(tiny("gd", out, steps=2, seed=1), prior, overwrite=True)
    assert not (out / "scores.json").exists()  # the old run's outputs went first
    run = json.loads((out / "run.json").read_text())
    assert run["seed"] == 1 and run["run_id"] and r.state.step == 2
    from gdbench.io import sha256_file

    assert run["scene_sha256"] == sha256_file(out / "scene.ply")
    assert f"comment gdbench run {run['run_id']}".encode() in (out / "scene.ply").read_bytes()[:300]


def test_scores_belong_to_the_scene_they_measured(prior, tmp_path, monkeypatch):
    from gdbench.io import sha256_file
    from gdbench.metrics import run_scores

    out = tmp_path / "run"
    train(tiny("gd", out, steps=2), prior)
    from gdbench.provenance import code_commit

    sha = sha256_file(out / "scene.ply")
    made = {"params": {"views": 100, "size": 256, "background": [1.0, 1.0, 1.0]}, "commit": code_commit()}
    colmap = {"registration_rate": 1.0, "var_theta_deg2": 0.1, "made": made}
    (out / "scores.json").write_text(json.dumps({"scene_sha256": sha, "colmap": colmap}))
    s = run_scores.score_run(out, gt=False, colmap=False)
    assert s["colmap"] == colmap and s["kept"] == ["colmap"]  # same scene, same code: kept
    (out / "scores.json").write_text(json.dumps({"scene_sha256": "another scene", "colmap": colmap}))
    s = run_scores.score_run(out, gt=False, colmap=False)
    assert "colmap" not in s and s["scene_sha256"] == sha  # another scene's block: dropped
    assert "colmap" not in json.loads((out / "scores.json").read_text())


@pytest.mark.parametrize("name", ["scores.json", "run.json"])
def test_a_broken_json_is_named_before_any_scoring(prior, tmp_path, monkeypatch, name):
    from gdbench.metrics import gt

    out = tmp_path / "run"
    train(tiny("gd", out, steps=2), prior)
    (out / name).write_text('{"gt": {"psnr": 21.0,')
    monkeypatch.setattr(gt, "score_against_asset", lambda *a, **k: pytest.fail("scored before checking"))
    from gdbench.metrics.run_scores import score_run

    with pytest.raises(ValueError, match=rf"{name}: {out / name} is not valid JSON"):
        score_run(out, colmap=False)


def test_ctrl_c_saves_a_checkpoint_and_resumes_exactly(prior, tmp_path, monkeypatch):
    from gdbench.train import run as run_mod

    real = run_mod.train_step

    def step(state, ctx, **kw):
        if state.step == 3:
            os.kill(os.getpid(), signal.SIGINT)  # lands mid-step
        return real(state, ctx, **kw)

    monkeypatch.setattr(run_mod, "train_step", step)
    with pytest.raises(RunInterrupted, match=r"interrupted at step 4 of 9; checkpoint saved"):
        train(tiny("gd", tmp_path / "a", steps=9, checkpoint_every=100), prior, write_outputs=False)
    monkeypatch.setattr(run_mod, "train_step", real)
    resumed = train(tiny("gd", tmp_path / "a", steps=9, checkpoint_every=100), prior, write_outputs=False)
    assert resumed.resumed_from == 4
    full = train(tiny("gd", tmp_path / "b", steps=9), prior, write_outputs=False)
    for k in PARAM_NAMES:
        assert torch.equal(full.state.params[k], resumed.state.params[k]), k


def test_a_full_disk_mid_checkpoint_keeps_the_last_one(prior, tmp_path, monkeypatch):
    out = tmp_path / "run"
    train(tiny("gd", out, steps=4), prior, stop_at=2, write_outputs=False)
    before = (out / "checkpoint.pt").read_bytes()

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(OSError, match="No space left"):
        train(tiny("gd", out, steps=4), prior, write_outputs=False)
    assert (out / "checkpoint.pt").read_bytes() == before
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]  # no temporary file left


def test_files_get_the_users_umask(prior, tmp_path):
    old = os.umask(0o022)
    try:
        train(tiny("gd", tmp_path / "run", steps=2), prior)
    finally:
        os.umask(old)
    for name in ("scene.ply", "checkpoint.pt", "run.json"):
        assert (tmp_path / "run" / name).stat().st_mode & 0o777 == 0o644, name


def test_an_unwritable_bank_cache_costs_the_cache_not_the_run(tmp_path, monkeypatch):
    from renderers.pyrender_points._lib import available

    if not available()[0]:
        pytest.skip("pyrender unavailable")
    from gdbench.assets.bank import BankConfig, load_bank

    monkeypatch.setenv("GDBENCH_CACHE", "/sys/gdbench-cache")  # a read-only file system
    with pytest.warns(UserWarning, match="GDBENCH_CACHE: cannot write the bank cache"):
        bank = load_bank("a sofa", BankConfig(resolution=16, azimuths=2, elevations=(0.0,)), verbose=False)
    assert bank.images.shape == (2, 16, 16, 3) and float(bank.alpha.mean()) > 0.05


# ------------------------------------------------------------------ 3. one line, exit code 2
@pytest.mark.parametrize(
    ("args", "match"),
    [
        (("generate", "a yellow duck", "--out", "/sys/gdbench-out", "--steps", "1"), r"/sys/gdbench-out"),
        (("generate", "a yellow duck", "--out", "FILE", "--steps", "1"), r"out: .*FILE is a file; expected a folder"),
        (("generate", "a yellow duck", "--resolution", "100000"), r"resolution: 100000 needs about \d+"),
        (("generate", "a blue duck", "--steps", "1"), r"prompt: 'a blue duck' matched 'a yellow duck'.*asks for blue"),
        (("generate", "not a duck", "--steps", "1"), r"prompt: 'not a duck' matched .*negates"),
        (("score", "MISSING"), r"run: expected a run folder, got .*MISSING"),
        (("render", "MISSING"), r"run: no PLY at .*MISSING"),
        (("render", "PLY", "--size", "40000"), r"size: 40000 needs about \d+"),
        (
            ("compare", "--scene", "isotropic", "--out", "/sys/gdbench-compare", "--backends", "splat"),
            "/sys/gdbench-compare",
        ),
        (("noise", "--preview", "--out", "x.jpg"), r"out: expected a .png file or a folder"),
        (("sweep", "--prompts", "a yellow duck", "a spaceship", "--presets", "gd", "--no-colmap"), "a spaceship"),
        (("sweep", "--prompts", "a yellow duck", "A yellow duck!", "--presets", "gd"), "share the cell folder"),
    ],
)
def test_bad_input_is_one_line_with_exit_code_2(monkeypatch, capsys, tmp_path, args, match):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "FILE").write_text("not a folder")
    from gdbench.builtin import demo_scene

    demo_scene(20).save_ply(tmp_path / "PLY")
    code, _, err = cli(monkeypatch, capsys, *args)
    line = one_line(err)
    assert code == 2 and line.startswith(f"gdbench {args[0]}: error: "), err
    import re

    assert re.search(match, line), line
    assert not (tmp_path / "runs").exists() or args[0] == "generate"  # nothing trained for a bad grid


def test_broken_checkpoints_are_one_line_errors(monkeypatch, capsys, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    for content in (b"", b"\x00" * 64):
        (out / "checkpoint.pt").write_bytes(content)
        code, _, err = cli(monkeypatch, capsys, "generate", "a yellow duck", "--out", out, "--steps", "1")
        assert code == 2 and "checkpoint.pt is unreadable" in one_line(err)


def test_noise_preview_into_a_folder(monkeypatch, capsys, tmp_path):
    (tmp_path / "dir").mkdir()
    for target, want in ((tmp_path / "dir", tmp_path / "dir" / "noise_preview.png"),
                         (tmp_path / "new", tmp_path / "new" / "noise_preview.png")):  # fmt: skip
        code, out, _ = cli(
            monkeypatch, capsys, "noise", "--preview", "--out", target, "--res", "24", "--n-gaussians", "100"
        )
        assert code == 0 and want.is_file() and str(want) in out


def test_generate_prints_the_matched_caption(prior, monkeypatch, capsys, tmp_path):
    from gdbench.cli import Generate, main
    from gdbench.train import run as run_mod

    real = run_mod.make_context
    monkeypatch.setattr(run_mod, "make_context", lambda cfg, p=None: real(cfg, prior))
    from gdbench.cli import GenerateTrain

    s = main(
        Generate(CAPTION, out=tmp_path / "r", score=False, progress=False, train=GenerateTrain(steps=2, resolution=16))
    )
    assert s["caption"] == CAPTION and s["caption_similarity"] == 1.0
    assert f"prompt {CAPTION!r} -> asset {CAPTION!r} (cosine 1.00)" in capsys.readouterr().out
    assert json.loads((tmp_path / "r" / "run.json").read_text())["caption_similarity"] == 1.0


def test_sweep_cell_names_stay_inside_out():
    from gdbench.sweep import CellSpec, cell_name

    assert cell_name("../../a yellow duck") == "a_yellow_duck"
    spec = CellSpec("../../a yellow duck", "gd", 0, 10, "/tmp/sweep")
    assert spec.dir.resolve().is_relative_to("/tmp/sweep")


# ------------------------------------------------------------------ 5. the C++ compositor's cache
def test_compositor_loads_the_built_library_directly_and_ignores_stale_locks(tmp_path, monkeypatch):
    import shutil

    from renderers.splat import _ext

    if _ext.load_extension() is None:
        pytest.skip(f"C++ compositor unavailable: {_ext.extension_status()}")
    built = _ext.build_dir() / f"{_ext.module_name()}.so"
    # another cache holding the same library, plus a stale lock of a killed build and a stale
    # torch build folder: the loader imports the file and never builds or waits
    monkeypatch.setenv("GDBENCH_CACHE", str(tmp_path))
    target = _ext.build_dir() / built.name
    target.parent.mkdir(parents=True)
    shutil.copy(built, target)
    (target.parent / ".build-stale").mkdir()
    (target.parent / ".build-stale" / "lock").write_text("")
    monkeypatch.setattr(_ext, "_STATE", {})
    monkeypatch.setattr(_ext, "_build", lambda *a: pytest.fail("rebuilt although the library exists"))
    mod = _ext.load_extension()
    assert mod is not None and _ext.extension_status() == "loaded"
    assert os.path.samefile(mod.__spec__.origin, target)


def test_every_listed_mutation_applies_to_the_current_code():
    """`make mutants` applies each mutation to a copy; a snippet the code no longer holds (or
    holds twice) would make the mutant meaningless, so the list must follow the code."""
    import importlib.util
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    spec = importlib.util.spec_from_file_location("gdbench_mutants", root / "scripts" / "mutants.py")
    mutants = importlib.util.module_from_spec(spec)
    sys.modules.setdefault("gdbench_mutants", mutants)  # dataclasses look their module up there
    spec.loader.exec_module(mutants)
    assert len(mutants.MUTATIONS) >= 16
    for m in mutants.MUTATIONS:
        text = (root / m.file).read_text()
        assert text.count(m.old) == 1, f"{m.name}: snippet found {text.count(m.old)} times in {m.file}"
        assert m.new != m.old
