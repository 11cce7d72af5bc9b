"""The commands beside the main ones (``generate``, ``render``, ``score``, ``sweep``: gdbench.app.cli):
the demo, noise preview, renderer comparison, benchmarks, the learned prior's training and the
cache. Each is an options dataclass (its field docstrings are the help) and a ``run_*`` function."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from gdbench.core.constraints import AtLeast, Between, Positive, Seed


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
    from gdbench.app.resources import check_render_memory
    from gdbench.core.turntable import demo

    check_render_memory(cmd.size, cmd.frames, gaussians=cmd.gaussians)

    return demo(cmd.out, frames=cmd.frames, size=cmd.size, gaussians=cmd.gaussians, seed=cmd.seed)


@dataclass
class Noise:
    """Structured noise tools: --preview writes 4 views of one noise source and the
    per-pixel histogram against N(0, 1)."""

    preview: bool = False
    """Write the preview figure."""
    out: Path = Path("runs/noise_preview.png")
    """Where the preview goes: a .png file, or a folder (existing, or a path without a suffix)
    that receives noise_preview.png."""
    res: Annotated[int, AtLeast(8, "px")] = 128
    """Resolution of the views."""
    seed: Annotated[int, Seed()] = 0
    """Seed of the noise cloud (positions and colours)."""
    n_gaussians: Annotated[int, AtLeast(1)] = 3072
    """Noise Gaussians in the cloud."""
    scale: Annotated[float, Positive()] = 0.02
    """Their isotropic scale."""


def run_noise(cmd: Noise) -> dict:
    from gdbench.app.noise_preview import preview
    from gdbench.app.resources import check_noise_memory
    from gdbench.mechanisms.noise import NoiseConfig

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


@dataclass
class Compare:
    """Run every applicable renderer on fixture scenes; write error-against-time rows (CSV/JSON),
    error maps and a Pareto plot per scene, and print the table."""

    scene: str = "all"
    """A fixture name (fixtures/scenes/*.json) or 'all'."""
    out: Path = Path("runs/compare")
    """Folder for compare.csv/json, the error maps and the Pareto plots."""
    backends: tuple[str, ...] = ()
    """Only these renderers (default: all); the float64 reference always runs."""


def run_compare(cmd: Compare) -> dict:
    from gdbench.refcheck.compare import run

    results = run(cmd.scene, backends=list(cmd.backends) or None, out=cmd.out)
    return {k: {"rows": len(v.rows), "skipped": len(v.skipped)} for k, v in results.items()}


BENCHES = {
    "render": ("gdbench.refcheck.bm_render", "render.csv", []),
    "peers": ("gdbench.refcheck.bm_render", "peers.csv", ["--peers"]),
    "error": ("gdbench.refcheck.bm_error", "error_vs_runtime.csv", []),
    "stability": ("gdbench.refcheck.bm_stability", "stability.csv", []),
    "noise": ("gdbench.bench.bm_noise", "noise.csv", []),
    "train": ("gdbench.bench.bm_train", "train.csv", []),
    "scale": ("gdbench.bench.bm_scale", "scale.csv", []),
    "cell": ("gdbench.bench.bm_cell", "cell.csv", []),
    "cuda": ("gdbench.refcheck.bm_cuda", "cuda", []),
}
"""Benchmark name -> (module, CSV name (a folder for cuda), extra arguments)."""


@dataclass
class Bench:
    """Benchmarks; each writes a CSV with a JSON summary (and a plot or table) to --out.

    render: splat vs the dense all-pairs path over N and resolution (speed, memory);
    peers: splat vs gsplat_torch vs Mitsuba ellipsoids (target: splat forward >= 10x gsplat at
    10k Gaussians, 256 px, same run); error: error against run time over all fixtures (Pareto);
    stability: stiff and extreme cases on every renderer; noise: structured-noise share of a
    training step; train: denoiser, full-run and per-step timings; scale: 1M Gaussians with SH
    degree 3 at 1920x1080 (time and peak memory); cell: one scored 1000-step sweep cell in a fresh
    process and its phases, COLMAP on its scene, a cold first run (the module gdbench.bench.bm_cell
    run with a peer checkout compares two versions of the code in one run); cuda: on a GPU, the
    renderer on CUDA (the gsplat backend, the torch path) against gsplat itself and the C++
    compositor (agreement, speed), the training step on both devices, and the C++ compositor's
    scaling with CPU threads (only that part without a GPU)."""

    which: tyro.conf.Positional[
        Literal["render", "peers", "error", "stability", "noise", "train", "scale", "cell", "cuda"]
    ]
    """The benchmark (above)."""
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
    """Optimiser steps."""
    batch: Annotated[int, AtLeast(1)] = 32
    """Images per step."""
    lr: Annotated[float, Positive()] = 6e-4
    """Peak learning rate (AdamW; warm-up, then cosine decay to a tenth)."""
    seed: Annotated[int, Seed()] = 0
    """Seed of the initial weights, the batches and the noise."""
    size: Annotated[int, AtLeast(8, "px")] = 32
    """The model's resolution (a divisor of --resolution; the 64 px renders are box-filtered to it)."""
    views: Annotated[int, AtLeast(1)] = 1024
    """Rendered cameras per (asset, variant)."""
    resolution: Annotated[int, AtLeast(8, "px")] = 64
    """Resolution the data is rendered at."""
    threads: Annotated[int, AtLeast(0)] = 0
    """torch CPU threads (0: torch's default); a result reproduces for one thread count."""
    device: Literal["auto", "cpu", "cuda"] = "auto"
    """Where the model trains (auto: CUDA when present)."""
    progress: bool = True
    """Report progress (a bar on a terminal, a line every few seconds in a log)."""


def run_train_prior(cmd: TrainPrior) -> dict:
    from gdbench.priors.learned.data import DataConfig
    from gdbench.priors.learned.training import PriorTrainConfig, train_prior
    from gdbench.priors.learned.unet import UNetConfig

    cfg = PriorTrainConfig(
        out=cmd.out, front_bias=cmd.front_bias, steps=cmd.steps, batch=cmd.batch, lr=cmd.lr, seed=cmd.seed,
        threads=cmd.threads, device=cmd.device, progress=cmd.progress, unet=UNetConfig(size=cmd.size),
        data=DataConfig(views=cmd.views, resolution=cmd.resolution),
    )  # fmt: skip
    return train_prior(cfg)


@dataclass
class Cache:
    """What gdbench caches on disk (prompts' image banks, calibration scenes, the learned prior's
    data, the compiled compositor), under $GDBENCH_CACHE or ~/.cache/gdbench: list it, clear it
    (all of it is rebuilt when next needed) or build the assets' banks ahead of their first run
    (scripts/setup.sh does so in the background)."""

    action: tyro.conf.Positional[Literal["list", "clear", "build"]]
    """list: the cache's folder, each part's size and age; clear: remove it (or --kinds); build:
    the banks and scoring references a default run of each of --prompts needs (16-45 s each when
    missing, nothing when present)."""
    kinds: tuple[Literal["banks", "fixtures", "learned_data", "clip_tokenizer", "ext"], ...] = ()
    """clear: only these parts (default: all of gdbench's)."""
    prompts: tuple[str, ...] = ()
    """build: prompts (or asset captions) to build for (default: every asset, the duck last)."""


def run_cache(cmd: Cache) -> dict:
    from gdbench.core import cache

    if cmd.action != "clear" and cmd.kinds:
        raise ValueError(f"kinds: only for clear, not {cmd.action} (list shows every part, build builds banks)")
    if cmd.action != "build" and cmd.prompts:
        raise ValueError("prompts: only for build")
    if cmd.action == "build":
        from gdbench.app.prebuild import build

        built = build(list(cmd.prompts) or None)
        return {"root": str(cache.root()), "built": built}
    if cmd.action == "clear":
        files, size = cache.clear(list(cmd.kinds) or None)
        print(f"gdbench cache: removed {files} files ({cache.human(size)}) from {cache.root()}")
    print(cache.listing())
    return {"root": str(cache.root()), "entries": {e.kind: e.bytes for e in cache.entries()}}


@dataclass
class Export:
    """Write a run's scene (or any scene file) for other viewers and editors: the Inria 3DGS PLY
    (padded to an SH degree for Inria's loader), antimatter15's .splat (web viewers) or
    SuperSplat's compressed PLY; rotated so the viewer's up axis is up (docs/export.md)."""

    src: tyro.conf.Positional[Path]
    """A run folder (its scene.ply), a PLY (3DGS or compressed) or a .splat file."""
    format: Literal["ply", "splat", "ply-compressed"] = "ply"
    """ply: exact float32, read by Inria's code and most tools; splat: 32 bytes per Gaussian, DC
    colour only; ply-compressed: about 16 bytes per Gaussian plus SH bands at 8 bits."""
    up: Literal["+z", "-y", "+y"] = "-y"
    """The axis that is up in the file: -y for Inria/COLMAP-convention viewers (SuperSplat, the
    .splat viewers), +y, or +z (gdbench's own)."""
    sh_degree: Annotated[int | None, Between(0, 3)] = None
    """SH degree written (ply, ply-compressed): higher pads with zeros (Inria's loader at degree
    3 wants all 45 f_rest_* properties), lower drops view-dependent colour (default: the scene's)."""
    out: Path | None = None
    """The file written (default: beside the source, named by the up axis: scene.y_down.ply,
    scene.y_down.splat, scene.z_up.compressed.ply, ...)."""
    src_up: Literal["+z", "-y", "+y"] = "+z"
    """The up axis of the source file (+z for gdbench's runs)."""


def run_export(cmd: Export) -> dict:
    from gdbench.app.export import export_scene, load_scene

    src = Path(cmd.src)
    path = src / "scene.ply" if src.is_dir() else src
    if not path.is_file():
        raise FileNotFoundError(f"src: no scene at {path} (pass a run folder, a .ply or a .splat file)")
    stem = path.name.removesuffix(".compressed.ply").removesuffix(".ply").removesuffix(".splat")
    tag = {"+z": "z_up", "-y": "y_down", "+y": "y_up"}[cmd.up]
    suffix = {"ply": ".ply", "splat": ".splat", "ply-compressed": ".compressed.ply"}[cmd.format]
    out = Path(cmd.out) if cmd.out is not None else path.parent / f"{stem}.{tag}{suffix}"
    if out.resolve() == path.resolve():
        raise ValueError(f"out: {out} is the source file; pass another --out")
    scene = load_scene(path, up=cmd.src_up)
    if cmd.format == "splat" and scene.sh.shape[1] > 1:
        print(f"gdbench export: note: .splat holds the DC colour only; SH degree {scene.sh_degree} dropped")
    written = export_scene(scene, out, fmt=cmd.format, up=cmd.up, sh_degree=cmd.sh_degree)
    size = written.stat().st_size
    print(f"gdbench export: {len(scene)} Gaussians -> {written} ({cmd.format}, {cmd.up} up, {size / 1e6:.2f} MB)")
    return {"path": str(written), "bytes": size, "gaussians": len(scene)}


@dataclass
class View:
    """Interactive viewer of a run folder or any scene file in the browser (viser): the splats,
    the run's turntable cameras on a slider and its training-view frustums (docs/viewer.md).
    Serves until Ctrl-C."""

    run: tyro.conf.Positional[Path]
    """A run folder (its scene.ply, and run.json for the turntable and training views) or a scene
    file (3DGS or compressed PLY, .splat)."""
    port: Annotated[int, Between(1, 65535)] = 8080
    """Port to serve on (viser takes the next free one when it is busy)."""
    host: str = "127.0.0.1"
    """Interface to listen on (0.0.0.0: every interface; default: this machine only)."""
    up: Literal["+z", "-z", "+y", "-y", "+x", "-x"] = "+z"
    """The scene's up direction (gdbench's runs: +z; Inria/COLMAP captures: -y)."""
    frustums: bool = False
    """Show the run's training-view frustums at start (a checkbox toggles them)."""


def run_view(cmd: View) -> dict:
    from gdbench.app.viewer import serve

    v = serve(cmd.run, host=cmd.host, port=cmd.port, up=cmd.up, frustums=cmd.frustums)  # until Ctrl-C
    return {"url": v.url}
