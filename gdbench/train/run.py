"""``train``: the loop around ``train_step`` with a progress bar, atomic checkpoints every
``checkpoint_every`` steps, resume, and the run folder's outputs."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import torch

from .config import TrainConfig
from .outputs import config_dict, package_versions, write_curves, write_json_atomic
from .trainer import (
    Context,
    TrainState,
    checkpoint_path,
    init_state,
    load_checkpoint,
    make_context,
    save_checkpoint,
    train_step,
)


@dataclass
class RunResult:
    state: TrainState
    out: Path
    paths: dict[str, Path]
    seconds: float
    resumed_from: int
    caption: str | None = None
    """The bank caption the prompt matched (empirical prior), else None."""


def train(
    cfg: TrainConfig, prior=None, *, resume: bool = True, stop_at: int | None = None, write_outputs: bool = True
) -> RunResult:
    """Train (or resume) the run in ``cfg.out``.

    ``stop_at`` ends the call after that many total steps with a checkpoint, as if the run had
    been killed there (for tests and time-sliced sweeps); calling again resumes it. On CPU a
    resumed run gives the same result as an uninterrupted one.
    """
    t_start = time.perf_counter()
    out = Path(cfg.out)
    ctx = make_context(cfg, prior)  # bad prompts fail here, before anything is written
    ckpt = checkpoint_path(cfg)
    if resume and ckpt.is_file():
        state = load_checkpoint(ckpt, ctx)
    else:
        state = init_state(ctx)
    resumed_from = state.step
    last = min(cfg.steps, stop_at) if stop_at is not None else cfg.steps
    bar = _progress(cfg, state.step, last)
    try:
        while state.step < last:
            m = train_step(state, ctx)
            if bar is not None:
                bar.update(1)
                if state.step % cfg.log_every == 0 or state.step == last:
                    bar.set_postfix(resid=f"{m['residual']:.3g}", sigma=f"{m['sigma']:.3g}", N=m["n"])
            if state.step % cfg.checkpoint_every == 0:
                save_checkpoint(state, ctx, ckpt)
    finally:
        if bar is not None:
            bar.close()
    save_checkpoint(state, ctx, ckpt)
    paths: dict[str, Path] = {"checkpoint": ckpt}
    if write_outputs and state.step >= cfg.steps:
        paths |= write_run_outputs(state, ctx, out, time.perf_counter() - t_start, resumed_from)
    caption = getattr(ctx.cond, "caption", None)
    return RunResult(state, out, paths, time.perf_counter() - t_start, resumed_from, caption)


def _progress(cfg: TrainConfig, start: int, last: int):
    if not cfg.progress:
        return None
    from tqdm import tqdm

    return tqdm(total=last, initial=start, desc=f"{cfg.preset} '{cfg.prompt}'", unit="step", dynamic_ncols=True)


def write_run_outputs(state: TrainState, ctx: Context, out: Path, seconds: float, resumed_from: int) -> dict[str, Path]:
    from ..turntable import write_turntable

    cfg = ctx.cfg
    scene = state.scene()
    paths = {"ply": scene.save_ply(out / "scene.ply")}
    t0 = time.perf_counter()
    tt = write_turntable(
        scene,
        out,
        frames=cfg.turntable_frames,
        size=max(128, cfg.resolution),
        radius=1.3,
        elevation=15.0,
        fovy=45.0,
        background=cfg.background,
    )
    paths |= {f"turntable_{k}": v for k, v in tt.paths.items()}
    paths["curves"] = write_curves(state.history, out / "curves.png")
    steps_s = [h["seconds"] for h in state.history]
    run = {
        "prompt": cfg.prompt,
        "caption": getattr(ctx.cond, "caption", None),
        "preset": cfg.preset,
        "seed": cfg.seed,
        "config": config_dict(cfg),
        "steps": state.step,
        "gaussians": len(scene),
        "resumed_from_step": resumed_from,
        "timings": {
            "this_call_s": seconds,
            "train_steps_s": sum(steps_s),
            "mean_step_s": sum(steps_s) / max(len(steps_s), 1),
            "turntable_s": time.perf_counter() - t0,
        },
        "skipped_steps": sum(1 for h in state.history if h.get("skipped")),
        "final_residual_mean_last_100": sum(h["residual"] for h in state.history[-100:])
        / max(1, len(state.history[-100:])),
        "versions": package_versions(),
        "threads": torch.get_num_threads(),
        "outputs": {k: str(v) for k, v in paths.items()},
    }
    paths["run_json"] = write_json_atomic(run, out / "run.json")
    return paths
