"""The ``gdbench`` command line. ``main(cmd)`` does the work and is tested; ``entrypoint``
only parses arguments with tyro."""

from __future__ import annotations

import functools
import signal
from dataclasses import dataclass, field, fields, make_dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from gdbench.app.commands import (
    Bench,
    Cache,
    Compare,
    Demo,
    Export,
    Noise,
    TrainPrior,
    View,
    run_bench,
    run_cache,
    run_compare,
    run_demo,
    run_export,
    run_noise,
    run_train_prior,
    run_view,
)
from gdbench.core.constraints import AtLeast, Between, Positive, Seed, check_fields
from gdbench.core.io import prompt_slug
from gdbench.priors.factory import PRIOR_CONFIGS
from gdbench.train.config import BASE_PRESETS, PRESETS
from gdbench.train.options import train_options

PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]
"""The presets' names, from the one place they are defined (train/config.py)."""
GENERATE_EXCLUDES = ("prompt", "preset", "out", "progress")
"""TrainConfig fields that are not training options of generate (its own options, or none)."""
GenerateTrain = train_options(GENERATE_EXCLUDES)
"""Every other TrainConfig field as an optional override of the preset (the empirical prior's
options; ``generate_command`` makes the others')."""


@dataclass
class GenerateBase:
    """Text to a 3D Gaussian scene: score distillation on the embedded CPU prior (or the learned
    prior with --prior learned, Stable Diffusion with --prior sd).

    Writes scene.ply, turntable.{gif,mp4}, turntable_sheet.png, curves.png, run.json and a
    checkpoint to --out; an interrupted run resumes from its checkpoint. Every training setting
    is an option; unset ones keep the preset's value (docs/training.md)."""

    prompt: Annotated[tyro.conf.Positional[str | None], tyro.conf.DisallowNone, tyro.conf.arg(metavar="PROMPT")] = None
    """What to generate: one of the built-in assets' captions or a paraphrase of one (required
    unless --config gives it)."""
    preset: Annotated[PresetName | None, tyro.conf.DisallowNone, tyro.conf.arg(help_behavior_hint="(default: gd)")] = (
        None
    )
    """gd: structured noise + VGS (the paper); the others are its ablations and baselines."""
    config: Path | None = None
    """A run.json (reproduces that run: same settings, same result on CPU; its device is not taken
    from it) or a JSON/YAML file of settings (TrainConfig's field names; nested groups as
    mappings). Options given on the command line override it; the file's run folder is used when
    --out is not given (default: none)."""
    out: Path | None = None
    """The run folder (default: runs/<the prompt, lower-case, '_' for other characters>, such as
    runs/a_yellow_duck)."""
    resume: bool = True
    """Continue from --out's checkpoint if there is one."""
    overwrite: bool = False
    """Replace a finished run in --out (its outputs are deleted first)."""
    score: bool = True
    """Score the result against the asset (PSNR/SSIM and view metrics) into scores.json."""
    progress: bool = True
    """Report progress: a bar on a terminal, a plain line every few seconds in a log."""


def _with_options(base: type, train: type, name: str) -> type:
    """``base`` with the option group ``train`` (a ``train_options`` class)."""
    cls = make_dataclass(
        name,
        [("train", tyro.conf.OmitArgPrefixes[train], field(default_factory=train))],
        bases=(base,),
        namespace={"__doc__": base.__doc__, "__module__": __name__},
    )
    return cls


@functools.cache
def generate_command(prior: str = "empirical") -> type:
    """The generate command with the options of ``prior`` (a --prior choice)."""
    return _with_options(GenerateBase, train_options(GENERATE_EXCLUDES, prior), "Generate")


Generate = generate_command()
"""The generate command with the empirical prior's options (the default --prior)."""


