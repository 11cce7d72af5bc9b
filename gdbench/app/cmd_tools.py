"""The small commands: ``demo`` (the built-in scene's turntable), ``noise`` (a preview of the
structured noise), ``train-prior`` (the learned prior's weights), ``train-judge`` (the Janus judge's
weights), ``cache`` (the cache folder) and ``prompts`` (the captions the priors know)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from gdbench.core.constraints import AtLeast, Positive, Seed


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
    data_workers: Annotated[int, AtLeast(1)] = 1
    """Processes rendering the data on first use, each its own part (the same data whatever the
    count; with PYOPENGL_PLATFORM=egl on a GPU machine they render on the GPU)."""
    progress: bool = True
    """Report progress (a bar on a terminal, a line every few seconds in a log)."""
    patch: Annotated[int, AtLeast(1, "px")] = 2
    """Pixels per side folded into channels at the UNet's input: its first level works at
    --size / --patch (64 px at patch 4 costs about what 32 px at patch 2 does)."""
    widths: Annotated[tuple[int, ...], AtLeast(8)] = (64, 96, 128)
    """Feature channels per level of the UNet (each a multiple of 8; each level halves the size)."""
    emb: Annotated[int, AtLeast(2)] = 128
    """Width of the conditioning embedding (even)."""
    stop_at: Annotated[int | None, AtLeast(1)] = None
    """End this call at that step with a checkpoint, the schedule still that of --steps (run the
    command again to go on): a long training in sittings, or a look at its first steps."""
    catalogue: Literal["six", "world"] = "six"
    """six: the paper's six assets, one embedding per caption (the shipped models); world: every
    caption of `gdbench prompts`, each the sum of its kind's, colour's and accessory's embeddings,
    with the world's held-out combinations never rendered (docs/learned_prior.md)."""
    teacher: Path | None = None
    """Guidance distillation: a finished model's weights (a file or a run folder) the new one starts
    from and learns to match, guided at --teacher-guidance, in one call (its architecture, data and
    view weighting are the teacher's: --size, --patch, --widths, --emb, --views, --resolution,
    --catalogue and --front-bias are not used; --lr left at its default trains at 1e-4, a fine-tuning
    rate; docs/learned_prior.md) (default: none, a model of its own)."""
    teacher_guidance: Annotated[float | None, AtLeast(1)] = None
    """The teacher's classifier-free guidance scale the one-call model learns, with --teacher only
    (default: 3, the learned prior's default --learned-guidance)."""


def run_train_prior(cmd: TrainPrior) -> dict:
    from gdbench.priors.learned.data import DataConfig
    from gdbench.priors.learned.training import PriorTrainConfig, train_prior, world_config
    from gdbench.priors.learned.unet import UNetConfig

    if cmd.teacher is None and cmd.teacher_guidance is not None:
        raise ValueError("teacher_guidance (--teacher-guidance): acts only with --teacher (a model to distil)")
    if cmd.teacher is not None:
        from gdbench.priors.learned.distillation import distill_config

        scale = 3.0 if cmd.teacher_guidance is None else cmd.teacher_guidance
        cfg = distill_config(
            cmd.teacher, scale, out=cmd.out, steps=cmd.steps, batch=cmd.batch, seed=cmd.seed,
            threads=cmd.threads, device=cmd.device, data_workers=cmd.data_workers, progress=cmd.progress,
            **({} if cmd.lr == 6e-4 else {"lr": cmd.lr}),
        )  # fmt: skip
        return train_prior(cfg, stop_at=cmd.stop_at)

    if cmd.catalogue == "world":
        cfg = world_config(
            out=cmd.out, front_bias=cmd.front_bias, steps=cmd.steps, batch=cmd.batch, lr=cmd.lr, seed=cmd.seed,
            threads=cmd.threads, device=cmd.device, data_workers=cmd.data_workers, progress=cmd.progress,
            unet={"size": cmd.size, "patch": cmd.patch, "widths": tuple(cmd.widths), "emb": cmd.emb},
            data={"views": cmd.views, "resolution": cmd.resolution},
        )  # fmt: skip
        return train_prior(cfg, stop_at=cmd.stop_at)
    cfg = PriorTrainConfig(
        out=cmd.out, front_bias=cmd.front_bias, steps=cmd.steps, batch=cmd.batch, lr=cmd.lr, seed=cmd.seed,
        threads=cmd.threads, device=cmd.device, data_workers=cmd.data_workers, progress=cmd.progress,
        unet=UNetConfig(size=cmd.size, patch=cmd.patch, widths=tuple(cmd.widths), emb=cmd.emb),
        data=DataConfig(views=cmd.views, resolution=cmd.resolution),
    )  # fmt: skip
    return train_prior(cfg, stop_at=cmd.stop_at)


