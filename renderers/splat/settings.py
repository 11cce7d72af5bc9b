"""``RasterSettings``: the renderer's constants in one object, with their documented defaults
(docs/renderer.md), validated once. ``rasterize``, ``prepare`` and the float64 twin take it as
``settings=``, or its fields as keywords (``rasterize(..., alpha_max=0.999)``)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, fields, replace

from . import _checks as ck
from .composite import BlendParams


@dataclass(frozen=True)
class RasterSettings:
    near_plane: float = 0.01
    """Gaussians with camera z at or below this are culled (gsplat's; the Inria 0.2 breaks small scenes)."""
    far_plane: float = 1e10
    eps2d: float = 0.3
    """2D dilation added to the projected covariance (pixels^2)."""
    alpha_min: float = 1.0 / 255.0
    """Gaussians below this alpha at a pixel are skipped there."""
    alpha_max: float = 0.99
    """alpha is clamped here (zero derivative at the clamp)."""
    t_min: float = 1e-4
    """The Gaussian that would bring T below this is not added and the pixel stops."""
    tile_size: int = 16
    chunk_budget: int = 1 << 22
    """Elements of one compositing chunk of the torch backend (memory, not results)."""
    backend: str = "auto"
    """Compositor: 'cpp' (C++/OpenMP, CPU), 'torch' (any device), 'gsplat' (gsplat's CUDA kernels)
    or 'auto' (cpp on CPU, gsplat on CUDA where it runs, else torch)."""

    def __post_init__(self) -> None:
        ck.check_range("near_plane", self.near_plane, 0.0, float("inf"), lo_open=True)
        ck.check_range("far_plane", self.far_plane, self.near_plane, float("inf"), lo_open=True)
        ck.check_range("eps2d", self.eps2d, 0.0, float("inf"))
        ck.check_range("alpha_min", self.alpha_min, 0.0, 1.0, lo_open=True)
        ck.check_range("alpha_max", self.alpha_max, self.alpha_min, 1.0, lo_open=True)
        if self.alpha_max >= 1.0:
            raise ValueError(f"alpha_max: expected a value below 1 (T would reach 0), got {self.alpha_max}")
        ck.check_range("t_min", self.t_min, 0.0, 1.0)
        ck.check_size("tile_size", self.tile_size)
        ck.check_size("chunk_budget", self.chunk_budget)
        if self.backend not in ("auto", "torch", "cpp", "gsplat"):
            raise ValueError(f"backend: expected 'auto', 'torch', 'cpp' or 'gsplat', got {self.backend!r}")

    @property
    def blend(self) -> BlendParams:
        return BlendParams(self.alpha_min, self.alpha_max, self.t_min)

    def projection(self) -> dict[str, float]:
        """The keywords of ``project``."""
        return {"near_plane": self.near_plane, "far_plane": self.far_plane, "eps2d": self.eps2d,
                "alpha_min": self.alpha_min}  # fmt: skip


NAMES = frozenset(f.name for f in fields(RasterSettings))


def resolve_settings(settings: RasterSettings | None, overrides: Mapping[str, object]) -> RasterSettings:
    """``settings`` (default: the documented defaults) with keyword ``overrides`` of its fields."""
    unknown = sorted(set(overrides) - NAMES)
    if unknown:
        raise TypeError(f"unexpected keyword arguments {unknown}; settings are {sorted(NAMES)}")
    if settings is not None and not isinstance(settings, RasterSettings):
        raise TypeError(f"settings: expected a RasterSettings, got {type(settings).__name__}")
    base = settings or RasterSettings()
    return replace(base, **overrides) if overrides else base
