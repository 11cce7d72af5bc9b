"""The ``gdbench`` command line. ``main(cmd)`` does the work and is tested; ``entrypoint``
only parses arguments with tyro."""

from __future__ import annotations

import signal
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Literal

import tyro

from .constraints import AtLeast, Between, Positive, Seed, check_fields
from .train.config import BASE_PRESETS, PRESETS
from .train.options import method_options, train_options


@dataclass
class Demo:
    """Render the built-in scene as a turntable (GIF, MP4, contact sheet) and print timings."""

    out: Path = Path("runs/demo")
    """Output folder."""
    frames: Annotated[int, AtLeast(1)] = 36
    """Views on the orbit (360/frames degrees apart)."""
    size: Annotated[int, AtLeast(8, "px")] = 256
    """Image width and height in pixels."""
    gaussians: Annotated[int, AtLeast(10)] = 3000
    """Number of Gaussians in the built-in scene."""
    seed: Annotated[int, Seed()] = 0
    """Seed of the built-in scene."""


def run_demo(cmd: Demo) -> dict:
    from .resources import check_render_memory
    from .turntable import demo

    check_render_memory(cmd.size, cmd.frames, gaussians=cmd.gaussians)

    return demo(cmd.out, frames=cmd.frames, size=cmd.size, gaussians=cmd.gaussians, seed=cmd.seed)


@dataclass
class Noise:
    """Structured noise tools: ``--preview`` writes 4 views of one noise source and the
    per-pixel histogram against N(0, 1)."""

    preview: bool = False
    """Write the preview figure."""
    out: Path = Path("runs/noise_preview.png")
    """Where the preview goes: a .png file, or a folder (existing, or a path without a suffix)
    that receives noise_preview.png."""
    res: Annotated[int, AtLeast(8, "px")] = 128
    """Resolution of the views."""
    seed: Annotated[int, Seed()] = 0
    n_gaussians: Annotated[int, AtLeast(1)] = 3072
    """Noise Gaussians in the cloud."""
    scale: Annotated[float, Positive()] = 0.02
    """Their isotropic scale."""


def run_noise(cmd: Noise) -> dict:
    from .noise import NoiseConfig
    from .noise_preview import preview
    from .resources import check_noise_memory

    if not cmd.preview:
        raise ValueError("preview: nothing to do; pass --preview to write the preview figure")
    out = Path(cmd.out)
    if out.is_dir() or not out.suffix:
        out = out / "noise_preview.png"
    elif out.suffix.lower() != ".png":
        raise ValueError(f"out: expected a .png file or a folder, got {cmd.out}")
    check_noise_memory(cmd.res, cmd.n_gaussians)
    stats = preview(out, NoiseConfig(n_gaussians=cmd.n_gaussians, scale=cmd.scale), res=cmd.res, seed=cmd.seed)
    print(
        f"wrote {stats['path']}: coverage {stats['coverage']:.2f}, per-pixel mean {stats['mean']:+.3f}, "
        f"variance {stats['var']:.3f}, KS distance to N(0,1) {stats['ks_statistic']:.4f}, "
        f"correlation length {stats['correlation_length_px']:.1f} px"
    )
    print(
        "  noise shared with the view at azimuth 0 (mean best-pixel correlation): "
        + ", ".join(f"{v:.2f} at {a} deg" for a, v in stats["view_coupling"].items() if a != "0")
    )
    return stats


MethodOptions = method_options()
"""The nested settings' overrides (the noise's redraw and mixing, the densification schedule)."""
PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]
"""The presets' names, from the one place they are defined (train/config.py)."""
GenerateTrain = train_options(("prompt", "preset", "out", "progress"))
"""Every other TrainConfig field as an optional override of the preset."""


@dataclass
class Generate:
    """Text to a 3D Gaussian scene: score distillation on the embedded CPU prior (or the learned
    prior with --prior learned, Stable Diffusion with --prior sd).

    Writes scene.ply, turntable.{gif,mp4}, turntable_sheet.png, curves.png, run.json and a
    checkpoint to --out; an interrupted run resumes from its checkpoint. Every training setting
    is an option; unset ones keep the preset's value (docs/training.md)."""

    prompt: tyro.conf.Positional[str]
    """What to generate: one of the built-in assets' captions or a paraphrase of one."""
    preset: PresetName = "gd"
    """gd: structured noise + VGS (the paper); the others are its ablations and baselines."""
    out: Path = Path("runs/duck")
    """The run folder."""
    resume: bool = True
    """Continue from --out's checkpoint if there is one."""
    overwrite: bool = False
    """Replace a finished run in --out (its outputs are deleted first)."""
    score: bool = True
    """Score the result against the asset (PSNR/SSIM and view metrics) into scores.json."""
    progress: bool = True
    """Show a progress bar."""
    train: tyro.conf.OmitArgPrefixes[GenerateTrain] = field(default_factory=GenerateTrain)
    method: tyro.conf.OmitArgPrefixes[MethodOptions] = field(default_factory=MethodOptions)


