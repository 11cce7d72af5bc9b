"""``train``: the loop around ``train_step`` with a progress bar, atomic checkpoints every
``checkpoint_every`` steps, resume, and the run folder's outputs.

A run folder holds one run. While a run trains, it holds the folder's lock (``io.FolderLock``);
a finished run (its ``run.json`` present) is never replaced unless ``overwrite=True``, and then
every old output goes first. Every output names the run it belongs to: ``run.json`` carries the
run id (a hash of the config) and the scene's hash, ``scene.ply`` the run id in a header comment,
``scores.json`` both. Ctrl-C saves a checkpoint before it stops the run.
"""

from __future__ import annotations

import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from gdbench.core.filetags import ply_comments
from gdbench.core.io import FolderLock, check_folder, probe_writable, read_json, sha256_file, sha256_json, write_json
from gdbench.core.signals import RunInterrupted, defer_stop_signals
from gdbench.train.checkpoint import checkpoint_path, load_checkpoint, save_checkpoint
from gdbench.train.config import TrainConfig
from gdbench.train.outputs import config_dict, package_versions, write_curves
from gdbench.train.trainer import Context, TrainState, init_state, make_context, train_step

RUN_OUTPUTS = (
    "run.json",
    "scores.json",
    "scene.ply",
    "turntable.gif",
    "turntable.mp4",
    "turntable_sheet.png",
    "curves.png",
    "checkpoint.pt",
    "colmap.log",
    *(
        f"scene_{kind}{tag}{end}"
        for kind in ("turntable", "camera_path")
        for tag in ("", "_depth", "_alpha")
        for end in (".gif", ".mp4", "_sheet.png", *((".npy",) if tag else ()))
    ),
)  # scene_* is what render writes of scene.ply (RENDERED below)
"""What a run and the commands that write into its folder (``score``, ``render``) put there
(removed before an overwrite, with the files ``files_of_run`` finds)."""


RENDERED = tuple(
    f"_{kind}{tag}{end}"
    for kind in ("turntable", "camera_path")
    for tag in ("", "_depth", "_alpha")
    for end in (".gif", ".mp4", "_sheet.png", *((".npy",) if tag else ()))
)
"""What ``gdbench render`` writes of a scene file ``<stem>.*``: ``<stem>`` + each of these."""


def files_of_run(folder: Path, run: str) -> list[Path]:
    """What in ``folder`` (not below it) ``gdbench export`` and ``render`` made of run ``run``'s
    scene besides ``RUN_OUTPUTS``: exports under ``export``'s default names for the run's scene
    (scene.y_down.splat, scene.z_up.sh3.ply, scene.y_up.glb, ...) that record this run, or no run
    (made before exports recorded it); a .splat's sidecar; what ``render`` wrote of them
    (``RENDERED``); and Inria model folders under the default name (``inria.<axis>``) whose
    point cloud records the run. Files under other names (a renamed export, a backup copy, notes)
    are the user's and stay."""
    import re

    from gdbench.core.filetags import UP_NAMES, read_tags, sidecar

    axes = "|".join(UP_NAMES.values())
    default = re.compile(rf"scene\.({axes})(\.sh\d)?(\.compressed\.ply|\.ply|\.splat|\.glb|\.obj)")

    def records(path: Path, accept=(run, None)) -> bool:
        try:
            return read_tags(path).run in accept
        except (OSError, ValueError):
            return False  # unreadable tags: not provably this run's, so left alone

    found: list[Path] = []
    for path in sorted(folder.iterdir()):
        if path.is_dir():  # an Inria model folder of this run, under export's default name
            clouds = path.glob("point_cloud/iteration_*/point_cloud.ply")
            if re.fullmatch(rf"inria\.({axes})", path.name) and (path / "cfg_args").is_file():
                found += [path] if any(records(c, (run,)) for c in clouds) else []
        elif default.fullmatch(path.name) and records(path):
            found += [path, sidecar(path), *(folder / f"{path.stem}{r}" for r in RENDERED)]
    return [p for p in found if p.is_file() or p.is_dir()]