@dataclass
class Render:
    """Turntable (GIF, MP4, contact sheet) of a run folder, a 3DGS or compressed PLY, or a .splat."""

    run: tyro.conf.Positional[Path]
    """A run folder (its scene.ply is used), a .ply file (Inria 3DGS, or the compressed PLY) or a
    .splat file."""
    out: Path | None = None
    """Output folder (default: the run folder, or the PLY's folder)."""
    frames: Annotated[int | None, AtLeast(1)] = None
    """Views on the orbit, 360/frames degrees apart (default: a run's turntable frames, else 36)."""
    size: Annotated[int | None, AtLeast(8, "px")] = None
    """Side of each frame in pixels (default: a run's turntable size, else 256)."""
    radius: Annotated[float | None, Positive()] = None
    """Orbit radius in scene units (default: a run's turntable radius, 1.3; a PLY from elsewhere:
    framed from its bounds, centred on them)."""
    elevation: Annotated[float, Between(-90, 90, unit="degrees")] = 15.0
    """Camera elevation above the scene's horizontal plane (+Z up), degrees."""
    fovy: Annotated[float, Between(1, 179, unit="degrees")] = 45.0
    """Vertical field of view, degrees."""
    up: Literal["+z", "-y", "+y"] = "+z"
    """The up axis of the scene file: +z for gdbench's runs, -y for Inria/COLMAP captures and
    `gdbench export`'s default, +y."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Where the frames are rendered: cpu (the C++ compositor), cuda (gsplat's CUDA kernels with
    gdbench's conventions, or the torch path where they cannot run) or auto (cuda when torch sees
    one)."""


def run_generate(cmd) -> dict:
    from gdbench.app.resources import check_generate_memory
    from gdbench.train.config import apply_overrides, preset
    from gdbench.train.options import inert_options
    from gdbench.train.run import train

    overrides = cmd.train.overrides()
    base, file_out = _config_file(cmd.config, cmd.preset) if cmd.config is not None else (None, None)
    prompt = cmd.prompt if cmd.prompt is not None else (base.prompt if base is not None else None)
    if not prompt:
        raise ValueError("prompt: expected a prompt (such as 'a yellow duck'), or --config with one")
    if cmd.out is not None:
        out = Path(cmd.out)
    elif file_out is not None:
        out = file_out
    else:
        try:
            out = Path("runs") / prompt_slug(prompt)
        except ValueError as e:
            raise ValueError(f"{e}; pass --out") from None
    given = {"prompt": prompt, "out": out, "progress": cmd.progress, **overrides}
    cfg = apply_overrides(base, given) if base is not None else preset(cmd.preset or "gd", **given)
    inert = inert_options(cfg, overrides)
    if inert:
        raise ValueError("; ".join(inert) + ": drop the option, or set the one it needs")
    check_generate_memory(cfg)
    if cfg.log_dir is not None:  # before the bank is built, not after
        from gdbench.train.tblog import require_tensorboard

        require_tensorboard()

    def started(ctx) -> None:  # the matched asset before the steps, not after them
        caption, sim = getattr(ctx.cond, "caption", None), getattr(ctx.cond, "similarity", None)
        match = f" -> asset {caption!r} (cosine {sim:.2f})" if caption is not None else ""
        print(f"gdbench generate: prompt {cfg.prompt!r}{match}; {cfg.steps} steps into {out}", flush=True)

    r = train(cfg, resume=cmd.resume, overwrite=cmd.overwrite, on_start=started)
    summary = r.summary()
    if cmd.score and r.caption is not None and r.state.step >= cfg.steps:
        from gdbench.metrics.run_scores import score_run

        summary["gt"] = score_run(out, gt=True, colmap=False, progress=cmd.progress, device=cfg.device)["gt"]
    print(r.report(summary, matched=False))
    return summary


def _config_file(path: Path, preset_name: str | None):
    """(the TrainConfig, the run folder the file names or None) of a run.json (its "config") or a
    JSON/YAML file of settings. ``preset_name`` (given on the command line) is the base of a file
    that names no preset; a file that names one keeps it (a preset is a set of settings, not a
    label to put on another's)."""
    from gdbench.train.config import PRESETS, config_from_dict

    d = load_mapping(path)
    settings = d["config"] if "run_id" in d and isinstance(d.get("config"), dict) else d  # a run.json
    if settings is not d:  # a run.json reproduces its run on any device: --device chooses (default cpu)
        settings = {k: v for k, v in settings.items() if k != "device"}
    if preset_name and "preset" in settings and settings["preset"] != preset_name:
        raise ValueError(
            f"preset: {path} holds the settings of preset {settings['preset']!r}; drop --preset {preset_name}, "
            "or drop 'preset' from the file to apply its settings to another preset"
        )
    base = PRESETS[preset_name] if preset_name and "preset" not in settings else None
    cfg = config_from_dict(settings, base=base, what=f"config ({path})")
    return cfg, (cfg.out if "out" in settings else None)


