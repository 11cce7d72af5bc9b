"""The commands' options and files: help texts, generate's default folder and stored config, settings
and sweep grid files, the cache, render, the log folder, exit codes and the prompts list."""

import json
import os
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from gdbench.app.cli import main
from gdbench.core.builtin import demo_scene
from tests._util import help_text, option_helps


def test_help_reads_once_per_option():
    """Every command's options: a help text, the default said once, no None to type, booleans
    as --x/--no-x."""
    import os
    import re

    from gdbench.app.cli import COMMANDS

    env = dict(os.environ, COLUMNS="100")  # the entry point's own output, once
    real = subprocess.run(
        [sys.executable, "-m", "gdbench.app.cli", "generate", "--help"], capture_output=True, text=True, env=env
    ).stdout
    assert "--steps INT" in real and "{None" not in real and "--anneal, --no-anneal" in real
    for command in COMMANDS:
        text = help_text(command)
        assert "{None" not in text and "{True,False}" not in text, command
        flat = " ".join(text.split())
        root = Path(__file__).resolve().parents[1]
        assert "../" not in flat, command  # nothing outside the project
        for doc in re.findall(r"[\w.-]+(?:/[\w.-]+)+\.md\b", flat):  # every document a help names is here
            assert (root / doc).is_file(), (command, doc)
        assert len(re.findall(r"\(default[^)]*\)\s*\(default", flat)) == 0, command
        helps = option_helps(command)
        assert helps, command
        for name, body in helps.items():
            assert name == "--help" or len(body.split()) >= 2, (command, name, body)


def test_generate_defaults_to_a_folder_named_after_the_prompt(tmp_path, monkeypatch, capsys):
    """No --out: runs/<prompt slug>. A finished run of another config there is refused before the
    bank is built; a fresh run does not say it resumed; the matched asset is printed before the
    steps."""

    import gdbench.train.run as run_mod
    from gdbench.app.cmd_generate import Generate, GenerateTrain

    monkeypatch.chdir(tmp_path)
    small = GenerateTrain(steps=2, resolution=16)
    s = main(Generate("A Yellow Duck!", score=False, progress=False, train=small))
    assert Path(s["out"]) == Path("runs/a_yellow_duck") and (tmp_path / "runs/a_yellow_duck/scene.ply").is_file()
    printed = capsys.readouterr().out.splitlines()
    assert printed[0].startswith("gdbench generate: prompt 'A Yellow Duck!' -> asset 'a yellow duck'")
    assert s["resumed_from"] is None and not any("resumed" in line for line in printed)
    run_json = json.loads((tmp_path / "runs/a_yellow_duck/run.json").read_text())
    assert run_json["resumed_from_step"] is None

    def no_bank(*a, **k):
        raise AssertionError("the prior was built before the folder was checked")

    monkeypatch.setattr(run_mod, "make_context", no_bank)
    with pytest.raises(FileExistsError, match="holds a finished run of 'A Yellow Duck!'"):
        main(Generate("a yellow duck!", score=False, progress=False, train=GenerateTrain(steps=3, resolution=16)))


