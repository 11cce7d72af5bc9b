"""The command line under bad input (docs/reliability.md): every error one line with exit code 2
naming what to fix; broken or foreign checkpoints and files named, not crashed on; memory
estimated before anything is allocated; and the listed mutations still apply to the code."""

import json
import os
import signal

import pytest
import torch

from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.run import train
from tests._util import CAPTION, cli, one_line, script, tiny, tiny_bank


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})


# ------------------------------------------------------------------ 1. run folders


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