def run_render(cmd: Render) -> dict:
    import contextlib

    from gdbench.app.export import load_scene
    from gdbench.app.resources import check_render_memory
    from gdbench.core.devices import resolve_device
    from gdbench.core.io import FolderLock
    from gdbench.core.turntable import write_turntable

    device = resolve_device(cmd.device, "device (--device)")
    src = Path(cmd.run)
    ply = src / "scene.ply" if src.is_dir() else src
    if not ply.is_file():
        raise FileNotFoundError(f"run: no PLY at {ply} (pass a run folder or a .ply file)")
    run = _run_turntable(ply)
    frames = cmd.frames or run.get("frames", 36)
    size = cmd.size or run.get("size", 256)
    check_render_memory(size, frames)
    out = Path(cmd.out or ply.parent)
    # a run folder has one writer: not while a generate (--overwrite) or score writes there
    run_folder = (out / "run.json").is_file() or (out / FolderLock.NAME).is_file()
    with FolderLock(out) if run_folder else contextlib.nullcontext():
        scene = load_scene(ply, up=cmd.up)  # a 3DGS or compressed PLY, or a .splat; +Z up
        radius = cmd.radius or run.get("radius")
        framing = ""
        if radius is None:  # not a run's scene: centred on its bounds and framed whole
            from gdbench.core.framing import frame

            scene, radius = frame(scene, cmd.fovy)
            framing = f", framed from its bounds at radius {radius:.3g}"
        res = write_turntable(
            scene.to(device),
            out,
            frames=frames,
            size=size,
            radius=radius,
            elevation=cmd.elevation,
            fovy=cmd.fovy,
            background=run.get("background", (1.0, 1.0, 1.0)),
            stem=ply.stem + "_turntable",
        )
    print(
        f"gdbench render: {len(scene)} Gaussians, {frames} frames at {size}px{framing}, "
        f"median {1e3 * sorted(res.seconds_per_frame)[frames // 2]:.1f} ms per frame"
    )
    for k, v in res.paths.items():
        print(f"  {k:5s} -> {v}")
    return {k: str(v) for k, v in res.paths.items()}


def _run_turntable(ply: Path) -> dict:
    """The turntable settings of the run whose scene ``ply`` is (its folder's run.json names the
    same scene), so ``render`` shows it from ``generate``'s cameras; {} for any other PLY."""
    from gdbench.core.io import run_json_of
    from gdbench.core.turntable import RUN_TURNTABLE
    from gdbench.train.run import turntable_size

    found = run_json_of(ply)
    if found is None:  # not a run's scene, or a run.json of another scene: framed as any PLY
        return {}
    config = found[1].get("config") or {}
    return {
        "frames": int(config.get("turntable_frames", 36)),
        "size": turntable_size(config.get("resolution", 128)),
        "background": tuple(float(c) for c in config.get("background", (1.0, 1.0, 1.0))),
        "radius": RUN_TURNTABLE["radius"],
    }


@dataclass
class Score:
    """Score a finished run folder: GT PSNR/SSIM against the asset and COLMAP consistency: the
    registration rate, Var(theta) and translation-direction error, written to its scores.json.
    Each block records its parameters, commit and time; a block is reused (and marked so) only
    when the scene, its parameters and the code (commit and uncommitted edits) match, and
    dropped when they do not."""

    run: tyro.conf.Positional[Path]
    """A run folder with scene.ply (and run.json for the caption)."""
    gt: bool = True
    """Score against the procedural asset (empirical-prior runs)."""
    colmap: bool = True
    """Run the COLMAP consistency metric (about 30 s on 2 cores)."""
    views: Annotated[int, AtLeast(2)] = 100
    """COLMAP's: the number of turntable views rendered and registered."""
    size: Annotated[int, AtLeast(16, "px")] = 256
    """COLMAP's: the side of each rendered view, in pixels."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Where the scene's views are rendered: cpu, cuda or auto (cuda when torch sees one); the
    images are compared on the CPU, and scores agree across devices to float rounding."""