@dataclass
class TrainJudge:
    """Train the Janus judge (docs/scoring.md, "The Janus judge"): its eye, which reads which side of the
    asset a view shows, on the assets' own renders (every caption, rendered on first use and
    cached; no label of any result), draws the templates its sameness, marking and outline readings
    compare views with from the same renders, then fits its head (a regression and boosted trees
    over the turntable readings, the views' sameness, look, front marking and outline, their
    probabilities averaged) on the consensus labels of v3's committed sheets and the spent fresh
    sets'. Writes eye.safetensors,
    templates.safetensors, head.json and provenance.json to --out (default: the shipped judge's
    folder, so `gdbench judge` and `score` then use it)."""

    out: Path | None = None
    """Where the judge goes (default: gdbench/metrics/judge/weights, the shipped judge)."""
    steps: Annotated[int, AtLeast(1)] = 3000
    """The eye's optimiser steps (batch 128)."""
    views: Annotated[int, AtLeast(8)] = 256
    """Rendered cameras per (caption, variant) of the eye's data."""
    data_workers: Annotated[int, AtLeast(1)] = 2
    """Processes rendering the eye's data on first use."""
    seed: Annotated[int, Seed()] = 0
    """Seed of the eye's weights and draws."""
    progress: bool = True
    """Report progress."""
    eye_from: Path | None = None
    """Take this judge folder's eye as it is (byte for byte) instead of training one, and its
    templates and elongation curves where it has them (then no data is rendered): only the head is
    fitted again."""


def run_train_judge(cmd: TrainJudge) -> dict:
    from gdbench.experiments.judge_build import build_judge
    from gdbench.metrics.judge.judge import WEIGHTS

    out = cmd.out or WEIGHTS
    prov = build_judge(out, steps=cmd.steps, views=cmd.views, workers=cmd.data_workers, seed=cmd.seed,
                       root=Path(__file__).resolve().parents[2], progress=cmd.progress,
                       eye_from=cmd.eye_from)  # fmt: skip
    print(f"judge trained in {prov['seconds']:.0f} s (data {prov['seconds_data']:.0f} s) -> {out}")
    return prov


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
    """build: prompts (or captions) to build for; `all` for every caption `gdbench prompts` lists,
    `world` for the world's objects (default: the six paper assets, the duck last)."""


def _prompt_set(prompts: tuple[str, ...]) -> list[str] | None:
    """--prompts with `all` and `world` spelled out (None: the default six)."""
    from gdbench.assets.families import WORLD
    from gdbench.assets.library import CAPTIONS

    out: list[str] = []
    for p in prompts:
        for c in {"all": CAPTIONS, "world": tuple(WORLD)}.get(p, (p,)):
            if c not in out:
                out.append(c)
    return out or None


def run_cache(cmd: Cache) -> dict:
    from gdbench.core import cache

    if cmd.action != "clear" and cmd.kinds:
        raise ValueError(f"kinds: only for clear, not {cmd.action} (list shows every part, build builds banks)")
    if cmd.action != "build" and cmd.prompts:
        raise ValueError("prompts: only for build")
    if cmd.action == "build":
        from gdbench.app.prebuild import build

        built = build(_prompt_set(cmd.prompts))
        return {"root": str(cache.root()), "built": built}
    if cmd.action == "clear":
        files, size = cache.clear(list(cmd.kinds) or None)
        print(f"gdbench cache: removed {files} files ({cache.human(size)}) from {cache.root()}")
    print(cache.listing())
    return {"root": str(cache.root()), "entries": {e.kind: e.bytes for e in cache.entries()}}


@dataclass
class Prompts:
    """List the captions the embedded priors know: the six paper assets and the world's objects,
    each with its kind, what its front shows, which CPU priors know it and whether its image bank
    is cached. Free text is matched to these (docs/world.md says how)."""

    kind: str | None = None
    """Only this kind ("duck", "cat", "car" ...; default: every kind)."""


def run_prompts(cmd: Prompts) -> dict:
    from gdbench.assets.bank import BankConfig, cached
    from gdbench.assets.library import ASSETS, CAPTIONS, FRONTS, PARTS
    from gdbench.priors.learned.prior import model_captions

    kinds = sorted({k for k, *_ in PARTS.values()})
    if cmd.kind is not None and cmd.kind not in kinds:
        raise ValueError(f"kind: expected one of {', '.join(kinds)}, got {cmd.kind!r}")
    learned, held_out = map(set, model_captions("uniform"))
    rows = []
    for c in CAPTIONS:
        kind = PARTS[c][0]
        if cmd.kind in (None, kind):
            priors = "empirical, learned" if c in learned else "empirical"
            priors += " (held out)" * (c in held_out)
            rows.append({"caption": c, "kind": kind, "front": FRONTS[c] or "(none)", "priors": priors,
                         "bank": "cached" if cached(c, BankConfig()) else "-", "paper": c in ASSETS})  # fmt: skip
    width = max(len(r["caption"]) for r in rows)
    for r in rows:
        print(f"{r['caption']:<{width}}  {r['kind']:<11}  {r['priors']:<29}  {r['bank']:<6}  {r['front']}")
    n_kinds, fronts = len({r["kind"] for r in rows}), sum(FRONTS[r["caption"]] is not None for r in rows)
    print(f"{len(rows)} objects ({fronts} with a front) in {n_kinds} kind{'s' * (n_kinds > 1)}", flush=True)
    return {"captions": [r["caption"] for r in rows], "rows": rows}
