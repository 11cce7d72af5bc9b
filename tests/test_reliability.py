"""Run folders and the command line under bad input and faults (docs/reliability.md): nothing is
lost, mixed or silently changed, and every error is one line with exit code 2 naming what to fix."""

import errno
import json
import os
import signal
import sys

import pytest
import torch

from gdbench.core.io import FolderBusy, FolderLock
from gdbench.core.signals import RunInterrupted
from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.densify import PARAM_NAMES
from gdbench.train.run import train
from tests._util import CAPTION, PACED_RUN, cli, one_line, script, tiny, tiny_bank


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})


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
        "from gdbench.core.io import FolderLock; import time\n"
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
    (out / "scene_turntable.gif").write_bytes(b"the old scene's render")  # gdbench render's output
    r = train(tiny("gd", out, steps=2, seed=1), prior, overwrite=True)
    assert not (out / "scores.json").exists()  # the old run's outputs went first
    assert not (out / "scene_turntable.gif").exists()
    run = json.loads((out / "run.json").read_text())
    assert run["seed"] == 1 and run["run_id"] and r.state.step == 2
    from gdbench.core.io import sha256_file

    assert run["scene_sha256"] == sha256_file(out / "scene.ply")
    assert f"comment gdbench run {run['run_id']}".encode() in (out / "scene.ply").read_bytes()[:300]


def test_scores_belong_to_the_scene_they_measured(prior, tmp_path, monkeypatch):
    from gdbench.core.io import sha256_file
    from gdbench.metrics import run_scores

    out = tmp_path / "run"
    train(tiny("gd", out, steps=2), prior)
    from gdbench.core.provenance import code_commit

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


@pytest.mark.parametrize("sig", ["SIGINT", "SIGTERM", "SIGHUP"])
def test_a_stop_signal_saves_a_checkpoint_and_resumes_exactly(prior, tmp_path, monkeypatch, sig, request):
    """Ctrl-C, SIGTERM (timeout, kill, Slurm) and SIGHUP (a closed SSH session) landing mid-step:
    the step ends, a checkpoint is saved, RunInterrupted names the signal with exit code 128 + its
    number, and the same command resumes bit-identically."""
    from gdbench.app.cli import error_line
    from gdbench.train import run as run_mod

    signum = getattr(signal, sig)
    if signal.getsignal(signum) is signal.SIG_IGN:  # the suite run under nohup: test the handled case
        signal.signal(signum, signal.SIG_DFL)
        request.addfinalizer(lambda: signal.signal(signum, signal.SIG_IGN))
    real, before = run_mod.train_step, signal.getsignal(signum)

    def step(state, ctx, **kw):
        if state.step == 3:
            os.kill(os.getpid(), signum)  # lands mid-step
        return real(state, ctx, **kw)

    monkeypatch.setattr(run_mod, "train_step", step)
    with pytest.raises(RunInterrupted, match=rf"interrupted by {sig} at step 4 of 9; checkpoint saved") as e:
        train(tiny("gd", tmp_path / "a", steps=9, checkpoint_every=100), prior, write_outputs=False)
    assert error_line(e.value) == (str(e.value), 128 + signum)
    assert signal.getsignal(signum) == before  # the loop gives the handler back
    if sig == "SIGHUP":  # under nohup SIGHUP is ignored, and stays so: the run goes on
        from gdbench.core.signals import defer_stop_signals

        flag: list = []
        old = signal.signal(signal.SIGHUP, signal.SIG_IGN)
        try:
            with defer_stop_signals(flag):
                assert signal.getsignal(signal.SIGHUP) is signal.SIG_IGN
                os.kill(os.getpid(), signal.SIGHUP)
            assert flag == []
        finally:
            signal.signal(signal.SIGHUP, old)
    monkeypatch.setattr(run_mod, "train_step", real)
    resumed = train(tiny("gd", tmp_path / "a", steps=9, checkpoint_every=100), prior, write_outputs=False)
    assert resumed.resumed_from == 4
    full = train(tiny("gd", tmp_path / "b", steps=9), prior, write_outputs=False)
    for k in PARAM_NAMES:
        assert torch.equal(full.state.params[k], resumed.state.params[k]), k