@dataclass
class Render:
    """Turntable (GIF, MP4, contact sheet) of a run folder or of any 3DGS PLY file."""

    run: tyro.conf.Positional[Path]
    """A run folder (its scene.ply is used) or a .ply file."""
    out: Path | None = None
    """Output folder (default: the run folder, or the PLY's folder)."""
    frames: Annotated[int, AtLeast(1)] = 36
    size: Annotated[int, AtLeast(8, "px")] = 256
    radius: Annotated[float, Positive()] = 1.3
    elevation: Annotated[float, Between(-90, 90, unit="degrees")] = 15.0
    fovy: Annotated[float, Between(1, 179, unit="degrees")] = 45.0


def run_generate(cmd: Generate) -> dict:
    from .resources import check_generate_memory
    from .train.config import preset
    from .train.options import inert_options
    from .train.run import train

    overrides = cmd.train.overrides() | cmd.method.overrides()
    cfg = preset(cmd.preset, prompt=cmd.prompt, out=cmd.out, progress=cmd.progress, **overrides)
    inert = inert_options(cfg, overrides)
    if inert:
        raise ValueError("; ".join(inert) + ": drop the option, or set the one it needs")
    check_generate_memory(cfg)
    r = train(cfg, resume=cmd.resume, overwrite=cmd.overwrite)
    summary = r.summary()
    if cmd.score and r.caption is not None and r.state.step >= cfg.steps:
        from .metrics.run_scores import score_run

        summary["gt"] = score_run(cmd.out, gt=True, colmap=False)["gt"]
    print(r.report(summary))
    return summary


def run_render(cmd: Render) -> dict:
    import contextlib

    from .io import FolderLock
    from .resources import check_render_memory
    from .scene import GaussianScene
    from .turntable import write_turntable

    src = Path(cmd.run)
    ply = src / "scene.ply" if src.is_dir() else src
    if not ply.is_file():
        raise FileNotFoundError(f"run: no PLY at {ply} (pass a run folder or a .ply file)")
    check_render_memory(cmd.size, cmd.frames)
    out = Path(cmd.out or ply.parent)
    # a run folder has one writer: not while a generate (--overwrite) or score writes there
    run_folder = (out / "run.json").is_file() or (out / FolderLock.NAME).is_file()
    with FolderLock(out) if run_folder else contextlib.nullcontext():
        scene = GaussianScene.load_ply(ply)
        res = write_turntable(
            scene,
            out,
            frames=cmd.frames,
            size=cmd.size,
            radius=cmd.radius,
            elevation=cmd.elevation,
            fovy=cmd.fovy,
            stem=ply.stem + "_turntable",
        )
    print(
        f"gdbench render: {len(scene)} Gaussians, {cmd.frames} frames at {cmd.size}px, "
        f"median {1e3 * sorted(res.seconds_per_frame)[cmd.frames // 2]:.1f} ms per frame"
    )
    for k, v in res.paths.items():
        print(f"  {k:5s} -> {v}")
    return {k: str(v) for k, v in res.paths.items()}


@dataclass
class Compare:
    """Run every applicable renderer on fixture scenes; write error-against-time rows (CSV/JSON),
    error maps and a Pareto plot per scene, and print the table."""

    scene: str = "all"
    """A fixture name (fixtures/scenes/*.json) or 'all'."""
    out: Path = Path("runs/compare")
    backends: tuple[str, ...] = ()
    """Only these renderers (default: all); the float64 reference always runs."""


def run_compare(cmd: Compare) -> dict:
    from .compare import run

    results = run(cmd.scene, backends=list(cmd.backends) or None, out=cmd.out)
    return {k: {"rows": len(v.rows), "skipped": len(v.skipped)} for k, v in results.items()}


