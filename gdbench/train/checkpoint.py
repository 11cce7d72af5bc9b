"""Checkpoints: atomic writes, safe loads (tensors and plain data only: ``weights_only=True``,
so a crafted file cannot run code), and a resume check that refuses a folder whose run had a
different config (every field that changes the result, ``steps`` included: the sigma, noise
and learning-rate schedules depend on it)."""

from __future__ import annotations

from pathlib import Path

import torch

from gdbench.train.streams import make_streams, set_stream_states

RESUME_IGNORES = frozenset(
    {"out", "progress", "checkpoint_every", "log_every", "turntable_frames", "log_dir", "device"}
)
"""Config fields that do not change a run's result (so a run may resume under other values). ``device``
changes it by float rounding only, as the thread count does: run.json records both."""

ADDED_AT_DEFAULT = {
    "views_spread_deg": None,
    "noise.source": "cloud",
    "densify.min_every": 25,
    "densify.max_growth": 0.3,
}
"""Config fields added after runs were made (a nested group's by its dotted key), with the value
that behaves as the code did before them: left out of a run's id at that value, so finished runs
keep their id (and resume, and are found finished) across the addition. One exception: the
densification floor and cap (``densify.min_every``, ``densify.max_growth``, commit after c054296)
behave as before in runs of 1000 steps or more (every default densification of those is as it
was), not in shorter ones; a run's ``densify_schedule`` in run.json tells the two apart, and a
checkpoint of the old schedule is refused on resume (``load_checkpoint``)."""


def comparable(d: dict) -> dict:
    """A config dict (either layout) as run ids and the resume check compare it: flat
    (``train.layout.flat_config``), without ``RESUME_IGNORES`` and without the fields of
    ``ADDED_AT_DEFAULT`` at their value there."""
    from gdbench.train.layout import flat_config

    def without(fields: dict, name: str, default) -> dict:
        return {k: v for k, v in fields.items() if not (k == name and v == default)}

    out = {k: v for k, v in flat_config(d).items() if k not in RESUME_IGNORES}
    for key, default in ADDED_AT_DEFAULT.items():
        group, _, name = key.rpartition(".")
        if not group:
            out = without(out, name, default)
        elif isinstance(out.get(group), dict):
            out[group] = without(out[group], name, default)
    return out


FORMAT = 2
"""Checkpoint layout version (2: one state per random stream, plain-data config and history)."""


class CheckpointError(ValueError):
    """A checkpoint that cannot be used: unreadable, foreign, unsafe or from another config."""


def save_blob(blob: dict, path: Path) -> Path:
    """Atomic (``io.atomic_write``): written to a temporary file in the same folder, then renamed
    over ``path``; a full disk raises an OSError naming ``path``."""
    from gdbench.core.io import atomic_write

    return atomic_write(path, lambda f: torch.save({"format": FORMAT} | blob, f))


def load_blob(path: Path) -> dict:
    """The checkpoint's contents; a file that is not a gdbench checkpoint raises CheckpointError."""
    from gdbench.core.io import load_torch_safely

    path = Path(path)
    blob = load_torch_safely(path, "delete it or start over with --no-resume", CheckpointError)
    if not isinstance(blob, dict) or blob.get("format") != FORMAT:
        found = blob.get("format") if isinstance(blob, dict) else type(blob).__name__
        raise CheckpointError(
            f"checkpoint: {path} is not a gdbench checkpoint of format {FORMAT} (found {found!r}); "
            "delete it or start over with --no-resume"
        )
    return blob


def config_diff(saved: dict, now: dict) -> list[str]:
    """Names of the fields that differ between two config dicts (either layout, compared as
    ``comparable`` gives them)."""
    saved, now = comparable(saved), comparable(now)
    return sorted(k for k in set(saved) | set(now) if saved.get(k) != now.get(k))


def checkpoint_path(cfg) -> Path:
    return Path(cfg.out) / "checkpoint.pt"