_TERM_SCRIPT = (
    PACED_RUN
    + """
from gdbench.app.cli import run_reporting
if sys.argv[2] == "before":  # the signal lands before training starts
    run_reporting("generate", lambda: (print("ready", flush=True), time.sleep(60)))
cfg = tiny("gd", sys.argv[1], steps=60, checkpoint_every=3)
run_reporting("generate", lambda: run.train(cfg, prior, write_outputs=False))
"""
)


@pytest.mark.parametrize("when", ["before", "during"])
def test_sigterm_from_outside_ends_the_command_with_one_line_and_143(prior, tmp_path, when):
    """What `timeout` and Slurm send, to a separate process through the CLI's handlers: before
    training, one line and 143; during training, one line naming the step, 143, a whole
    checkpoint, and a resume that gives the uninterrupted result."""
    import subprocess
    import time

    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    out = tmp_path / "t"
    proc = subprocess.Popen([sys.executable, "-c", _TERM_SCRIPT, str(out), when], cwd=root,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    ckpt = out / "checkpoint.pt"
    try:
        if when == "before":
            assert proc.stdout.readline().strip() == "ready"
        else:
            deadline = time.time() + 120
            while not ckpt.exists() and time.time() < deadline and proc.poll() is None:
                time.sleep(0.05)
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    line = one_line(err)
    if when == "before":
        assert line == "gdbench generate: error: interrupted by SIGTERM"
        return
    assert line.startswith("gdbench generate: error: interrupted by SIGTERM at step "), line
    step = int(line.split(" at step ")[1].split()[0])
    assert 0 < step < 60 and f"checkpoint saved to {ckpt}" in line
    assert torch.load(ckpt, weights_only=True)["step"] == step
    resumed = train(tiny("gd", out, steps=60, checkpoint_every=3), prior, write_outputs=False)
    assert resumed.resumed_from == step
    full = train(tiny("gd", tmp_path / "full", steps=60, checkpoint_every=3), prior, write_outputs=False)
    for k in PARAM_NAMES:
        assert torch.equal(full.state.params[k], resumed.state.params[k]), k


@pytest.mark.parametrize("how", ["OSError", "torch's RuntimeError"])
def test_a_full_disk_mid_checkpoint_keeps_the_last_one(prior, tmp_path, monkeypatch, how):
    """A full disk during torch.save, as an OSError or as torch reports it on a real disk (a
    RuntimeError "unexpected pos" whose context is the OSError): one OSError naming the
    checkpoint, the previous checkpoint intact, no temporary file left."""
    from gdbench.app.cli import error_line

    out = tmp_path / "run"
    train(tiny("gd", out, steps=4), prior, stop_at=2, write_outputs=False)
    before = (out / "checkpoint.pt").read_bytes()

    def full(*a, **k):
        try:
            raise OSError(errno.ENOSPC, "No space left on device")
        except OSError:
            if how == "OSError":
                raise
            raise RuntimeError("[enforce fail at inline_container.cc:672] . unexpected pos 704 vs 598") from None

    monkeypatch.setattr(torch, "save", full)
    with pytest.raises(OSError, match="No space left") as e:
        train(tiny("gd", out, steps=4), prior, write_outputs=False)
    assert e.value.filename == str(out / "checkpoint.pt")
    assert error_line(e.value) == (f"{out / 'checkpoint.pt'}: No space left on device", 2)
    assert (out / "checkpoint.pt").read_bytes() == before
    assert not [p for p in out.iterdir() if p.name.endswith(".tmp")]  # no temporary file left


@pytest.fixture
def small_disk(tmp_path):
    """A real 2 MiB file system (tmpfs) at tmp_path/disk. Mounting one needs root; elsewhere the
    test is skipped, and the faked full-disk tests above still run."""
    import shutil
    import subprocess

    disk = tmp_path / "disk"
    disk.mkdir()
    if os.geteuid() != 0 or shutil.which("mount") is None:
        pytest.skip("a real full disk needs a tmpfs mount, which needs root here (the faked full-disk tests run)")
    r = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=2m", "tmpfs", str(disk)], capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"mounting a tmpfs was refused ({r.stderr.strip()}); the faked full-disk tests run")
    try:
        yield disk
    finally:
        subprocess.run(["umount", "-l", str(disk)], check=False)


def fill(disk) -> None:
    """Fill the file system to its last byte."""
    fd = os.open(disk / "filler", os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        for size in (1 << 16, 1 << 10, 1):
            while True:
                try:
                    os.write(fd, b"\0" * size)
                except OSError as e:
                    assert e.errno == errno.ENOSPC
                    break
    finally:
        os.close(fd)


@pytest.mark.filterwarnings("error::pytest.PytestUnraisableExceptionWarning")
def test_a_really_full_disk_keeps_every_file_whole(prior, small_disk):
    """On a real full file system: the checkpoint write (torch.save) and the turntable's GIF each
    end in one OSError naming the file; the previous checkpoint and GIF are intact; no partial
    or temporary file is left, and imageio's half-written file says nothing more (its __del__
    would retry the write and print a second traceback)."""
    from gdbench.app.cli import error_line
    from gdbench.core.scene import sphere_init
    from gdbench.core.turntable import write_turntable

    out = small_disk / "run"
    train(tiny("gd", out, steps=6, checkpoint_every=2), prior, stop_at=2, write_outputs=False)
    ckpt = out / "checkpoint.pt"
    before = ckpt.read_bytes()
    scene = sphere_init(200, opacity=0.5, generator=torch.Generator().manual_seed(0))
    write_turntable(scene, small_disk / "tt", frames=4, size=48, mp4=False)
    gif = (small_disk / "tt" / "turntable.gif").read_bytes()
    fill(small_disk)
    with pytest.raises(OSError) as e:
        train(tiny("gd", out, steps=6, checkpoint_every=2), prior, write_outputs=False)
    assert e.value.errno == errno.ENOSPC and e.value.filename == str(ckpt), e.value
    assert error_line(e.value)[1] == 2 and ckpt.read_bytes() == before
    with pytest.raises(OSError) as e:
        write_turntable(scene, small_disk / "tt", frames=24, size=96, mp4=False)
    assert e.value.errno == errno.ENOSPC and e.value.filename.startswith(str(small_disk / "tt")), e.value
    assert (small_disk / "tt" / "turntable.gif").read_bytes() == gif
    left = [p.name for d in (out, small_disk / "tt") for p in d.iterdir() if p.name.startswith(".")]
    assert left == [FolderLock.NAME], left  # the run's lock file, and no temporary file


def test_images_are_written_atomically(tmp_path, monkeypatch):
    """A writer that fails midway (here imageio, after writing part of the file) leaves the old
    GIF and contact sheet as they were, no temporary file, and one OSError naming the file."""
    import imageio.v3 as iio

    from gdbench.core.scene import sphere_init
    from gdbench.core.turntable import write_turntable

    scene = sphere_init(100, opacity=0.5, generator=torch.Generator().manual_seed(0))
    write_turntable(scene, tmp_path, frames=3, size=32, mp4=False)
    old = {p.name: p.read_bytes() for p in tmp_path.iterdir()}
    real = iio.imwrite

    def partial(path, *a, **k):
        with open(path, "wb") as f:
            f.write(b"GIF89a half a file")
        raise ValueError("the writer failed") from OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(iio, "imwrite", partial)
    with pytest.raises(OSError, match="No space left") as e:
        write_turntable(scene, tmp_path, frames=3, size=32, mp4=False)
    assert e.value.filename == str(tmp_path / "turntable.gif")
    monkeypatch.setattr(iio, "imwrite", real)
    assert {p.name: p.read_bytes() for p in tmp_path.iterdir()} == old


def test_score_and_render_are_writers_that_take_the_lock(prior, tmp_path, monkeypatch, capsys):
    """score and render write into a run folder: refused (one line, exit 2) while another gdbench
    process holds it, e.g. a generate --overwrite replacing the run."""
    from gdbench.metrics.run_scores import score_run

    out = tmp_path / "run"
    train(tiny("gd", out, steps=2), prior)
    with FolderLock(out):
        with pytest.raises(FolderBusy, match=rf"run: {out} is in use by another gdbench run"):
            score_run(out, gt=False, colmap=False)
        code, _, err = cli(monkeypatch, capsys, "render", out, "--frames", "2", "--size", "32")
        assert code == 2 and "is in use by another gdbench run" in one_line(err)
        assert not (out / "scene_turntable.gif").exists()
    assert score_run(out, gt=False, colmap=False)["run_id"]  # free again: both work
    code, _, err = cli(monkeypatch, capsys, "render", out, "--frames", "2", "--size", "32")
    assert code == 0 and (out / "scene_turntable.gif").is_file(), err


def test_score_refuses_a_folder_whose_files_come_from_two_runs(prior, tmp_path):
    """scene.ply's header names its run; run.json records the run and the scene's hash. A PLY of
    another run, or a PLY changed after the run, is refused naming both."""
    from gdbench.core.scene import GaussianScene
    from gdbench.metrics.run_scores import score_run

    a, b = tmp_path / "a", tmp_path / "b"
    train(tiny("gd", a, steps=2), prior)
    train(tiny("gd", b, steps=2, seed=1), prior)
    id_a, id_b = (json.loads((d / "run.json").read_text())["run_id"] for d in (a, b))
    (a / "scene.ply").write_bytes((b / "scene.ply").read_bytes())
    with pytest.raises(ValueError, match=rf"scene.ply is from run {id_b} but .*run.json describes run {id_a}"):
        score_run(a, gt=False, colmap=False)
    scene = GaussianScene.load_ply(b / "scene.ply")
    scene.opacity_logits.add_(0.5)
    scene.save_ply(b / "scene.ply", comments=[f"gdbench run {id_b}"])  # its own run's header, other values
    with pytest.raises(ValueError, match=r"scene.ply is not the scene .*run.json records"):
        score_run(b, gt=False, colmap=False)
    assert not (a / "scores.json").exists() and not (b / "scores.json").exists()


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
        (
            ("generate", "a yellow duck", "--out", "/sys/gdbench-out", "--steps", "1"),
            r"out \(--out\): cannot write into /sys/gdbench-out \(",
        ),
        (
            ("generate", "a yellow duck", "--out", "/proc/gdbench/out", "--steps", "1"),
            r"out \(--out\): cannot write into /proc/gdbench/out",
        ),
        (
            ("export", "PLY", "--format", "splat", "--out", "x.ply"),
            r"out \(--out\): --format splat writes a \.splat file",
        ),
        (
            ("generate", "a yellow duck", "--preset", "dreamgaussian"),
            r"--preset: unknown preset 'dreamgaussian'; expected one of gd, gd-no-sn, .*gd-pose-locked$",
        ),
        (
            ("generate", "a yellow duck", "--out", "FILE", "--steps", "1"),
            r"out \(--out\): .*FILE is a file; expected a folder",
        ),
        (("generate", "a yellow duck", "--resolution", "100000"), r"\(--resolution\): 100000 needs about \d+"),
        (("generate", "a green duck", "--steps", "1"), r"'a green duck' matches no duck .*asks for green.*nearest"),
        (("generate", "not a duck", "--steps", "1"), r"prompt: 'not a duck' negates \('not'\)"),
        (("score", "MISSING"), r"run: expected a run folder, got .*MISSING"),
        (("render", "MISSING"), r"run: no scene at .*MISSING"),
        (("render", "PLY", "--size", "40000"), r"size \(--size\): 40000 needs about \d+"),
        (
            ("compare", "--scene", "isotropic", "--out", "/sys/gdbench-compare", "--backends", "splat"),
            "/sys/gdbench-compare",
        ),
        (("noise", "--preview", "--out", "x.jpg"), r"out: expected a .png file or a folder"),
        (("sweep", "--prompts", "a yellow duck", "a spaceship", "--presets", "gd", "--no-colmap"), "a spaceship"),
        (("sweep", "--prompts", "a yellow duck", "A yellow duck!", "--presets", "gd"), "share the cell folder"),
        # declared ranges (gdbench.core.constraints), refused before anything is built: the flag typed
        (("generate", "a yellow duck", "--out", "R", "--log-every", "0"), r"\(--log-every\): expected an int >= 1"),
        (("generate", "a yellow duck", "--out", "R", "--densify-every", "0"), r"\(--densify-every\): expected"),
        (("generate", "a yellow duck", "--out", "R", "--densify-reset-every", "0"), r"\(--densify-reset-every\)"),
        (("generate", "a yellow duck", "--out", "R", "--camera-radius", "inf"), r"\(--camera-radius\): expected a f"),
        (("generate", "a yellow duck", "--out", "R", "--turntable-frames", "0"), r"\(--turntable-frames\)"),
        (("generate", "a yellow duck", "--out", "R", "--fovy-range", "70", "40"), r"\(--fovy-range\): expected low"),
        (("sweep", "--colmap-views", "0", "--out", "R"), r"\(--colmap-views\): expected an int >= 2"),
        (("render", "PLY", "--frames", "0"), r"\(--frames\): expected an int >= 1"),
        (("noise", "--preview", "--res", "0"), r"\(--res\): expected an int >= 8 px"),
        (("score", "MISSING", "--views", "1"), r"\(--views\): expected an int >= 2"),
        # memory, estimated before anything is allocated: the flag of the largest buffer
        (("noise", "--preview", "--res", "400000"), r"res \(--res\): 400000 needs about \d+"),
        (("demo", "--size", "300000", "--out", "R"), r"size \(--size\): 300000 needs about \d+"),
        (("render", "PLY", "--frames", "10000000", "--size", "64"), r"frames \(--frames\): 10000000 needs about"),
        (("generate", "a yellow duck", "--out", "R", "--samples-per-step", "10000000"), r"\(--samples-per-step\)"),
        (("generate", "a yellow duck", "--out", "R", "--init-points", "1000000000"), r"\(--init-points\): 1000"),
    ],
)
def test_bad_input_is_one_line_with_exit_code_2(monkeypatch, capsys, tmp_path, args, match):
    monkeypatch.chdir(tmp_path)
    (tmp_path / "FILE").write_text("not a folder")
    from gdbench.core.builtin import demo_scene

    demo_scene(20).save_ply(tmp_path / "PLY")
    handlers = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)}
    code, _, err = cli(monkeypatch, capsys, *args)
    assert {s: signal.getsignal(s) for s in handlers} == handlers  # given back after the error line
    line = one_line(err)
    assert code == 2 and line.startswith(f"gdbench {args[0]}: error: "), err
    import re

    assert re.search(match, line), line
    assert not (tmp_path / "runs").exists() or args[0] == "generate"  # nothing trained for a bad grid
    assert not (tmp_path / "R").exists()  # a bad option: nothing built, no folder made