@dataclass
class Score:
    """Score a finished run folder: GT PSNR/SSIM against the asset and COLMAP consistency
    (registration rate, Var(theta), translation-direction error), written to its scores.json.
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


def run_score(cmd: Score) -> dict:
    from .metrics.run_scores import report, score_run
    from .resources import check_score_memory

    if not Path(cmd.run).is_dir():
        raise FileNotFoundError(f"run: expected a run folder, got {cmd.run}")
    if cmd.colmap:
        check_score_memory(cmd.size, cmd.views)
    s = score_run(cmd.run, gt=cmd.gt, colmap=cmd.colmap, views=cmd.views, size=cmd.size)
    print(report(s))
    return s


SweepTrain = train_options(("prompt", "preset", "out", "progress", "seed", "steps", "log_every"))
"""Every other TrainConfig field as an override of every cell (cells run without a progress bar,
so --log-every has no place here)."""


@dataclass
class Sweep:
    """Train and score every (setting, prompt, preset, seed) cell; write cells.csv, summary.csv,
    summary.md, verdict.csv (the paper's claims over (prompt, seed) pairs: BCa intervals,
    signed-rank p-values Holm-adjusted, equivalence tests, power, per-prompt effects) and
    ablation.png. Resumable: finished cells (scored by the same code) are skipped, an
    interrupted cell resumes from its checkpoint. The grid is validated before the first cell."""

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
    train: tyro.conf.OmitArgPrefixes[SweepTrain] = field(default_factory=SweepTrain)
    """Overrides applied to every cell (after its setting's)."""
    method: tyro.conf.OmitArgPrefixes[MethodOptions] = field(default_factory=MethodOptions)


def run_sweep(cmd: Sweep) -> dict:
    from .sweep import sweep

    per = {"janus": cmd.janus_presets, "instance": cmd.instance_presets}
    rows = sweep(
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
        overrides=cmd.train.overrides() | cmd.method.overrides(),
        settings=list(cmd.settings),
        setting_presets={k: list(v) for k, v in per.items() if v},
        colmap_presets=list(cmd.colmap_presets) or None,
        colmap_settings=list(cmd.colmap_settings) or None,
    )
    print((Path(cmd.out) / "summary.md").read_text())
    return {"cells": len(rows), "out": str(cmd.out)}


BENCHES = {
    "render": ("gdbench.bench.bm_render", "render.csv", []),
    "peers": ("gdbench.bench.bm_render", "peers.csv", ["--peers"]),
    "error": ("gdbench.bench.bm_error", "error_vs_runtime.csv", []),
    "stability": ("gdbench.bench.bm_stability", "stability.csv", []),
    "noise": ("gdbench.bench.bm_noise", "noise.csv", []),
    "train": ("gdbench.bench.bm_train", "train.csv", []),
    "scale": ("gdbench.bench.bm_scale", "scale.csv", []),
}
"""Benchmark name -> (module, CSV name, extra arguments)."""


@dataclass
class Bench:
    """Benchmarks; each writes a CSV with a JSON summary (and a plot or table) to --out.

    render: splat vs the dense all-pairs path over N and resolution (speed, memory);
    peers: splat vs gsplat_torch vs Mitsuba ellipsoids (target: splat forward >= 10x gsplat at
    10k Gaussians, 256 px, same run); error: error against run time over all fixtures (Pareto);
    stability: stiff and extreme cases on every renderer; noise: structured-noise share of a
    training step; train: denoiser, full-run and per-step timings; scale: 1M Gaussians with SH
    degree 3 at 1920x1080 (time and peak memory)."""

    which: tyro.conf.Positional[Literal["render", "peers", "error", "stability", "noise", "train", "scale"]]
    out: Path = Path("bench_results")
    """Folder for the CSV/JSON/plots."""
    quick: bool = False
    """Small grid (render and peers only; render's cases all in this process, so its peak memory
    is not per case): a smoke run, not numbers to publish."""


def run_bench(cmd: Bench) -> dict:
    import importlib

    module, csv_name, extra = BENCHES[cmd.which]
    argv = ["--out", str(Path(cmd.out) / csv_name), *extra]
    if cmd.quick:
        if cmd.which not in ("render", "peers"):
            raise ValueError(f"quick: only render and peers have a quick grid, not {cmd.which!r}")
        argv += ["--quick"] + (["--inprocess"] if cmd.which == "render" else [])
    code = importlib.import_module(module).main(argv)
    return {"bench": cmd.which, "csv": str(Path(cmd.out) / csv_name), "exit": code}


@dataclass
class TrainPrior:
    """Train the learned prior: a small conditional diffusion model of the built-in assets
    (docs/learned_prior.md). Renders its data on first use (cached), checkpoints and resumes in
    --out, and writes model.safetensors (use it with generate --prior learned --learned-model OUT),
    loss.csv and loss.png."""

    out: Path = Path("runs/prior")
    """The run folder (reused with the same settings: the run resumes)."""
    front_bias: Annotated[float, AtLeast(0)] = 0.0
    """kappa: training views drawn with probability ~ exp(kappa cos azimuth) (the shipped 'front'
    model: 2)."""
    steps: Annotated[int, AtLeast(1)] = 8000
    batch: Annotated[int, AtLeast(1)] = 32
    lr: Annotated[float, Positive()] = 6e-4
    """Peak learning rate (AdamW; warm-up, then cosine decay to a tenth)."""
    seed: Annotated[int, Seed()] = 0
    size: Annotated[int, AtLeast(8, "px")] = 32
    """The model's resolution (a divisor of --resolution; the 64 px renders are box-filtered to it)."""
    views: Annotated[int, AtLeast(1)] = 1024
    """Rendered cameras per (asset, variant)."""
    resolution: Annotated[int, AtLeast(8, "px")] = 64
    """Resolution the data is rendered at."""
    threads: Annotated[int, AtLeast(0)] = 0
    """torch CPU threads (0: torch's default); a result reproduces for one thread count."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    progress: bool = True


def run_train_prior(cmd: TrainPrior) -> dict:
    from .priors.learned_data import DataConfig
    from .priors.learned_train import PriorTrainConfig, train_prior
    from .priors.unet import UNetConfig

    cfg = PriorTrainConfig(
        out=cmd.out, front_bias=cmd.front_bias, steps=cmd.steps, batch=cmd.batch, lr=cmd.lr, seed=cmd.seed,
        threads=cmd.threads, device=cmd.device, progress=cmd.progress, unet=UNetConfig(size=cmd.size),
        data=DataConfig(views=cmd.views, resolution=cmd.resolution),
    )  # fmt: skip
    return train_prior(cfg)


COMMANDS = {
    "generate": (Generate, run_generate),
    "render": (Render, run_render),
    "compare": (Compare, run_compare),
    "demo": (Demo, run_demo),
    "noise": (Noise, run_noise),
    "score": (Score, run_score),
    "sweep": (Sweep, run_sweep),
    "bench": (Bench, run_bench),
    "train-prior": (TrainPrior, run_train_prior),
}
"""Subcommand name -> (its options, the function that runs them)."""


def main(cmd) -> dict:
    """Validate the whole command line against its declared ranges (``gdbench.constraints``),
    then run it: nothing is built, rendered or trained for a command that cannot run."""
    for _, (kind, run) in COMMANDS.items():
        if type(cmd) is kind:
            check_fields(cmd, nested=False)  # option groups (train, method) hold plain flags
            return run(cmd)
    raise TypeError(f"cmd: unknown command {type(cmd).__name__}")


def error_line(e: BaseException) -> tuple[str, int]:
    """(one-line message, exit code) for an error a user can act on; re-raises anything else.

    Exit code 2: bad arguments, missing or broken files, a busy or unwritable folder, a full
    disk; 128 + the signal's number when a stop signal ended a run after it saved its checkpoint
    (130 Ctrl-C, 143 SIGTERM, 129 SIGHUP)."""
    from .io import FolderBusy
    from .train.run import RunInterrupted
    from .train.update import TrainingDiverged

    if isinstance(e, RunInterrupted):
        return str(e), e.exit_code
    if isinstance(e, TrainingDiverged):  # its message says what to try
        return str(e), 2
    if isinstance(e, KeyboardInterrupt):
        signum = getattr(e, "signum", signal.SIGINT)
        return f"interrupted by {signal.Signals(signum).name}", 128 + signum
    if isinstance(e, (ValueError, FolderBusy, FileNotFoundError, FileExistsError, NotADirectoryError)):
        return str(e), 2
    if isinstance(e, OSError):  # read-only file system, permission, disk full, ...
        where = f"{e.filename}: " if e.filename else ""
        return f"{where}{e.strerror or e}", 2
    raise e


class Stopped(KeyboardInterrupt):
    """SIGTERM or SIGHUP outside a training loop: raised like Ctrl-C's KeyboardInterrupt, so files
    being written are removed (``io.atomic_write``) and the command ends with one line."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)


def _stop(signum, _frame):
    raise Stopped(signum)


def install_stop_handlers() -> None:
    """SIGTERM and SIGHUP raise ``Stopped`` (as Ctrl-C raises KeyboardInterrupt); a training loop
    defers all three to the end of its step (``train.run.defer_stop_signals``)."""
    for s in (getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)):
        if signal.getsignal(s) is not signal.SIG_IGN:  # nohup's ignored SIGHUP stays ignored
            signal.signal(s, _stop)


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


def entrypoint() -> None:
    """Parse the command line and run it. Bad arguments, missing or broken files and unwritable
    folders end with a one-line error naming what to fix and exit code 2. A stop signal (Ctrl-C,
    SIGTERM, SIGHUP) ends the command with one line and exit code 128 + its number; during
    training, after the step it lands in and a checkpoint. Set GDBENCH_DEBUG=1 for the traceback."""
    cmd = tyro.extras.subcommand_cli_from_dict({name: kind for name, (kind, _) in COMMANDS.items()})
    name = next(n for n, (kind, _) in COMMANDS.items() if type(cmd) is kind)
    run_reporting(name, lambda: main(cmd))


if __name__ == "__main__":
    entrypoint()