@dataclass
class RunResult:
    state: TrainState
    out: Path
    paths: dict[str, Path]
    seconds: float
    resumed_from: int | None
    """The step the checkpoint read held; None for a run started afresh."""
    caption: str | None = None
    """The bank caption the prompt matched (empirical prior), else None."""
    similarity: float | None = None
    """Cosine similarity of the prompt to that caption (1 for an exact match)."""
    prompt: str = ""

    def summary(self) -> dict:
        return {
            "out": str(self.out),
            "caption": self.caption,
            "caption_similarity": self.similarity,
            "steps": self.state.step,
            "gaussians": int(self.state.params["means"].shape[0]),
            "seconds": self.seconds,
            "resumed_from": self.resumed_from,
        }

    def report(self, summary: dict | None = None, matched: bool = True) -> str:
        """The lines ``gdbench generate`` prints at the end (``matched``: with the prompt's matched
        asset, which the command prints before training)."""
        s = summary or self.summary()
        lines = []
        if self.caption is not None and matched:
            lines.append(
                f"gdbench generate: prompt {self.prompt!r} -> asset {self.caption!r} (cosine {self.similarity:.2f})"
            )
        resumed = "" if s["resumed_from"] is None else f" (resumed from step {s['resumed_from']})"
        lines.append(
            f"gdbench generate: {s['steps']} steps, {s['gaussians']} Gaussians, {s['seconds']:.1f} s{resumed} "
            f"-> {s['out']}"
        )
        if "gt" in s:
            from gdbench.metrics.run_scores import result_lines

            lines += result_lines(s["gt"], s.get("views"), s.get("judge"))
        lines += [f"  {k:18s} {v}" for k, v in sorted(self.paths.items())]
        return "\n".join(lines)


def run_id(cfg: TrainConfig) -> str:
    """A short hash of everything in the config that changes the result, in the flat layout runs
    were first named in (``train.layout.flat_config``); fields added later are left out at the value
    that behaves as before them (``ADDED_AT_DEFAULT``)."""
    from gdbench.train.checkpoint import comparable

    return sha256_json(comparable(config_dict(cfg)))[:16]


def _check_finished(out: Path, cfg: TrainConfig, overwrite: bool, resume: bool) -> None:
    """Refuse to replace a finished run, unless asked to (then its outputs go first)."""
    run_json = out / "run.json"
    if not run_json.is_file():
        return
    old = read_json(run_json, what="run.json")
    if overwrite:
        derived = files_of_run(out, old["run_id"]) if isinstance(old.get("run_id"), str) else []
        for path in [*(out / name for name in RUN_OUTPUTS), *derived]:
            if path.is_dir():
                shutil.rmtree(path)
            else:
                path.unlink(missing_ok=True)
        return
    same = old.get("run_id") == run_id(cfg)
    if same and resume and checkpoint_path(cfg).is_file():
        return  # the same run: resuming it rewrites the same outputs
    what = f"'{old.get('prompt')}' (preset {old.get('preset')}, seed {old.get('seed')}, run {old.get('run_id')})"
    raise FileExistsError(
        f"out: {out} holds a finished run of {what}; pass --overwrite to replace it, or use another --out"
    )