def save_checkpoint(state, ctx, path: Path) -> Path:
    """Atomic (temporary file + rename); tensors and plain data only."""
    from gdbench.train.outputs import config_dict

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
    from gdbench.train.densify import DensifyState
    from gdbench.train.outputs import config_dict
    from gdbench.train.state import TrainState
    from gdbench.train.trainer import _optimizer

    blob = load_blob(path)
    saved = blob.get("config")
    if not isinstance(saved, dict):
        raise _broken(path, "its config", "not a dict")
    diff = config_diff(saved, config_dict(ctx.cfg))
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
    try:  # a well-formed file of format 2 can still lack or mangle a part: name it, do not crash on it
        _check_params(blob["params"])
        params = {k: v.to(ctx.device).clone().requires_grad_(True) for k, v in blob["params"].items()}
        opt = _optimizer(params, ctx.cfg)
        opt.load_state_dict(blob["optimizer"])
        streams = make_streams(ctx.cfg.seed)
        set_stream_states(streams, blob["streams"])
        dens = DensifyState(blob["densify"]["grad2d"], blob["densify"]["count"])
        step, history, bad = int(blob["step"]), list(blob["history"]), int(blob["bad_steps"])
        noise_colors = blob["noise_colors"]
        noise_colors = noise_colors.to(ctx.device) if noise_colors is not None else None
        _check_state(params, opt, dens, noise_colors, ctx)
    except (KeyError, TypeError, AttributeError, ValueError, RuntimeError, IndexError) as e:
        raise _broken(path, "its training state", f"{type(e).__name__}: {e}") from None
    return TrainState(step, params, opt, dens, noise_colors, streams, history, bad)


def _broken(path: Path, part: str, why: str) -> CheckpointError:
    return CheckpointError(
        f"checkpoint: {path} is a gdbench checkpoint but {part} is broken ({why}); "
        "delete it or start over with --no-resume"
    )


def _check_state(params, opt, dens, noise_colors, ctx) -> None:
    """What the fused Adam kernel and the densification index without checking: the optimizer's
    moments shaped like their parameters (a mismatch crashes the kernel or trains on wrong state),
    the densification statistics one per Gaussian, the noise colours one row per noise Gaussian."""
    for g in opt.param_groups:
        p = g["params"][0]
        st = opt.state.get(p, {})
        for k in ("exp_avg", "exp_avg_sq"):
            if k in st and tuple(st[k].shape) != tuple(p.shape):
                raise ValueError(
                    f"optimizer[{g['name']!r}].{k}: expected shape {list(p.shape)}, got {list(st[k].shape)}"
                )
    n = params["means"].shape[0]
    for k in ("grad2d", "count"):
        v = getattr(dens, k)
        if v is not None and hasattr(v, "shape") and v.dim() and v.shape[0] != n:
            raise ValueError(f"densify.{k}: expected {n} entries (one per Gaussian), got {v.shape[0]}")
    want = None if ctx.noise is None else (len(ctx.noise.cloud), ctx.noise.cloud.channels)
    got = None if noise_colors is None else tuple(noise_colors.shape)
    if got != want:
        raise ValueError(f"noise_colors: expected shape {want}, got {got}")


def _check_params(params) -> None:
    """The saved parameters: tensors of one Gaussian count with the trainer's shapes."""
    from gdbench.train.densify import PARAM_NAMES

    if not isinstance(params, dict) or set(params) != set(PARAM_NAMES):
        found = sorted(params) if isinstance(params, dict) else type(params).__name__
        raise ValueError(f"params: expected {sorted(PARAM_NAMES)}, got {found}")
    n = params["means"].shape[0]
    want = {"means": (n, 3), "quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
    for k, shape in want.items():
        if tuple(params[k].shape) != shape:
            raise ValueError(f"params[{k!r}]: expected shape {list(shape)}, got {list(params[k].shape)}")
    for k in ("sh", "sh_rest"):
        if params[k].dim() != 3 or params[k].shape[0] != n:
            raise ValueError(f"params[{k!r}]: expected shape [{n}, K, C], got {list(params[k].shape)}")