def test_generate_config_reproduces_a_run(tmp_path):
    """--config run.json trains the same config again: same run id, bit-identical scene.ply on
    CPU; an option on the command line overrides the file; a YAML file of a few settings is
    applied to the preset."""
    from gdbench.app.cmd_generate import Generate, GenerateTrain

    a = tmp_path / "a"
    main(Generate("a corgi", preset="gd-no-vgs", out=a, score=False, progress=False,
                  train=GenerateTrain(steps=4, resolution=16, seed=3, fovy_range=(30.0, 50.0))))  # fmt: skip
    b = tmp_path / "b"
    main(Generate(config=a / "run.json", out=b, score=False, progress=False))
    ra, rb = (json.loads((p / "run.json").read_text()) for p in (a, b))
    assert ra["run_id"] == rb["run_id"] and rb["preset"] == "gd-no-vgs" and rb["prompt"] == "a corgi"
    assert (a / "scene.ply").read_bytes() == (b / "scene.ply").read_bytes()
    c = tmp_path / "c"
    main(Generate(config=a / "run.json", out=c, score=False, progress=False, train=GenerateTrain(steps=5)))
    rc = json.loads((c / "run.json").read_text())
    assert rc["steps"] == 5 and rc["config"]["fovy_range"] == [30.0, 50.0] and rc["run_id"] != ra["run_id"]
    (tmp_path / "few.yaml").write_text("prompt: a penguin\nsteps: 2\nresolution: 16\nnoise:\n  redraw: ou\n")
    d = main(Generate(config=tmp_path / "few.yaml", out=tmp_path / "d", score=False, progress=False))
    rd = json.loads((tmp_path / "d" / "run.json").read_text())
    assert d["steps"] == 2 and rd["config"]["noise"]["redraw"] == "ou" and rd["preset"] == "gd"
    (tmp_path / "bad.yaml").write_text("steps: 2\nnoise:\n  redraws: ou\n")

    with pytest.raises(ValueError, match=r"unknown setting 'noise.redraws'"):
        main(Generate("a penguin", config=tmp_path / "bad.yaml", out=tmp_path / "e", progress=False))


def test_sweep_config_file_gives_the_defaults(tmp_path, monkeypatch):
    """sweep --config grid.yaml: the file's options are the defaults, the command line overrides
    them, and the mapping a sweep writes (<out>/sweep.yaml) reads back to the same command."""
    import gdbench.app.cli as cli
    from gdbench.app.cmd_sweep import sweep_from_mapping, sweep_mapping

    grid = tmp_path / "grid.yaml"
    grid.write_text(
        "prompts: [a corgi]\npresets: [gd, gd-no-sn]\nseeds: [0, 1, 2]\nsettings: [janus]\nsteps: 300\n"
        f"out: {tmp_path / 'sw'}\ncolmap: false\noverrides:\n  views-per-step: 2\n  noise_redraw: ou\n"
    )
    seen = []
    monkeypatch.setattr(cli, "main", lambda cmd: seen.append(cmd) or {})
    monkeypatch.setattr(sys, "argv", ["gdbench", "sweep", "--config", str(grid), "--steps", "50"])
    cli.entrypoint()
    cmd = seen[0]
    assert cmd.prompts == ("a corgi",) and cmd.seeds == (0, 1, 2) and cmd.settings == ("janus",)
    assert cmd.steps == 50 and cmd.colmap is False and cmd.config == grid
    assert cmd.train.overrides() == {"views.per_step": 2, "noise.redraw": "ou"}
    assert cmd.train.options() == {"views_per_step": 2, "noise_redraw": "ou"}
    again = sweep_from_mapping(sweep_mapping(cmd))
    assert sweep_mapping(again) == sweep_mapping(cmd)

    with pytest.raises(ValueError, match="unknown sweep option 'prompt'"):
        sweep_from_mapping({"prompt": "a duck"})


def test_cache_list_and_clear(tmp_path, monkeypatch, capsys):
    """The cache's listing adds up the files on disk; clear removes gdbench's parts only."""
    from gdbench.app.cmd_tools import Cache
    from gdbench.core import cache

    monkeypatch.setenv("GDBENCH_CACHE", str(tmp_path / "c"))
    (tmp_path / "c" / "banks").mkdir(parents=True)
    (tmp_path / "c" / "banks" / "a.npz").write_bytes(b"x" * 1500)
    (tmp_path / "c" / "banks" / "b.npz").write_bytes(b"x" * 2500)
    (tmp_path / "c" / "fixtures").mkdir()
    (tmp_path / "c" / "fixtures" / "f.pt").write_bytes(b"y" * 10)
    (tmp_path / "c" / "mine").mkdir()
    (tmp_path / "c" / "mine" / "keep.txt").write_bytes(b"z" * 7)
    listed = main(Cache("list"))
    assert listed["entries"] == {"banks": 4000, "fixtures": 10, "mine": 7}
    assert "4.0 KB" in capsys.readouterr().out
    main(Cache("clear", kinds=("banks",)))
    assert not (tmp_path / "c" / "banks").exists() and (tmp_path / "c" / "fixtures" / "f.pt").is_file()
    main(Cache("clear"))
    assert cache.entries()[0].kind == "mine" and len(cache.entries()) == 1
    (tmp_path / "c" / "prebuild.log").write_text("gdbench cache: 'a corgi' ready (20.0 s)\n")
    main(Cache("list"))
    line = next(x for x in capsys.readouterr().out.splitlines() if "prebuild.log" in x)
    assert "the log of the background bank build" in line and "not gdbench's" not in line
    with pytest.raises(ValueError, match="prompts: only for build"):
        main(Cache("list", prompts=("a corgi",)))
    with pytest.raises(ValueError, match="kinds: only for clear"):
        main(Cache("build", kinds=("banks",)))