def train(
    cfg: TrainConfig,
    prior=None,
    *,
    resume: bool = True,
    stop_at: int | None = None,
    write_outputs: bool = True,
    overwrite: bool = False,
    on_start=None,
    on_step=None,
    figures: bool = True,
) -> RunResult:
    """Train (or resume) the run in ``cfg.out``.

    ``on_start(ctx)``, if given, is called once the prompt is matched and the prior built, before
    the first step (``gdbench generate`` prints the matched asset there). ``on_step(state)``, if
    given, is called after every step (``gdbench generate --view`` sends the scene to the viewer).

    ``stop_at`` ends the call after that many total steps with a checkpoint, as if the run had
    been killed there (for tests and time-sliced sweeps); calling again resumes it. On CPU a
    resumed run gives the same result as an uninterrupted one.

    ``figures=False`` writes only scene.ply and run.json of the outputs (no turntable or curves:
    what a sweep's scores and tables need, and the turntable renders are a sizeable share of a
    short run).
    """
    t_start = time.perf_counter()
    out = check_folder(cfg.out, "out (--out)")  # before the bank is built: a file or a dangling link is refused
    probe_writable(out, "out (--out)")  # and a place that refuses files (read-only, /sys, /proc)
    if not overwrite:  # a finished run of another config is refused before the bank is built
        _check_finished(out, cfg, overwrite, resume)
    ctx = make_context(cfg, prior)  # bad prompts fail here, before anything is written
    if on_start is not None:
        on_start(ctx)
    with FolderLock(out):
        _check_finished(out, cfg, overwrite, resume)  # again under the lock: the folder may have changed
        ckpt = checkpoint_path(cfg)
        read = resume and ckpt.is_file()
        state = load_checkpoint(ckpt, ctx) if read else init_state(ctx)
        resumed_from = state.step if read else None
        setup_s = time.perf_counter() - t_start
        last = min(cfg.steps, stop_at) if stop_at is not None else cfg.steps
        if _loop(state, ctx, ckpt, last, on_step) != state.step:  # the loop saved this step already, or not
            save_checkpoint(state, ctx, ckpt)
        paths: dict[str, Path] = {"checkpoint": ckpt}
        # a run found finished (figures drawn later, scores made again) keeps its provenance: the
        # commit, versions and threads that trained it, and its timings
        made = _run_json(out) if read and resumed_from >= cfg.steps else None
        if write_outputs and state.step >= cfg.steps:
            paths |= write_run_outputs(
                state, ctx, out, time.perf_counter() - t_start, resumed_from, figures=figures, setup_s=setup_s,
                made=made,
            )  # fmt: skip
    caption = getattr(ctx.cond, "caption", None)
    similarity = getattr(ctx.cond, "similarity", None)
    return RunResult(state, out, paths, time.perf_counter() - t_start, resumed_from, caption, similarity, cfg.prompt)


def _run_json(out: Path) -> dict | None:
    """The run.json in ``out`` as a dict, None when there is none or it does not read."""
    try:
        blob = read_json(out / "run.json", what="run.json")
    except (OSError, ValueError):
        return None
    return blob if isinstance(blob, dict) else None


PROVENANCE = ("commit", "utc", "versions", "threads", "device", "timings", "resumed_from_step")
"""What run.json says about how its scene was trained, kept when a finished run's outputs are
written again."""


def _loop(state: TrainState, ctx: Context, ckpt: Path, last: int, on_step=None) -> int | None:
    """Steps until ``last``; returns the step of the last checkpoint it saved (None if none). A stop
    signal (Ctrl-C, SIGTERM, SIGHUP) is deferred to the end of the step it lands in, so the
    checkpoint saved then holds a whole step, and the run resumes exactly where it stopped."""
    cfg = ctx.cfg
    scalars = None
    if cfg.log_dir is not None:
        from gdbench.train.tblog import ScalarLog

        scalars = ScalarLog(cfg, ctx, run_id(cfg))
    bar = _progress(cfg, state.step, last)
    interrupted, saved = [], None
    with defer_stop_signals(interrupted):
        try:
            while state.step < last and not interrupted:
                m = train_step(state, ctx)
                if bar is not None:
                    if state.step % cfg.log_every == 0 or state.step == last:  # before the line it goes on
                        bar.set_postfix(resid=f"{m['residual']:.3g}", sigma=f"{m['sigma']:.3g}", N=m["n"])
                    bar.update(1)
                if scalars is not None:
                    scalars.step(state, m, last)
                if state.step % cfg.checkpoint_every == 0 and not interrupted:
                    save_checkpoint(state, ctx, ckpt)
                    saved = state.step
                if on_step is not None:
                    on_step(state)
        finally:
            if bar is not None:
                bar.close()
            if scalars is not None:
                scalars.close()
    if interrupted:
        save_checkpoint(state, ctx, ckpt)
        raise RunInterrupted.at(interrupted[0], state.step, cfg.steps, ckpt)
    return saved


