"""Image banks: an asset rendered by pyrender over a grid of views, cached on disk.

A bank holds, for V = azimuths x elevations views on a sphere of radius ``radius``:
rgb [V, H, W, 3] in [0, 1] on the training background, camera-space depth z [V, H, W]
(0 where empty), coverage alpha [V, H, W], and the view angles. Banks are cached as .npz
under ``$GDBENCH_CACHE`` (default ``~/.cache/gdbench``)/banks, keyed by a hash of the caption,
the settings and the asset code version; the build time is printed when one is built.
"""

from __future__ import annotations

import hashlib
import json
import time
import warnings
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from gdbench.core.camera import SphericalPoses

ASSET_VERSION = 3  # bump when the meshes, their front marks or the lighting change: old caches are then ignored


@dataclass(frozen=True)
class BankConfig:
    resolution: int = 128
    """Image width and height (2x the 64 px training renders: a query at fovy 40 zooms into the
    central 52% of a 70-degree bank image and still finds 67 source pixels across)."""
    azimuths: int = 72
    """Views per turn (360/azimuths degrees apart), starting at azimuth 0 (the front)."""
    elevations: tuple[float, ...] = (-40.0, -20.0, 0.0, 20.0, 40.0)
    """Elevation rings in degrees (the training range is [-45, 45])."""
    radius: float = 1.0
    fovy: float = 70.0
    """Vertical field of view (degrees): the widest of the paper's 40-70 range; the prior zooms
    the bank to each query's field of view (``assets/zoom.py``)."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        if self.resolution < 8:
            raise ValueError(f"resolution: expected at least 8 px, got {self.resolution}")
        if self.azimuths < 1 or not self.elevations:
            raise ValueError("azimuths, elevations: expected at least one view")
        if any(not -90 < e < 90 for e in self.elevations):
            raise ValueError(f"elevations: expected degrees inside (-90, 90), got {self.elevations}")

    def poses(self) -> SphericalPoses:
        az = torch.arange(self.azimuths, dtype=torch.float64) * (360.0 / self.azimuths)
        az = (az + 180.0) % 360.0 - 180.0
        el = torch.tensor(self.elevations, dtype=torch.float64)
        A, E = torch.meshgrid(az, el, indexing="ij")
        n = A.numel()
        return SphericalPoses(
            A.reshape(-1),
            E.reshape(-1),
            torch.full((n,), self.radius, dtype=torch.float64),
            torch.full((n,), self.fovy, dtype=torch.float64),
        )


@dataclass(frozen=True)
class Bank:
    caption: str
    config: BankConfig
    images: torch.Tensor
    """[V, H, W, 3] float32 in [0, 1]."""
    depth: torch.Tensor
    """[V, H, W] camera-space z, 0 where empty."""
    alpha: torch.Tensor
    """[V, H, W] coverage in [0, 1]."""
    azimuth: torch.Tensor
    """[V] degrees in [-180, 180)."""
    elevation: torch.Tensor
    """[V] degrees."""

    def __len__(self) -> int:
        return self.images.shape[0]

    def subset(self, index: torch.Tensor) -> Bank:
        return Bank(
            self.caption,
            self.config,
            self.images[index],
            self.depth[index],
            self.alpha[index],
            self.azimuth[index],
            self.elevation[index],
        )

    def cameras(self):
        return self.config.poses().cameras(self.config.resolution, self.config.resolution)


def cache_dir() -> Path:
    from gdbench.core.cache import root

    return root() / "banks"


def bank_key(caption: str, config: BankConfig, variant: int = 0) -> str:
    key = {"caption": caption, "config": asdict(config), "version": ASSET_VERSION}
    if variant:
        key["variant"] = variant
    blob = json.dumps(key, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def render_bank(caption: str, config: BankConfig, variant: int = 0) -> Bank:
    """Render the bank of ``caption`` (procedural variant ``variant``), without the cache."""
    from gdbench.assets.library import build
    from renderers.pyrender_points.mesh import render_mesh

    mesh = build(caption, variant)
    poses = config.poses()
    cams = poses.cameras(config.resolution, config.resolution)
    pose_gl, K = cams.to_opengl()
    rgb, depth, alpha = render_mesh(
        mesh,
        pose_gl.double().numpy(),
        K.double().numpy(),
        config.resolution,
        config.resolution,
        background=config.background,
    )
    return Bank(
        caption,
        config,
        torch.from_numpy(rgb),
        torch.from_numpy(depth),
        torch.from_numpy(alpha),
        poses.azimuth.float(),
        poses.elevation.float(),
    )


def bank_path(caption: str, config: BankConfig, variant: int = 0) -> Path:
    """Where the bank of ``caption`` (variant ``variant``) is cached."""
    return cache_dir() / f"{caption.replace(' ', '_')}-{bank_key(caption, config, variant)}.npz"


def cached(caption: str, config: BankConfig, variant: int = 0) -> bool:
    """Whether the bank is in the cache (not whether it reads: ``load_bank`` checks that)."""
    return bank_path(caption, config, variant).is_file()


def load_bank(caption: str, config: BankConfig | None = None, *, variant: int = 0, verbose: bool = True) -> Bank:
    """The bank of ``caption`` (variant ``variant``), from the cache or rendered (and cached atomically)."""
    from gdbench.assets.library import check_caption

    config = config or BankConfig()
    check_caption(caption)
    path = bank_path(caption, config, variant)
    if path.is_file():
        try:
            with np.load(path) as z:
                return Bank(
                    caption,
                    config,
                    *(torch.from_numpy(z[k]) for k in ("images", "depth", "alpha", "azimuth", "elevation")),
                )
        except Exception as e:  # a corrupt cache entry is rebuilt, never trusted
            if verbose:
                print(f"bank cache {path} unreadable ({type(e).__name__}); rebuilding")
    t0 = time.perf_counter()
    bank = render_bank(caption, config, variant)
    if verbose:
        took = time.perf_counter() - t0
        print(f"built bank '{caption}' (variant {variant}): {len(bank)} views at {config.resolution}px in {took:.1f} s")
    _cache_write(path, bank, verbose)
    return bank


def _cache_write(path: Path, bank: Bank, verbose: bool) -> None:
    """Cache a bank atomically; a cache folder that cannot be written costs the cache, not the run."""
    arrays = {k: getattr(bank, k).numpy() for k in ("images", "depth", "alpha", "azimuth", "elevation")}
    _write_npz(path, arrays, "the bank")


def _write_npz(path: Path, arrays: dict[str, np.ndarray], what: str) -> None:
    from gdbench.core.io import atomic_write

    try:
        atomic_write(path, lambda f: np.savez(f, **arrays))
    except OSError as e:
        warnings.warn(
            f"GDBENCH_CACHE: cannot write the bank cache {path.parent} ({e.strerror or e}); {what} is "
            "rebuilt in every process until GDBENCH_CACHE points at a writable folder",
            stacklevel=4,
        )


def cached_arrays(name: str, key: dict, build, *, version: int, fields: tuple[str, ...]) -> dict[str, np.ndarray]:
    """Arrays derived from an asset (``build()``, a dict of the numpy arrays ``fields``), cached
    beside the banks under a hash of ``key``, ``version`` (the caller's: bump it when ``build``
    changes) and the asset code version: the surface palette of the prompt check, the held-out
    views of the ground-truth score. The same arrays, bit for bit, as ``build()`` (npz keeps dtypes
    and values); an unreadable entry, or one without ``fields``, is rebuilt, never trusted."""
    blob = json.dumps(key | {"version": ASSET_VERSION, "build_version": version}, sort_keys=True)
    path = cache_dir() / f"{name}-{hashlib.sha256(blob.encode()).hexdigest()[:16]}.npz"
    if path.is_file():
        try:
            with np.load(path) as z:
                if set(z.files) == set(fields):
                    return {k: z[k] for k in fields}
        except Exception:  # a corrupt entry: rebuilt below
            pass
    arrays = build()
    _write_npz(path, arrays, name)
    return arrays