def run_score(cmd: Score) -> dict:
    from gdbench.app.resources import check_score_memory
    from gdbench.metrics.run_scores import report, score_run

    if not Path(cmd.run).is_dir():
        raise FileNotFoundError(f"run: expected a run folder, got {cmd.run}")
    if cmd.colmap:
        check_score_memory(cmd.size, cmd.views)
    s = score_run(
        cmd.run, gt=cmd.gt, colmap=cmd.colmap, views=cmd.views, size=cmd.size, progress=True, device=cmd.device
    )
    print(report(s))
    return s


SWEEP_EXCLUDES = ("prompt", "preset", "out", "progress", "seed", "steps", "log_every", "log_dir")
"""TrainConfig fields that are not overrides of a sweep's cells (cells run without a progress bar,
so --log-every has no place here)."""
SweepTrain = train_options(SWEEP_EXCLUDES)
"""Every other TrainConfig field as an override of every cell (the empirical prior's options;
``sweep_command`` makes the others')."""


@dataclass
class SweepBase:
    """Train and score every (setting, prompt, preset, seed) cell; write cells.csv, summary.csv,
    summary.md and verdict.csv (the paper's claims over (prompt, seed) pairs: BCa intervals,
    signed-rank p-values Holm-adjusted, equivalence tests, power, per-prompt effects); with
    --figures also ablation.png and each cell's turntable. Resumable: finished cells (scored by
    the same code) are skipped, an interrupted cell resumes from its checkpoint. The grid is
    validated before the first cell."""

    config: Path | None = None
    """A YAML or JSON file of this command's options (their names with '_' or '-', lists for
    the tuples) and 'overrides', a mapping of training options applied to every cell; options on
    the command line override it. Each sweep writes the options it ran with to <out>/sweep.yaml,
    which this reads back (default: none)."""
    prompts: tuple[str, ...] = ("a yellow duck", "a corgi", "a penguin")
    """Prompts (free text; matched to the embedded prior's assets)."""
    presets: tuple[str, ...] = BASE_PRESETS
    """Training presets to compare (see docs/training.md; gd-redraw-step, the mechanism's
    control, on request)."""
    seeds: Annotated[tuple[int, ...], Seed()] = (0, 1)
    """Seeds per (setting, prompt, preset); cells with one seed and prompt are paired."""
    settings: tuple[Literal["easy", "janus", "instance"], ...] = ("easy",)
    """Ambiguity settings: easy (the presets' view window, one variant), janus (no view prompting,
    front-heavy bank), instance (three procedural variants per caption)."""
    janus_presets: tuple[str, ...] = ()
    """Presets of the janus setting (default: all of --presets)."""
    instance_presets: tuple[str, ...] = ()
    """Presets of the instance setting (default: all of --presets)."""
    colmap_presets: tuple[str, ...] = ()
    """Score only these presets with COLMAP (default: all, when --colmap)."""
    colmap_settings: tuple[str, ...] = ()
    """Score with COLMAP only in these settings (default: all, when --colmap)."""
    steps: Annotated[int, AtLeast(1)] = 2000
    """Training steps per cell."""
    out: Path = Path("runs/sweep")
    """Folder for the cells (one run folder each) and the tables."""
    executor: Literal["local", "ray"] = "local"
    """Where cells run: a local process pool or a Ray cluster."""
    address: str = ""
    """Ray cluster address (ray executor); empty starts a local Ray instance."""
    workers: Annotated[int, AtLeast(1)] = 1
    """Cells run at once (one training already uses both cores of a small machine)."""
    colmap: bool = True
    """Score cells with COLMAP consistency (the slow part: ~1 min per cell)."""
    colmap_views: Annotated[int, AtLeast(2)] = 100
    """Views on the circle rendered for COLMAP."""
    figures: bool = False
    """Also draw each cell's turntable (GIF, MP4, contact sheet) and training curves, as generate
    does (about 2 s a cell), and the sweep's ablation.png (every cell's metrics). Off, a cell
    writes scene.ply, run.json, scores.json and cell.json, what the tables need; run a finished
    sweep again with --figures to draw them (nothing is trained again)."""