def _progress(cfg: TrainConfig, start: int, last: int):
    if not cfg.progress:
        return None
    from gdbench.core.progress import progress

    return progress(last, f"{cfg.preset} '{cfg.prompt}'", "step", initial=start)


def turntable_size(resolution: int) -> int:
    """The side of a run's turntable frames, in pixels: its training resolution, at least 128."""
    return max(128, int(resolution))


def write_run_outputs(
    state: TrainState,
    ctx: Context,
    out: Path,
    seconds: float,
    resumed_from: int | None,
    *,
    figures: bool = True,
    setup_s: float = float("nan"),
    made: dict | None = None,
) -> dict[str, Path]:
    """scene.ply, run.json and, with ``figures``, the turntable (GIF, MP4, sheet) and the curves.
    run.json's timings: ``this_call_s`` (the call up to its outputs), ``setup_s`` (prompt, prior,
    bank and initial state or checkpoint), ``train_steps_s`` and ``outputs_s`` (these outputs).
    ``made``: the run.json of an earlier call that finished this run, whose ``PROVENANCE`` fields
    are kept."""
    from gdbench.core.provenance import code_commit, utc_now
    from gdbench.core.turntable import RUN_TURNTABLE, write_turntable

    cfg = ctx.cfg
    rid = run_id(cfg)
    scene = state.scene()
    t0 = time.perf_counter()
    paths = {"ply": scene.save_ply(out / "scene.ply", comments=ply_comments("+z", rid))}
    if figures:
        tt = write_turntable(
            scene,
            out,
            frames=cfg.turntable_frames,
            size=turntable_size(cfg.resolution),
            background=cfg.background,
            **RUN_TURNTABLE,
        )
        paths |= {f"turntable_{k}": v for k, v in tt.paths.items()}
        paths["curves"] = write_curves(state.history, out / "curves.png", ctx.strategy.schedule)
    steps_s = [h["seconds"] for h in state.history]
    run = {
        "run_id": rid,
        "scene_sha256": sha256_file(paths["ply"]),
        "prompt": cfg.prompt,
        "caption": getattr(ctx.cond, "caption", None),
        "caption_similarity": getattr(ctx.cond, "similarity", None),
        "preset": cfg.preset,
        "seed": cfg.seed,
        "config": config_dict(cfg),
        "densify_schedule": ctx.strategy.schedule.as_dict(),
        "scene_extent": ctx.extent,
        "steps": state.step,
        "gaussians": len(scene),
        "resumed_from_step": resumed_from,
        "timings": {
            "this_call_s": seconds,
            "setup_s": setup_s,
            "train_steps_s": sum(steps_s),
            "mean_step_s": sum(steps_s) / max(len(steps_s), 1),
            "outputs_s": time.perf_counter() - t0,
        },
        "skipped_steps": sum(1 for h in state.history if h.get("skipped")),
        "final_residual_mean_last_100": sum(h["residual"] for h in state.history[-100:])
        / max(1, len(state.history[-100:])),
        "versions": package_versions(),
        "commit": code_commit(),
        "utc": utc_now(),
        "threads": torch.get_num_threads(),
        "device": str(ctx.device),  # where it trained: results differ across devices by float rounding
        "outputs": {k: str(v) for k, v in paths.items()},
    }
    if made is not None:  # the run.json of the call that trained this scene: its provenance stands
        run |= {k: made[k] for k in PROVENANCE if k in made}
        if "device" not in made:  # made before the option: trained on the CPU
            run["device"] = "cpu"
    paths["run_json"] = write_json(run, out / "run.json")
    return paths
