"""Refuse work that cannot fit in memory, before it starts, naming the argument and the estimate.

Estimates are rough upper bounds of the big buffers (not the interpreter or the libraries),
compared against the memory the system reports available."""

from __future__ import annotations

import math
import os

GIB = 1024**3


def available_bytes() -> int:
    """MemAvailable from /proc/meminfo, else physical memory, else a large number."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 1 << 62


def _refuse(arg: str, value, need: float, what: str) -> None:
    have = available_bytes()
    if need > have:
        raise ValueError(
            f"{arg}: {value} needs about {need / GIB:.1f} GiB ({what}); this machine has {have / GIB:.1f} GiB available"
        )


def generate_bytes(cfg) -> tuple[float, str]:
    """(bytes, what) of a training run's big buffers: the prior's bank and zoomed copies, the
    renders of one step, and the Gaussians at their cap."""
    R, V = cfg.resolution, cfg.views_per_step
    need, parts = 0.0, []
    if cfg.prior == "empirical":
        from .assets.bank import BankConfig

        lo, hi = cfg.fovy_range
        ratio = math.tan(math.radians(hi) / 2) / math.tan(math.radians(lo) / 2) if 0 < lo <= hi < 180 else 2.0
        b = math.ceil(R * ratio)
        views = BankConfig().azimuths * len(BankConfig().elevations)
        bank = views * b * b * 4 * 12  # rgb, depth, alpha as float32, rendered and held twice
        levels = min(64, round((hi - lo) / 0.5) + 1) * views * R * R * 3 * 4
        need += bank + levels
        parts.append(f"image bank {bank / GIB:.1f} GiB and its zoomed copies {levels / GIB:.1f} GiB")
    render = V * R * R * 4 * 64  # rgb, alpha, depth, noise, score and their gradients
    gaussians = cfg.densify.max_gaussians * 4 * 200
    need += render + gaussians
    parts.append(f"renders {render / GIB:.2f} GiB")
    return need, ", ".join(parts)


def check_generate_memory(cfg) -> None:
    need, what = generate_bytes(cfg)
    _refuse("resolution", cfg.resolution, need, what)


def check_render_memory(size: int, frames: int) -> None:
    """A turntable holds its frames (uint8 RGB) and one float render with its tile buffers."""
    if size < 8:
        raise ValueError(f"size: expected at least 8 px, got {size}")
    need = frames * size * size * 3 + size * size * 4 * 48
    _refuse("size", size, need, f"{frames} frames of {size}x{size} px and the render's buffers")