def test_a_background_build_is_found_by_its_pid_file_while_it_lives(tmp_path, monkeypatch):
    """``prebuild.running``: the pid file of a live process names it; of a dead one, or of the
    caller itself, nothing (``generate`` prints a note when it names a build)."""
    from gdbench.app.prebuild import PID, running

    monkeypatch.setenv("GDBENCH_CACHE", str(tmp_path))
    assert running() is None  # no file
    child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
    try:
        (tmp_path / PID).write_text(str(child.pid))
        assert running() == child.pid
    finally:
        child.kill()
        child.wait()
    assert running() is None  # the process is gone
    (tmp_path / PID).write_text(str(os.getpid()))
    assert running() is None  # the caller is not a build beside itself


@pytest.mark.slow
def test_cache_build_leaves_nothing_for_a_first_run_to_render(tmp_path, monkeypatch):
    """After `gdbench cache build --prompts PROMPT` in an empty cache, a first run of the prompt and
    its scores render nothing with pyrender (oracle: pyrender's entry points raise), and the
    build of every asset writes the marker scripts/setup.sh looks for."""
    from gdbench.app.cmd_generate import Generate, GenerateTrain
    from gdbench.app.cmd_tools import Cache
    from gdbench.app.prebuild import PREBUILT

    monkeypatch.setenv("GDBENCH_CACHE", str(tmp_path / "c"))
    assert main(Cache("build", prompts=("a yellow duck",)))["built"] == ["a yellow duck"]
    assert not (tmp_path / "c" / "banks" / PREBUILT).exists()  # only when every asset was built

    def no_render(*a, **k):
        raise AssertionError("a first run rendered with pyrender after cache build")

    import renderers.pyrender_points.mesh as mesh

    monkeypatch.setattr(mesh, "render_mesh", no_render)
    main(
        Generate(
            "a yellow duck", out=tmp_path / "run", progress=False, train=GenerateTrain(steps=2, turntable_frames=2)
        )
    )
    assert json.loads((tmp_path / "run" / "scores.json").read_text())["gt"]["psnr"] > 0


def test_render_uses_the_runs_cameras_and_frames_any_ply(tmp_path):
    """render of a run folder draws generate's turntable frames again (same cameras, size and
    background: identical pixels); a PLY from elsewhere is framed from its bounds, so the same
    scene scaled by 7 and moved renders the same frames (a camera's image is invariant under a
    similarity applied to scene and orbit)."""
    import dataclasses

    from gdbench.app.cmd_generate import Generate, GenerateTrain
    from gdbench.app.cmd_scenes import Render

    out = tmp_path / "run"
    small = GenerateTrain(steps=3, resolution=16, turntable_frames=4, background=(0.2, 0.3, 0.4))
    main(Generate("a yellow duck", out=out, score=False, progress=False, train=small))
    main(Render(out))
    a, b = iio.imread(out / "turntable.gif"), iio.imread(out / "scene_turntable.gif")
    assert a.shape == b.shape == (4, 128, 128, 3) and np.array_equal(a, b)
    scene = demo_scene(300, seed=1)
    moved = dataclasses.replace(
        scene, means=scene.means * 7 + torch.tensor([3.0, -2.0, 5.0]), log_scales=scene.log_scales + np.log(7)
    )
    scene.save_ply(tmp_path / "s.ply")
    moved.save_ply(tmp_path / "m.ply")
    main(Render(tmp_path / "s.ply", frames=3, size=64))
    main(Render(tmp_path / "m.ply", frames=3, size=64))
    fs, fm = (iio.imread(tmp_path / f"{n}_turntable_sheet.png").astype(int) for n in ("s", "m"))
    assert fs.std() > 10 and (fs != 255).any(axis=-1).mean() > 0.1  # a framed object, not a speck
    assert np.abs(fs - fm).mean() < 1.0 and np.abs(fs - fm).max() <= 40