def test_broken_checkpoints_are_one_line_errors(monkeypatch, capsys, tmp_path):
    out = tmp_path / "run"
    out.mkdir()
    for content in (b"", b"\x00" * 64):
        (out / "checkpoint.pt").write_bytes(content)
        code, _, err = cli(monkeypatch, capsys, "generate", "a yellow duck", "--out", out, "--steps", "1")
        assert code == 2 and "checkpoint.pt is unreadable" in one_line(err)


def test_well_formed_but_foreign_files_are_named_not_crashed_on(prior, tmp_path):
    """Files of the right format with the wrong content: a checkpoint of format 2 with no config
    or with parameters of wrong shapes, a run.json with a field of the wrong type, a cell.json
    without its row. Each is a ValueError naming the file, not a KeyError or AttributeError."""
    from gdbench.experiments.sweep import CellSpec, _done
    from gdbench.metrics.run_scores import score_run
    from gdbench.train.checkpoint import FORMAT, CheckpointError

    out = tmp_path / "run"
    train(tiny("gd", out, steps=4), prior, stop_at=2, write_outputs=False)
    ckpt = out / "checkpoint.pt"
    blob = torch.load(ckpt, weights_only=True)
    torch.save({"format": FORMAT}, ckpt)
    with pytest.raises(CheckpointError, match=r"checkpoint: .*checkpoint.pt is a gdbench checkpoint but its config"):
        train(tiny("gd", out, steps=4), prior, write_outputs=False)
    moments = blob["optimizer"]["state"][0]["exp_avg"]
    blob["optimizer"]["state"][0]["exp_avg"] = moments[:2]  # the fused Adam kernel would crash on it
    torch.save(blob, ckpt)
    with pytest.raises(CheckpointError, match=r"training state is broken \(ValueError: optimizer\['means'\].exp_avg"):
        train(tiny("gd", out, steps=4), prior, write_outputs=False)
    blob["optimizer"]["state"][0]["exp_avg"] = moments
    blob["params"]["quats"] = blob["params"]["quats"][:-1]
    torch.save(blob, ckpt)
    with pytest.raises(CheckpointError, match=r"training state is broken \(ValueError: params\['quats'\]: expected"):
        train(tiny("gd", out, steps=4), prior, write_outputs=False)
    run = tmp_path / "done"
    train(tiny("gd", run, steps=2), prior)
    info = json.loads((run / "run.json").read_text())
    for field_, bad in (("config", [1, 2]), ("caption", 3)):
        (run / "run.json").write_text(json.dumps(info | {field_: bad}))
        with pytest.raises(ValueError, match=rf"run.json: .*run.json: '{field_}' should be a"):
            score_run(run, gt=False, colmap=False)
    (run / "run.json").write_text(json.dumps(info | {"config": info["config"] | {"background": "white"}}))
    with pytest.raises(ValueError, match=r"config.background should be 3 numbers"):
        score_run(run, gt=False, colmap=False)
    spec = CellSpec(CAPTION, "gd", 0, 2, str(tmp_path / "sweep"), colmap=False)
    spec.dir.mkdir(parents=True)
    for content, match in (("[]", "holds a JSON list"), ('{"spec": {}}', "holds no 'row' object")):
        (spec.dir / "cell.json").write_text(content)
        with pytest.raises(ValueError, match=rf"cell.json: .*cell.json {match}"):
            _done(spec)


