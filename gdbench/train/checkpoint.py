"""Checkpoints: atomic writes, safe loads (tensors and plain data only: ``weights_only=True``,
so a crafted file cannot run code), and a resume check that refuses a folder whose run had a
different config (every field that changes the result, ``steps`` included: the sigma, noise
and learning-rate schedules depend on it)."""

from __future__ import annotations

import pickle
import zipfile
from pathlib import Path

import torch

from .streams import make_streams, set_stream_states

RESUME_IGNORES = frozenset({"out", "progress", "checkpoint_every", "log_every", "turntable_frames"})
"""Config fields that do not change a run's result (so a run may resume under other values)."""

ADDED_AT_DEFAULT = {"views_spread_deg": None}
"""Config fields added after runs were made, with the value that behaves as the code did before
them: left out of a run's id at that value, so finished runs keep their id (and resume, and are
found finished) across the addition."""

FORMAT = 2
"""Checkpoint layout version (2: one state per random stream, plain-data config and history)."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable, foreign, unsafe or from another config."""


def save_blob(blob: dict, path: Path) -> Path:
    """Atomic (``io.atomic_write``): written to a temporary file in the same folder, then renamed
    over ``path``; a full disk raises an OSError naming ``path``."""
    from ..io import atomic_write

    return atomic_write(path, lambda f: torch.save({"format": FORMAT} | blob, f))


def load_blob(path: Path) -> dict:
    """The checkpoint's contents; a file that is not a gdbench checkpoint raises CheckpointError."""
    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":  # torch.save writes a zip archive
        raise CheckpointError(
            f"checkpoint: {path} is unreadable (empty, truncated or not a checkpoint); "
            "delete it or start over with --no-resume"
        )
    try:
        blob = torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise CheckpointError(
            f"checkpoint: {path} holds objects other than tensors and plain data; refusing to load it "
            f"(it may run code). Delete it or start over with --no-resume"
        ) from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError) as e:
        raise CheckpointError(
            f"checkpoint: {path} is unreadable (truncated or not a checkpoint: {type(e).__name__}); "
            "delete it or start over with --no-resume"
        ) from None
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        found = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise CheckpointError(
            f"checkpoint: {path} is not a gdbench checkpoint of format {FORMAT} (found {found!r}); "
            "delete it or start over with --no-resume"
        )
    return blob


def config_diff(saved: dict, now: dict) -> list[str]:
    """Names of the fields that differ between two config dicts, ignoring ``RESUME_IGNORES``."""
    return sorted(k for k in set(saved) | set(now) if k not in RESUME_IGNORES and saved.get(k) != now.get(k))


def checkpoint_path(cfg) -> Path:
    return Path(cfg.out) / "checkpoint.pt"


def save_checkpoint(state, ctx, path: Path) -> Path:
    """Atomic (temporary file + rename); tensors and plain data only."""
    from .outputs import config_dict

    return save_blob(
        {
            "step": state.step,
            "params": {k: v.detach() for k, v in state.params.items()},
            "optimizer": state.optimizer.state_dict(),
            "densify": state.densify.state_dict(),
            "noise_colors": state.noise_colors,
            "streams": state.rng_state(),
            "history": state.history,
            "bad_steps": state.bad_steps,
            "config": config_dict(ctx.cfg),
            "densify_schedule": ctx.strategy.schedule.as_dict(),
        },
        path,
    )


def load_checkpoint(path: Path, ctx):
    """The ``TrainState`` saved at ``path``, after checking it belongs to ``ctx``'s config."""
    from .densify import DensifyState
    from .outputs import config_dict
    from .state import TrainState
    from .trainer import _optimizer

    blob = load_blob(path)
    diff = config_diff(blob["config"], config_dict(ctx.cfg))
    if diff:
        why = " (the sigma, noise and learning-rate schedules depend on steps)" if "steps" in diff else ""
        raise CheckpointError(
            f"out: {path.parent} holds a run with a different config (fields {diff}){why}; "
            "use another --out, or --no-resume to start over"
        )
    schedule = ctx.strategy.schedule.as_dict()
    if blob.get("densify_schedule", schedule) != schedule:
        raise CheckpointError(
            f"out: {path.parent} holds a run whose densification schedule {blob['densify_schedule']} differs from "
            f"the one this code resolves from the same config ({schedule}); use another --out, or --no-resume"
        )
    params = {k: v.clone().requires_grad_(True) for k, v in blob["params"].items()}
    opt = _optimizer(params, ctx.cfg)
    opt.load_state_dict(blob["optimizer"])
    streams = make_streams(ctx.cfg.seed)
    set_stream_states(streams, blob["streams"])
    dens = DensifyState(blob["densify"]["grad2d"], blob["densify"]["count"])
    return TrainState(
        blob["step"], params, opt, dens, blob["noise_colors"], streams, blob["history"], blob["bad_steps"]
    )
