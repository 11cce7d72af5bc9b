"""The ``gdbench`` command line. ``main(cmd)`` does the work and is tested; ``entrypoint``
only parses arguments with tyro."""

from __future__ import annotations

import json
import platform
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import tyro


@dataclass
class Demo:
    """Render the built-in scene as a turntable (GIF, MP4, contact sheet) and print timings."""

    out: Path = Path("runs/demo")
    """Output folder."""
    frames: int = 36
    """Views on the orbit (360/frames degrees apart)."""
    size: int = 256
    """Image width and height in pixels."""
    gaussians: int = 3000
    """Number of Gaussians in the built-in scene."""
    seed: int = 0
    """Seed of the built-in scene."""


def run_demo(cmd: Demo) -> dict:
    import torch

    from renderers.splat._ext import extension_status

    from .builtin import demo_scene
    from .turntable import write_turntable

    t0 = time.perf_counter()
    scene = demo_scene(cmd.gaussians, seed=cmd.seed)
    res = write_turntable(scene, cmd.out, frames=cmd.frames, size=cmd.size)
    total = time.perf_counter() - t0
    ply = scene.save_ply(cmd.out / "scene.ply")
    per = sorted(res.seconds_per_frame)
    summary = {
        "command": "demo",
        "config": {k: str(v) for k, v in asdict(cmd).items()},
        "gaussians": len(scene),
        "frames": cmd.frames,
        "resolution": [cmd.size, cmd.size],
        "first_frame_s": res.seconds_per_frame[0],
        "median_frame_s": per[len(per) // 2],
        "fps_median": 1.0 / per[len(per) // 2],
        "total_s": total,
        "compositor": extension_status(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "outputs": {k: str(v) for k, v in res.paths.items()} | {"ply": str(ply)},
    }
    (cmd.out / "summary.json").write_text(json.dumps(summary, indent=2))
    print(f"gdbench demo: {len(scene)} Gaussians, {cmd.frames} frames at {cmd.size}x{cmd.size}")
    print(f"  first frame {summary['first_frame_s'] * 1e3:8.1f} ms (includes loading the compositor)")
    print(f"  median      {summary['median_frame_s'] * 1e3:8.1f} ms  ({summary['fps_median']:.1f} frames/s)")
    print(f"  total       {total:8.2f} s   compositor: {summary['compositor']}")
    for k, v in summary["outputs"].items():
        print(f"  {k:5s} -> {v}")
    return summary


@dataclass
class Noise:
    """Structured noise tools: ``--preview`` writes 4 views of one noise source and the
    per-pixel histogram against N(0, 1)."""

    preview: bool = False
    """Write the preview figure."""
    out: Path = Path("runs/noise_preview.png")
    """Where the preview PNG goes."""
    res: int = 128
    """Resolution of the views."""
    seed: int = 0
    n_gaussians: int = 3072
    """Noise Gaussians in the cloud."""
    scale: float = 0.02
    """Their isotropic scale."""


def run_noise(cmd: Noise) -> dict:
    from .noise import NoiseConfig
    from .noise_preview import preview

    if not cmd.preview:
        raise SystemExit("gdbench noise: nothing to do; pass --preview to write the preview figure")
    stats = preview(cmd.out, NoiseConfig(n_gaussians=cmd.n_gaussians, scale=cmd.scale), res=cmd.res, seed=cmd.seed)
    print(
        f"wrote {stats['path']}: coverage {stats['coverage']:.2f}, per-pixel mean {stats['mean']:+.3f}, "
        f"variance {stats['var']:.3f}, KS distance to N(0,1) {stats['ks_statistic']:.4f}, "
        f"correlation length {stats['correlation_length_px']:.1f} px"
    )
    return stats


COMMANDS = {"demo": Demo, "noise": Noise}


def main(cmd) -> dict:
    if isinstance(cmd, Demo):
        return run_demo(cmd)
    if isinstance(cmd, Noise):
        return run_noise(cmd)
    raise TypeError(f"cmd: unknown command {type(cmd).__name__}")


def entrypoint() -> None:
    main(tyro.extras.subcommand_cli_from_dict(COMMANDS))


if __name__ == "__main__":
    entrypoint()