def test_log_dir_writes_tensorboard_scalars(tmp_path):
    """--log-dir: TensorBoard's own reader finds the step metrics at every log_every steps, equal
    to the run's history, and the PSNR against the asset at checkpoints and the end, equal to the
    PSNR of the written scene.ply's renders."""
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from gdbench.core.scene import GaussianScene
    from gdbench.core.turntable import render_views
    from gdbench.metrics.gt import asset_views, heldout_poses, psnr
    from gdbench.train.config import preset
    from gdbench.train.run import train

    cfg = preset("gd", prompt="a yellow duck", out=tmp_path / "run", steps=6, resolution=16, progress=False,
                 log_every=2, checkpoint_every=3, log_dir=tmp_path / "tb")  # fmt: skip
    r = train(cfg)
    (run_dir,) = (tmp_path / "tb").iterdir()
    ev = EventAccumulator(str(run_dir))
    ev.Reload()
    res = {e.step: e.value for e in ev.Scalars("train/residual")}
    assert sorted(res) == [2, 4, 6]
    for h in r.state.history:
        if h["step"] in res:
            assert res[h["step"]] == pytest.approx(h["residual"], rel=1e-6)
    gt = {e.step: e.value for e in ev.Scalars("gt/psnr_vs_asset")}
    assert sorted(gt) == [3, 6]
    scene = GaussianScene.load_ply(tmp_path / "run" / "scene.ply")
    poses = heldout_poses()
    ref = asset_views("a yellow duck", poses, 64, cfg.background, 0)
    want = float(psnr(render_views(scene, poses.cameras(64, 64), background=cfg.background), ref).mean())
    assert gt[6] == pytest.approx(want, abs=1e-3) and 5 < want < 40


def test_settings_files_are_typed_and_numbers_are_numbers(tmp_path, monkeypatch):
    """A settings file's values are checked by type ("false" is not a bool, 5 not a path), a
    number is the same setting written as 1 or 1.0 (same run id), --preset cannot relabel a
    file's preset, and a file's run folder is used when --out is not given."""
    import yaml

    from gdbench.app.cmd_generate import Generate, _config_file
    from gdbench.app.cmd_sweep import Sweep, SweepTrain, sweep_mapping
    from gdbench.train.config import config_from_dict, preset
    from gdbench.train.run import run_id

    a = config_from_dict({"fovy_range": [30, 60], "camera_radius": 1, "sigma_min": "3e-2"})
    assert run_id(a) == run_id(preset("gd", fovy_range=(30.0, 60.0)))
    cases = [({"vgs": "false"}, "vgs: expected bool"), ({"init_ply": 3}, "init_ply: expected Path"),
           ({"steps": 2.5}, "steps: expected int"), ({"fovy_range": [1, 2, 3]}, "expected 2 values")]  # fmt: skip
    for bad, match in cases:
        with pytest.raises(ValueError, match=match):
            config_from_dict(bad)
    f = tmp_path / "gd.yaml"
    f.write_text(f"preset: gd\nprompt: a corgi\nout: {tmp_path / 'from_file'}\n")
    with pytest.raises(ValueError, match=r"preset: .* holds the settings of preset 'gd'; drop --preset sjc-gs"):
        main(Generate(config=f, preset="sjc-gs", progress=False))
    cfg, out = _config_file(f, None)
    assert out == tmp_path / "from_file" and cfg.prompt == "a corgi"
    sw = Sweep(train=SweepTrain(init="ply", init_ply=Path("pts.ply")))  # a path override writes as text
    assert yaml.safe_load(yaml.safe_dump(sweep_mapping(sw)))["overrides"]["init_ply"] == "pts.ply"


