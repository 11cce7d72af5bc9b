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
from tests._util import CAPTION, PACED_RUN, cli, one_line, tiny, tiny_bank


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