def test_a_diverged_run_and_a_dangling_out_are_one_line(prior, monkeypatch, capsys, tmp_path):
    from gdbench.priors import factory

    monkeypatch.setattr(factory, "make_prior", lambda cfg: prior)
    monkeypatch.setattr(prior, "denoise", lambda x, *a, **k: x * float("nan"))
    args = ["generate", CAPTION, "--steps", "30", "--resolution", "16", "--init-points", "150", "--no-progress",
            "--max-bad-steps", "2"]  # fmt: skip
    code, _, err = cli(monkeypatch, capsys, *args, "--out", tmp_path / "d")
    assert code == 2 and "consecutive steps had non-finite gradients" in one_line(err) and "lower the" in err
    for name, target in (("dangling", tmp_path / "nowhere"), ("loop", tmp_path / "loop")):
        (tmp_path / name).symlink_to(target)
        code, _, err = cli(monkeypatch, capsys, *args, "--out", tmp_path / name)
        assert code == 2 and f"out (--out): {tmp_path / name} is a symbolic link to" in one_line(err), err
    assert not (tmp_path / "nowhere").exists()


def test_the_memory_estimate_names_the_flag_that_sizes_the_largest_buffer():
    """Without the empirical prior's bank, a huge resolution still names --resolution (its
    renders), and many views per step name --views-per-step."""
    from gdbench.app.resources import generate_terms
    from gdbench.train.config import TrainConfig, apply_overrides

    def largest(**kw):
        return max(generate_terms(apply_overrides(TrainConfig(), kw)), key=lambda x: x[2])[0]

    assert largest(prior="learned", resolution=40000) == "resolution"
    assert largest(prior="learned", views_per_step=100000) == "views_per_step"
    assert largest(resolution=40000) == "resolution"