def test_sweep_grid_files_and_optional_parts_fail_in_one_line(tmp_path, monkeypatch, capsys):
    """sweep --config: dotted and nested training names as run.json writes them, an empty file
    (every default), two --config, a missing file and an option of the wrong type each end in
    one line; a missing optional dependency's advice is one line too; clear refuses a cache
    folder that is the current one (GDBENCH_CACHE="" means unset)."""
    import gdbench.app.cli as cli
    from gdbench.app.cli import error_line
    from gdbench.app.cmd_sweep import sweep_from_mapping
    from gdbench.core import cache

    s = sweep_from_mapping({"overrides": {"noise": {"redraw": "ou"}, "densify.enabled": False}})
    assert s.train.overrides() == {"noise.redraw": "ou", "densify.enabled": False}
    assert sweep_from_mapping(None).prompts == cli.command("sweep")().prompts
    (tmp_path / "g.yaml").write_text("workers: null\n")
    for argv, match in ((["--config", "a.yaml", "--config=b.yaml"], "given more than once"),
                        (["--config", str(tmp_path / "none.yaml")], "no file at"),
                        (["--config", str(tmp_path / "g.yaml")], "workers: expected a value")):  # fmt: skip
        monkeypatch.setattr(sys, "argv", ["gdbench", "sweep", *argv])
        with pytest.raises(SystemExit) as e:
            cli.entrypoint()
        err = capsys.readouterr().err.strip()
        assert e.value.code == 2 and len(err.splitlines()) == 1 and match in err, err
    assert error_line(ImportError("viewer: pip install -e '.[view]'")) == ("viewer: pip install -e '.[view]'", 2)
    monkeypatch.setenv("GDBENCH_CACHE", "")
    assert cache.root() == Path.home() / ".cache" / "gdbench"
    monkeypatch.setenv("GDBENCH_CACHE", ".")
    with pytest.raises(ValueError, match="relative or the current folder"):
        cache.clear(["fixtures"])


def test_the_program_exits_as_python_would_without_its_teardown():
    """``program`` (the gdbench command) ends with os._exit after what a normal exit owes. Oracle:
    Python's own exit of the same script: an exit handler registered before runs and prints, a
    thread that is not a daemon finishes its line, every line of the help reaches the pipe, and the
    exit codes are Python's (0 for --help, 2 for a bad option, 1 and the text for a string)."""
    import os

    root = Path(__file__).resolve().parents[1]
    script = (
        "import atexit, sys, threading, time\n"
        "from concurrent.futures import ThreadPoolExecutor\n"
        "atexit.register(lambda: print('exit handler ran', flush=True))\n"
        "pool = ThreadPoolExecutor(1)\n"  # a worker left waiting: Python's exit wakes it, so must program
        "pool.submit(lambda: None).result()\n"
        "from gdbench.app import cli\n"
        "sys.argv = ['gdbench', *sys.argv[1:]]\n"
        "real = cli.entrypoint if sys.argv[1:] != ['text'] else lambda: sys.exit('a text exit')\n"
        "def entrypoint():\n"
        "    threading.Thread(target=lambda: (time.sleep(1.0), print('thread done', flush=True))).start()\n"
        "    real()\n"
        "cli.entrypoint = entrypoint\n"
        "cli.program()\n"
        "print('not reached')\n"
    )
    env = dict(os.environ, COLUMNS="100")

    def run(*argv):
        return subprocess.run([sys.executable, "-c", script, *argv], capture_output=True, text=True, cwd=root, env=env,
                              timeout=120)  # fmt: skip

    ok = run("generate", "--help")
    python = subprocess.run([sys.executable, "-m", "gdbench.app.cli", "generate", "--help"], capture_output=True,
                            text=True, cwd=root, env=env)  # fmt: skip
    assert ok.returncode == 0 and "not reached" not in ok.stdout
    help_lines = python.stdout.splitlines()[1:]  # the first names the program as it was called
    assert ok.stdout.splitlines()[1 : len(help_lines) + 1] == help_lines and "--steps INT" in ok.stdout
    assert ok.stdout.splitlines()[len(help_lines) + 1 :] == ["thread done", "exit handler ran"]  # Python's order
    bad = run("generate", "--steps", "many")
    assert bad.returncode == 2 and "exit handler ran" in bad.stdout and "--steps" in bad.stderr
    text = run("text")
    assert text.returncode == 1 and "a text exit" in text.stderr and "exit handler ran" in text.stdout