@functools.cache
def sweep_command(prior: str = "empirical") -> type:
    """The sweep command with the options of ``prior`` (a --prior choice) as overrides of every
    cell (after its setting's)."""
    return _with_options(SweepBase, train_options(SWEEP_EXCLUDES, prior), "Sweep")


Sweep = sweep_command()
"""The sweep command with the empirical prior's options (the default --prior)."""


def sweep_from_mapping(d: dict, what: str = "config", prior: str | None = None):
    """The ``Sweep`` a grid file describes (see ``Sweep.config``): each value checked against its
    option's type (``train.config.from_json``); ``overrides`` takes the training options by their
    option names (views-per-step, noise-redraw) or run.json's (noise.redraw, or nested mappings).
    Its command has the options of ``prior`` (the command line's --prior), else of the file's
    'prior' override, else of the empirical prior."""
    import typing

    from gdbench.core.constraints import flag
    from gdbench.train.config import NESTED, from_json

    if d is None:
        d = {}  # an empty file: every default
    if not isinstance(d, dict):
        raise ValueError(f"{what}: expected a mapping of sweep options, got {type(d).__name__}")
    over = d.get("overrides")
    kind = prior or (over.get("prior") if isinstance(over, dict) else None) or "empirical"
    command = sweep_command(kind if kind in PRIOR_CONFIGS else "empirical")  # (a bad name: the check names it)
    train_cls = typing.get_type_hints(command)["train"]
    train_cls = typing.get_args(train_cls)[0] if typing.get_origin(train_cls) is Annotated else train_cls
    hints = typing.get_type_hints(SweepBase, include_extras=True)
    names = {f.name for f in fields(SweepBase)} - {"config"}
    train_hints = typing.get_type_hints(train_cls, include_extras=True)
    top, train = {}, {}
    for key, value in d.items():
        k = str(key).replace("-", "_")
        if k == "overrides":
            if not isinstance(value, dict):
                raise ValueError(f"{what}: overrides: expected a mapping of training options, got {value!r}")
            flat = {}
            for ok, ov in value.items():
                if ok in NESTED and isinstance(ov, dict):  # run.json's nested form
                    flat |= {f"{ok}.{k2}": v2 for k2, v2 in ov.items()}
                else:
                    flat[str(ok)] = ov
            for ok, ov in flat.items():
                o = flag(ok)[2:].replace("-", "_")  # run.json's names (noise.redraw) -> the options'
                if o in train_hints:
                    train[o] = from_json(train_hints[o], ov, f"overrides: {ok}", what)
                else:
                    raise ValueError(f"{what}: overrides: unknown training option {ok!r}")
        elif k in names:
            if isinstance(value, (str, int, float)) and typing.get_origin(typing.get_args(hints[k])[0]) is tuple:
                value = [value]  # one prompt or seed written without a list
            top[k] = from_json(hints[k], value, k, what)
        else:
            raise ValueError(f"{what}: unknown sweep option {key!r}; expected some of {sorted(names | {'overrides'})}")
    return command(**top, train=train_cls(**train))


def load_mapping(path: Path, what: str = "config") -> dict:
    """A YAML (.yaml, .yml) or JSON file's top-level mapping; errors name ``what`` and the file."""
    from gdbench.core.io import read_json

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what}: no file at {path}")
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            d = yaml.safe_load(path.read_text())
        except yaml.YAMLError as e:
            raise ValueError(f"{what}: {path} is not valid YAML ({str(e).splitlines()[0]})") from None
    else:
        d = read_json(path, what=what)
    if not isinstance(d, dict):
        raise ValueError(f"{what}: {path}: expected a mapping, got {type(d).__name__}")
    return d


def sweep_mapping(cmd) -> dict:
    """``cmd`` as the mapping ``sweep_from_mapping`` reads (what <out>/sweep.yaml holds)."""
    d = {}
    for f in fields(cmd):
        if f.name in ("config", "train"):
            continue
        v = getattr(cmd, f.name)
        d[f.name] = list(v) if isinstance(v, tuple) else (str(v) if isinstance(v, Path) else v)

    def plain(v):
        return list(v) if isinstance(v, tuple) else (str(v) if isinstance(v, Path) else v)

    over = {k: plain(v) for k, v in cmd.train.options().items()}  # by option name, as a user writes them
    if over:
        d["overrides"] = over
    return d


