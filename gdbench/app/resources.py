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


def _refuse(terms: list[tuple[str, object, float, str]]) -> None:
    """``terms``: (field, value, bytes, what) of each big buffer. When their sum exceeds what is
    available, a ValueError names the field (and its flag) of the largest and every part."""
    from gdbench.core.constraints import flag

    need = sum(b for _, _, b, _ in terms)
    have = available_bytes()
    if need > have:
        name, value, _, _ = max(terms, key=lambda x: x[2])
        what = ", ".join(f"{w} {b / GIB:.2f} GiB" for _, _, b, w in terms)
        raise ValueError(
            f"{name} ({flag(name)}): {value} needs about {need / GIB:.1f} GiB ({what}); "
            f"this machine has {have / GIB:.1f} GiB available"
        )


def generate_terms(cfg) -> list[tuple[str, object, float, str]]:
    """The big buffers of a training run, each with the option that sizes it: the prior's bank
    and its zoomed copies (resolution), one step's renders and noise fields (views per step,
    samples per step) and the Gaussians (initial points, the densification cap)."""
    R, V, K = cfg.resolution, cfg.views.per_step, cfg.samples_per_step
    terms: list[tuple[str, object, float, str]] = []
    if cfg.prior.kind == "empirical":
        from gdbench.assets.bank import BankConfig

        lo, hi = cfg.fovy_range
        ratio = math.tan(math.radians(hi) / 2) / math.tan(math.radians(lo) / 2) if 0 < lo <= hi < 180 else 2.0
        b = math.ceil(R * ratio)
        views = BankConfig().azimuths * len(BankConfig().elevations)
        bank = views * b * b * 4 * 12  # rgb, depth, alpha as float32, rendered and held twice
        levels = min(64, round((hi - lo) / 0.5) + 1) * views * R * R * 3 * 4
        terms.append(("resolution", R, bank + levels, "image bank and its zoomed copies"))
    name, value = ("views_per_step", V) if V > 1 else ("resolution", R)  # what scales this one most
    terms.append((name, value, V * R * R * 4 * 64, "renders of one step and their gradients"))
    terms.append(("samples_per_step", K, K * V * R * R * 4 * 8, "noise fields and the prior's estimates"))
    n = max(cfg.init_points, cfg.densify.max_gaussians)
    terms.append(("init_points", cfg.init_points, n * 4 * 200, "Gaussians, their gradients and Adam state"))
    return terms


def generate_bytes(cfg) -> tuple[float, str]:
    """(bytes, what) of a training run's big buffers (``generate_terms``)."""
    terms = generate_terms(cfg)
    return sum(b for _, _, b, _ in terms), ", ".join(f"{w} {b / GIB:.2f} GiB" for _, _, b, w in terms)


def check_generate_memory(cfg) -> None:
    _refuse(generate_terms(cfg))


def check_render_memory(size: int, frames: int, gaussians: int = 0) -> None:
    """A turntable holds its frames (uint8 RGB) and one float render with its tile buffers (and,
    for ``demo``, the Gaussians it builds)."""
    if size < 8:
        raise ValueError(f"size: expected at least 8 px, got {size}")
    _refuse([("frames", frames, frames * size * size * 3, f"{frames} frames of {size}x{size} px"),
             ("size", size, size * size * 4 * 48, "the render's buffers"),
             ("gaussians", gaussians, gaussians * 4 * 200, "the Gaussians and their projections")])  # fmt: skip


def check_noise_memory(res: int, n_gaussians: int) -> None:
    """The noise preview: four views of the noise cloud and their per-pixel statistics."""
    _refuse([("res", res, 4 * res * res * 4 * 64, f"four {res}x{res} views and their buffers"),
             ("n_gaussians", n_gaussians, n_gaussians * 4 * 200, "the noise Gaussians")])  # fmt: skip


def check_score_memory(size: int, views: int) -> None:
    """Scoring: COLMAP's views (uint8, written to disk one by one) and one float render."""
    _refuse([("views", views, views * size * size * 3, f"{views} COLMAP views of {size}x{size} px"),
             ("size", size, size * size * 4 * 48, "the render's buffers")])  # fmt: skip