def test_a_resumed_run_says_so_in_its_first_line(tmp_path, capsys):
    """The second generate into a folder with a checkpoint: its first line says it resumes from
    the checkpoint (a fresh run's says how many steps go into the folder), and the last says
    from which step."""
    from gdbench.app.cmd_generate import Generate, GenerateTrain

    out = tmp_path / "r"
    small = GenerateTrain(steps=3, resolution=16)
    main(Generate("a yellow duck", out=out, score=False, progress=False, train=small))
    first = capsys.readouterr().out.splitlines()
    assert "; 3 steps into " in first[0] and "resuming" not in first[0]
    main(Generate("a yellow duck", out=out, score=False, progress=False, train=small))
    again = capsys.readouterr().out.splitlines()
    assert again[0].endswith(f"; resuming the run in {out} from its checkpoint (3 steps in all)"), again[0]
    assert any("(resumed from step 3)" in line for line in again)
    # --overwrite deletes the finished run with its checkpoint: a fresh run, and it says so
    main(Generate("a yellow duck", out=out, score=False, progress=False, overwrite=True, train=small))
    over = capsys.readouterr().out.splitlines()
    assert "; 3 steps into " in over[0] and "resuming" not in over[0], over[0]
    assert not any("resumed from step" in line for line in over)


def test_prompts_lists_the_catalogue_and_filters_by_kind(tmp_path, monkeypatch, capsys):
    """`gdbench prompts` lists every caption of the catalogue (oracle: library.CAPTIONS and PARTS)
    with its kind, the priors that know it and its bank's state (oracle: the file on disk);
    --kind keeps one kind; an unknown kind is refused naming the kinds."""
    from gdbench.app.cmd_tools import Prompts, _prompt_set
    from gdbench.assets.bank import BankConfig, bank_path
    from gdbench.assets.families import WORLD
    from gdbench.assets.library import ASSETS, CAPTIONS, PARTS
    from gdbench.priors.learned.prior import LearnedPrior

    monkeypatch.setenv("GDBENCH_CACHE", str(tmp_path / "c"))
    path = bank_path("a blue duck", BankConfig())
    path.parent.mkdir(parents=True)
    path.write_bytes(b"x")
    out = main(Prompts())
    assert out["captions"] == list(CAPTIONS) and len(CAPTIONS) >= 36
    rows = {r["caption"]: r for r in out["rows"]}
    assert rows["a blue duck"]["bank"] == "cached" and rows["a white duck"]["bank"] == "-"
    # the learned column follows the shipped model's own caption rows (oracle: the loaded prior)
    prior = LearnedPrior("uniform", device="cpu")
    for c in CAPTIONS:
        want = "empirical, learned" if c in prior.captions else "empirical"
        assert rows[c]["priors"] == want + " (held out)" * (c in prior.held_out), c
    assert rows["a yellow duck"]["priors"] == "empirical, learned"
    text = capsys.readouterr().out
    assert (
        f"{len(CAPTIONS)} objects ({len(CAPTIONS) - 1} with a front) in {len(set(k for k, *_ in PARTS.values()))} kinds"
        in text
    )
    ducks = main(Prompts(kind="duck"))["captions"]
    assert ducks == [c for c in CAPTIONS if PARTS[c][0] == "duck"] and len(ducks) == 3
    with pytest.raises(ValueError, match=r"kind: expected one of bear, bird, .* got 'cow'"):
        main(Prompts(kind="cow"))
    assert _prompt_set(("all",)) == list(CAPTIONS) and _prompt_set(()) is None
    assert _prompt_set(("a corgi", "world", "a corgi")) == ["a corgi", *WORLD]
    assert set(ASSETS) <= set(CAPTIONS)