def run_sweep(cmd) -> dict:
    import yaml

    from gdbench.core.io import atomic_write, check_folder
    from gdbench.experiments.sweep import SweepConfig, sweep

    check_folder(cmd.out)
    text = yaml.safe_dump(sweep_mapping(cmd), sort_keys=False).encode()

    def record() -> None:  # once the grid is valid: a refused grid leaves nothing behind
        Path(cmd.out).mkdir(parents=True, exist_ok=True)
        atomic_write(Path(cmd.out) / "sweep.yaml", lambda f: f.write(text))

    per = {"janus": cmd.janus_presets, "instance": cmd.instance_presets}
    grid = SweepConfig(
        list(cmd.prompts),
        list(cmd.presets),
        list(cmd.seeds),
        steps=cmd.steps,
        out=cmd.out,
        executor=cmd.executor,
        address=cmd.address,
        workers=cmd.workers,
        colmap=cmd.colmap,
        colmap_views=cmd.colmap_views,
        overrides=cmd.train.overrides(),
        settings=list(cmd.settings),
        setting_presets={k: list(v) for k, v in per.items() if v},
        colmap_presets=list(cmd.colmap_presets) or None,
        colmap_settings=list(cmd.colmap_settings) or None,
        figures=cmd.figures,
    )
    rows = sweep(grid, on_valid=record)
    print((Path(cmd.out) / "summary.md").read_text())
    return {"cells": len(rows), "out": str(cmd.out)}


COMMANDS = {
    "generate": (GenerateBase, run_generate),
    "render": (Render, run_render),
    "compare": (Compare, run_compare),
    "demo": (Demo, run_demo),
    "noise": (Noise, run_noise),
    "score": (Score, run_score),
    "sweep": (SweepBase, run_sweep),
    "bench": (Bench, run_bench),
    "train-prior": (TrainPrior, run_train_prior),
    "view": (View, run_view),
    "export": (Export, run_export),
    "cache": (Cache, run_cache),
}
"""Subcommand name -> (its options, the function that runs them); generate's and sweep's options
are those of a --prior choice (``generate_command``, ``sweep_command``)."""


def one_paragraph_help(cls) -> type:
    """Each field's docstring as one paragraph of help (tyro keeps the line breaks of an indented
    docstring) with the default said once: by the docstring where it says it, else by tyro. An
    optional field's None is its default, not a value to type (``--out PATH``, not
    ``--out {None}|PATH``). The class's own annotations are kept."""
    import types
    import typing

    from gdbench.train.options import _field_docs

    docs = _field_docs(cls)
    hints = typing.get_type_hints(cls, include_extras=True)
    new = {}
    for name, hint in hints.items():
        marks = []
        inner = typing.get_args(hint)[0] if typing.get_origin(hint) is Annotated else hint
        if typing.get_origin(inner) in (typing.Union, types.UnionType) and type(None) in typing.get_args(inner):
            marks.append(tyro.conf.DisallowNone)
        if name in docs:
            said = "(default" in docs[name] or "(required" in docs[name]
            marks.append(tyro.conf.arg(help=docs[name], **({"help_behavior_hint": ""} if said else {})))
        new[name] = Annotated[(hint, *marks)] if marks else hint
    cls.__annotations__ = new
    return cls


for _kind, _ in COMMANDS.values():
    one_paragraph_help(_kind)


def main(cmd) -> dict:
    """Validate the whole command line against its declared ranges (``gdbench.core.constraints``),
    then run it: nothing is built, rendered or trained for a command that cannot run."""
    for _, (kind, run) in COMMANDS.items():
        if isinstance(cmd, kind):
            check_fields(cmd, nested=False)  # option groups (train, method) hold plain flags
            return run(cmd)
    raise TypeError(f"cmd: unknown command {type(cmd).__name__}")