def test_the_sweeps_advice_names_what_it_has(prior, tmp_path, monkeypatch):
    """A cell folder holding a finished run of another config: the sweep (which has no
    --overwrite) says to delete that cell's folder. A prompt too long for a folder name is
    refused when the grid is checked."""
    from gdbench.experiments.sweep import CellSpec, cell_name, run_cell
    from gdbench.priors import factory

    monkeypatch.setattr(factory, "make_prior", lambda cfg: prior)
    over = {"resolution": 16, "init_points": 150, "turntable_frames": 2}
    spec = CellSpec(CAPTION, "gd", 0, 2, str(tmp_path), colmap=False, overrides=over)
    train(tiny("gd", spec.dir, steps=2, seed=5), prior)  # another seed's run in the cell's folder
    (spec.dir / "checkpoint.pt").unlink()
    with pytest.raises(ValueError, match=rf"holds a finished run .*; delete {spec.dir} to retrain this cell") as e:
        run_cell(spec)
    assert "--overwrite" not in str(e.value)
    with pytest.raises(ValueError, match=r"names a folder of 299 characters; expected at most 200"):
        cell_name("a " * 150)


def test_an_unreachable_ray_address_fails_within_its_timeout():
    """ray.init waits for minutes on an address nobody answers; the sweep probes it first. A
    closed local port answers at once (refused); a non-routable address (TEST-NET-1) times out."""
    import socket
    import time

    from gdbench.experiments.sweep import check_ray_address

    with socket.socket() as s:  # a port that was free a moment ago: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ValueError, match=rf"address: nothing answers at 127.0.0.1:{port} within 10 s"):
        check_ray_address(f"127.0.0.1:{port}")
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match=r"address: nothing answers at 192.0.2.1:6379 within 0.5 s"):
        check_ray_address("ray://192.0.2.1:6379", timeout=0.5)
    assert time.perf_counter() - t0 < 5
    for bad in ("my-cluster", "127.0.0.1:70000", "127.0.0.1:²"):
        with pytest.raises(ValueError, match="expected HOST:PORT"):
            check_ray_address(bad)
    with socket.socket() as s:  # something listening: accepted
        s.bind(("127.0.0.1", 0))
        s.listen()
        check_ray_address(f"127.0.0.1:{s.getsockname()[1]}")