def error_line(e: BaseException) -> tuple[str, int]:
    """(one-line message, exit code) for an error a user can act on; re-raises anything else.

    Exit code 2: bad arguments, missing or broken files, a busy or unwritable folder, a full
    disk, an optional dependency not installed (its message says what to install); 128 + the
    signal's number when a stop signal ended a run after it saved its checkpoint (130 Ctrl-C,
    143 SIGTERM, 129 SIGHUP)."""
    from gdbench.core.io import FolderBusy
    from gdbench.core.signals import RunInterrupted
    from gdbench.train.update import TrainingDiverged

    if isinstance(e, RunInterrupted):
        return str(e), e.exit_code
    if isinstance(e, TrainingDiverged):  # its message says what to try
        return str(e), 2
    if isinstance(e, KeyboardInterrupt):
        signum = getattr(e, "signum", signal.SIGINT)
        return f"interrupted by {signal.Signals(signum).name}", 128 + signum
    if isinstance(e, (ValueError, FolderBusy, FileNotFoundError, FileExistsError, NotADirectoryError)):
        return str(e), 2
    if isinstance(e, ImportError) and "pip install" in str(e):  # an optional part, and what installs it
        return str(e), 2
    if isinstance(e, OSError):  # read-only file system, permission, disk full, ...
        where = f"{e.filename}: " if e.filename else ""
        return f"{where}{e.strerror or e}", 2
    raise e


def run_reporting(name: str, work) -> None:
    """``work()`` under ``install_stop_handlers``; an error a user can act on, or a stop signal,
    ends the process with one line (``gdbench <name>: error: ...``) and its exit code
    (``error_line``). The signal handlers it found are given back when it ends (a caller that
    catches the SystemExit, such as a test, keeps its own)."""
    import os
    import sys

    stops = [getattr(signal, s) for s in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, s)]
    saved = {s: signal.getsignal(s) for s in stops}
    try:
        try:
            from gdbench.core.signals import install_stop_handlers

            install_stop_handlers()  # inside the try: a signal from here on is reported in one line
            work()
        except (Exception, KeyboardInterrupt) as e:
            for s in stops:  # a second signal must not cut the one line short
                signal.signal(s, signal.SIG_IGN)
            if os.environ.get("GDBENCH_DEBUG"):
                raise
            message, code = error_line(e)
            print(f"gdbench {name}: error: {message}", file=sys.stderr)
            sys.exit(code)
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)


def _config_arg(argv: list[str]) -> tuple[Path, list[str]] | None:
    """(--config's path, the other arguments after the subcommand) when ``argv`` has --config;
    given twice, a ValueError."""
    rest = argv[1:]
    found = [i for i, a in enumerate(rest) if a == "--config" or a.startswith("--config=")]
    if len(found) > 1:
        raise ValueError("config: given more than once; expected one grid file")
    if not found:
        return None
    i = found[0]
    if rest[i].startswith("--config="):
        return Path(rest[i].split("=", 1)[1]), rest[:i] + rest[i + 1 :]
    if i + 1 < len(rest):
        return Path(rest[i + 1]), rest[:i] + rest[i + 2 :]
    return None  # tyro names the missing value


def entrypoint() -> None:
    """Parse the command line and run it. Bad arguments, missing or broken files and unwritable
    folders end with a one-line error naming what to fix and exit code 2. A stop signal (Ctrl-C,
    SIGTERM, SIGHUP) ends the command with one line and exit code 128 + its number; during
    training, after the step it lands in and a checkpoint. Set GDBENCH_DEBUG=1 for the traceback."""
    import sys

    argv = sys.argv[1:]
    if hasattr(sys.stdout, "reconfigure"):  # piped to a file: each line as it is printed
        sys.stdout.reconfigure(line_buffering=True)
    try:
        config = _config_arg(argv) if argv[:1] == ["sweep"] else None
    except ValueError as e:
        print(f"gdbench sweep: error: {e}", file=sys.stderr)
        sys.exit(2)
    prior = None
    if argv[:1] in (["generate"], ["sweep"]):
        try:
            prior = chosen_prior(argv)
        except ValueError as e:
            print(f"gdbench {argv[0]}: error: {e}", file=sys.stderr)
            sys.exit(2)
    if config is not None:  # the file's options become the defaults the command line overrides

        def with_config() -> None:  # read under run_reporting: a bad file is one line, as any error
            path, rest = config
            default = sweep_from_mapping(load_mapping(path), what=f"config ({path})", prior=prior)
            cmd = tyro.cli(type(default), default=default, args=rest, prog="gdbench sweep")
            cmd.config = path
            main(cmd)

        run_reporting("sweep", with_config)
        return
    cmd = tyro.extras.subcommand_cli_from_dict({name: command(name, prior or "empirical") for name in COMMANDS})
    name = next(n for n, (kind, _) in COMMANDS.items() if isinstance(cmd, kind))
    run_reporting(name, lambda: main(cmd))


def command(name: str, prior: str = "empirical") -> type:
    """The options class of subcommand ``name``; generate's and sweep's with ``prior``'s options."""
    if name == "generate":
        return generate_command(prior)
    if name == "sweep":
        return sweep_command(prior)
    return COMMANDS[name][0]


def chosen_prior(argv: list[str]) -> str:
    """The --prior of a generate or sweep command line (``argv`` from the subcommand on): given,
    else the one its --config file names, else 'empirical'; a bad name is left to the parser. A
    prior's option typed for another prior is a ValueError naming the prior it needs."""
    from gdbench.train.config import PRIOR_KEYS

    rest = argv[1:]
    kind = None
    for i, a in enumerate(rest):
        if a == "--prior" and i + 1 < len(rest):
            kind = rest[i + 1]
        elif a.startswith("--prior="):
            kind = a.split("=", 1)[1]
    if kind is None:
        kind = _file_prior(argv)
    kind = kind if kind in PRIOR_CONFIGS else "empirical"
    for a in rest:
        if a == "--":
            break
        name = a.split("=", 1)[0].removeprefix("--").removeprefix("no-").replace("-", "_")
        if a.startswith("--") and name in PRIOR_KEYS and kind not in PRIOR_KEYS[name]:
            raise ValueError(f"{a.split('=', 1)[0]} acts only with --prior {' or '.join(PRIOR_KEYS[name])} "
                             f"(this command: --prior {kind})")  # fmt: skip
    return kind


def _file_prior(argv: list[str]) -> str | None:
    """The prior a generate or sweep --config file names (a run.json's config, a settings file,
    a sweep's overrides), or None; a file that cannot be read is left to the command to report."""
    try:
        found = _config_arg(argv)
        if found is None:
            return None
        d = load_mapping(found[0])
    except Exception:  # (the command reads the file again and names what is wrong)
        return None
    d = d.get("config", d) if "run_id" in d else d
    d = d.get("overrides", d) if argv[0] == "sweep" else d
    prior = d.get("prior") if isinstance(d, dict) else None
    prior = prior.get("kind") if isinstance(prior, dict) else prior
    return prior if isinstance(prior, str) else None


def program() -> None:
    """The ``gdbench`` command and ``python -m gdbench.app.cli``: ``entrypoint``, then the process
    ends without Python's teardown of its modules, most of the exit's time once torch is imported
    (docs/log/2026-11-26_cell_cost.md, "The command's exit"). What an exit owes still happens,
    in the order Python does it: ``threading._shutdown``
    (executors' exit hooks, then the threads that are not daemons joined), the exit handlers
    (logging's flush, the finalizers of temporary folders, multiprocessing), both streams flushed
    (a failed flush exits 120, as Python does), and the exit code is the one ``sys.exit`` gives.
    An error that escapes (``GDBENCH_DEBUG=1``) takes Python's own way out, traceback and all."""
    import os
    import sys

    from gdbench.core.private import run_exit_functions, shutdown_threads

    try:
        entrypoint()
        code = 0
    except SystemExit as e:
        code = exit_code(e.code)
    shutdown_threads()  # Python's own first step: wakes executors' workers, joins non-daemon threads
    run_exit_functions()
    for stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        try:
            if stream is not None:
                stream.flush()
        except Exception:
            code = code or 120  # as Python does when its streams cannot be flushed at exit
    os._exit(code)


def exit_code(code) -> int:
    """The exit status ``SystemExit(code)`` gives a Python process: None is 0, an integer itself,
    anything else is written to standard error and gives 1."""
    import sys

    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


if __name__ == "__main__":
    program()