def test_noise_preview_into_a_folder(monkeypatch, capsys, tmp_path):
    (tmp_path / "dir").mkdir()
    for target, want in ((tmp_path / "dir", tmp_path / "dir" / "noise_preview.png"),
                         (tmp_path / "new", tmp_path / "new" / "noise_preview.png")):  # fmt: skip
        code, out, _ = cli(
            monkeypatch, capsys, "noise", "--preview", "--out", target, "--res", "24", "--n-gaussians", "100"
        )
        assert code == 0 and want.is_file() and str(want) in out


def test_generate_prints_the_matched_caption(prior, monkeypatch, capsys, tmp_path):
    from gdbench.app.cli import main
    from gdbench.app.cmd_generate import Generate
    from gdbench.train import run as run_mod

    real = run_mod.make_context
    monkeypatch.setattr(run_mod, "make_context", lambda cfg, p=None: real(cfg, prior))
    from gdbench.app.cmd_generate import GenerateTrain

    s = main(
        Generate(CAPTION, out=tmp_path / "r", score=False, progress=False, train=GenerateTrain(steps=2, resolution=16))
    )
    assert s["caption"] == CAPTION and s["caption_similarity"] == 1.0
    assert f"prompt {CAPTION!r} -> asset {CAPTION!r} (cosine 1.00)" in capsys.readouterr().out
    assert json.loads((tmp_path / "r" / "run.json").read_text())["caption_similarity"] == 1.0


def test_sweep_cell_names_stay_inside_out():
    from gdbench.experiments.sweep import CellSpec, cell_name

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
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    mutants = script("mutants")  # registered in sys.modules: dataclasses look their module up there
    assert len(mutants.MUTATIONS) >= 16
    for m in mutants.MUTATIONS:
        text = (root / m.file).read_text()
        assert text.count(m.old) == 1, f"{m.name}: snippet found {text.count(m.old)} times in {m.file}"
        assert m.new != m.old
