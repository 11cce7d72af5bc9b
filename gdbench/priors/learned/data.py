"""The learned prior's training data: the procedural assets rendered at random continuous cameras.

Every caption of ``assets/library.py`` and each of its procedural variants is rendered by pyrender
(as the image banks are) at ``views`` cameras drawn as the trainer draws its own: azimuth uniform
over the turn, elevation and vertical field of view uniform in the trainer's ranges, on a sphere of
the trainer's radius, white background, 64 px. The set is uniform in azimuth; the front bias of a
model is a sampling weight over its views (``view_weights``: view i drawn with probability
proportional to exp(kappa cos azimuth_i)), so both shipped models learn from the same renders.

Data sets are cached as .npz under ``$GDBENCH_CACHE/learned_data``, keyed by a hash of the settings
and the asset code version (about 12 KB per view: 221 MB for the default 18 x 1024 views, rendered
in about 11 minutes on 2 cores).
"""

from __future__ import annotations

import hashlib
import json
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch


@dataclass(frozen=True)
class DataConfig:
    views: int = 1024
    """Cameras per (caption, variant)."""
    resolution: int = 64
    """Rendered width and height (a 32 px model sees them box-filtered to its size)."""
    seed: int = 0
    """Seed of the cameras."""
    radius: float = 1.0
    """Camera distance (the trainer's --camera-radius)."""
    fovy_range: tuple[float, float] = (40.0, 70.0)
    elevation_range: tuple[float, float] = (-45.0, 45.0)
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    captions: tuple[str, ...] = ()
    """The captions rendered, in catalogue order (empty: the six paper assets, as the first shipped models;
    the shipped world models name theirs in their metadata)."""

    @classmethod
    def from_dict(cls, d: dict) -> DataConfig:
        """The config of ``asdict(config)`` read back from JSON (lists -> tuples)."""
        return cls(**{k: tuple(v) if isinstance(v, list) else v for k, v in d.items()})

    def __post_init__(self) -> None:
        from gdbench.assets.library import check_caption

        for c in self.captions:
            check_caption(c)
        if self.views < 1:
            raise ValueError(f"views: expected at least one camera per asset, got {self.views}")
        if self.resolution < 8:
            raise ValueError(f"resolution: expected at least 8 px, got {self.resolution}")


@dataclass(frozen=True)
class Dataset:
    images: torch.Tensor
    """[N, H, W, 3] uint8."""
    caption: torch.Tensor
    """[N] index into ``captions``."""
    variant: torch.Tensor
    """[N] procedural variant."""
    azimuth: torch.Tensor
    """[N] degrees in [-180, 180)."""
    elevation: torch.Tensor
    fovy: torch.Tensor
    captions: tuple[str, ...]

    def __len__(self) -> int:
        return self.images.shape[0]


def captions(config: DataConfig | None = None) -> tuple[str, ...]:
    """The captions of a data set (default: the six paper assets)."""
    from gdbench.assets.library import ASSETS

    return tuple(config.captions) if config is not None and config.captions else tuple(sorted(ASSETS))


def parts_of(caps: tuple[str, ...]) -> tuple[tuple[tuple[int, ...], ...], tuple[int, ...]]:
    """(rows, sizes) of a compositional model's ``UNetConfig.parts`` for the captions ``caps``:
    kind (over every kind of the catalogue, sorted), body colour, hat colour and scarf colour
    (0: none, then the world's colour names in their order)."""
    from gdbench.assets.families import COLOURS
    from gdbench.assets.library import PARTS

    kinds = sorted({k for k, *_ in PARTS.values()})
    colours = [None, *COLOURS]
    rows = []
    for c in caps:
        kind, colour, hat, scarf = PARTS[c]
        rows.append((kinds.index(kind), colours.index(colour), colours.index(hat), colours.index(scarf)))
    return tuple(rows), (len(kinds), len(colours), len(colours), len(colours))


def data_dir() -> Path:
    from gdbench.assets.bank import cache_dir

    return cache_dir().parent / "learned_data"


def data_key(config: DataConfig) -> str:
    from gdbench.assets.bank import ASSET_VERSION
    from gdbench.assets.library import VARIANTS

    cfg = asdict(config)
    if not config.captions:  # the six: the key as before the field existed
        cfg.pop("captions")
    key = {"config": cfg, "asset_version": ASSET_VERSION, "captions": captions(config), "variants": VARIANTS}
    return hashlib.sha256(json.dumps(key, sort_keys=True).encode()).hexdigest()[:16]


FIELDS = ("images", "caption", "variant", "azimuth", "elevation", "fovy")
"""The arrays of a data set's .npz files (the whole set and its parts)."""


def _write_npz(path: Path, data: Dataset) -> None:
    """A data set (or one part of it) as .npz, atomically."""
    from gdbench.core.io import atomic_write

    path.parent.mkdir(parents=True, exist_ok=True)
    atomic_write(path, lambda f: np.savez(f, **{k: getattr(data, k).numpy() for k in FIELDS}))


def _read_npz(path: Path, caps: tuple[str, ...]) -> Dataset:
    """The data set (or part) ``_write_npz`` wrote, its captions ``caps``."""
    with np.load(path) as z:
        return Dataset(**{k: torch.from_numpy(z[k]) for k in FIELDS}, captions=caps)


def _part_path(parts: Path, caps: tuple[str, ...], caption: str, variant: int) -> Path:
    return parts / f"{caps.index(caption)}-{variant}.npz"


def _one_thread() -> None:
    """A render worker's initializer: one torch thread, and one llvmpipe thread for OSMesa (which
    otherwise starts one per core in every worker; the pixels do not depend on it)."""
    import os

    os.environ.setdefault("LP_NUM_THREADS", "1")
    torch.set_num_threads(1)


def _render_part(job: tuple[DataConfig, str, int, Path]) -> int:
    """A worker's job: one (caption, variant) part rendered and kept at its path."""
    config, caption, variant, path = job
    part = render_subset(config, caption, variant)
    _write_npz(path, part)
    return len(part)


def render_dataset(
    config: DataConfig, *, progress: bool = True, parts: Path | None = None, workers: int = 1
) -> Dataset:
    """Render the data set. Each (caption, variant) draws its cameras from its own generator, seeded
    from ``config.seed`` and its index, so a set is the same whatever renders first (and
    ``render_subset`` gives one part of it alone). With ``parts`` (a folder), each part is kept
    there as it is rendered and read back instead of rendered again: an interrupted render resumes.
    ``workers`` > 1 (with ``parts``) renders the missing parts in that many processes, each with its
    own pyrender context: the same set, in about 1 / workers of the time where there are the cores
    (or a GPU, with ``PYOPENGL_PLATFORM=egl``). The workers are spawned, so they import the caller's
    main module: a script needs an ``if __name__ == "__main__":`` guard, and one read from stdin
    cannot use them."""
    from gdbench.assets.library import VARIANTS

    if workers < 1:
        raise ValueError(f"workers: expected an int >= 1, got {workers}")
    if workers > 1 and parts is None:
        raise ValueError("workers: rendering in several processes needs a parts folder (parts=...)")
    caps = captions(config)
    from gdbench.core.progress import progress as progress_bar

    total = len(caps) * VARIANTS * config.views
    bar = progress_bar(total, "rendering the learned prior's data", "view", disable=not progress)
    try:
        pooled = _render_parts_in_pool(config, caps, parts, workers, bar) if workers > 1 else set()
        done = []
        for c in caps:
            for v in range(VARIANTS):
                path = _part_path(parts, caps, c, v) if parts is not None else None
                counted = path in pooled  # the pool counted its own parts' views
                if path is not None and path.is_file():
                    try:
                        done.append(_read_npz(path, caps))
                        if bar is not None and not counted:
                            bar.update(config.views)
                        continue
                    except Exception:  # an unreadable part is rendered again
                        pass
                part = render_subset(config, c, v, bar=None if counted else bar)
                if path is not None:
                    _write_npz(path, part)
                done.append(part)
    finally:
        if bar is not None:
            bar.close()
    return Dataset(**{k: torch.cat([getattr(p, k) for p in done]) for k in FIELDS}, captions=caps)


def _render_parts_in_pool(config: DataConfig, caps: tuple[str, ...], parts: Path, workers: int, bar) -> set[Path]:
    """The parts not yet in ``parts`` rendered by a pool of ``workers`` processes (spawned: none
    inherits the parent's GL state); the caller then reads every part back, in order. Each job's
    views count on ``bar`` as it finishes; returns the paths rendered here (the caller does not
    count them again)."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor, as_completed

    from gdbench.assets.library import VARIANTS

    paths = [(c, v, _part_path(parts, caps, c, v)) for c in caps for v in range(VARIANTS)]
    jobs = [(config, c, v, path) for c, v, path in paths if not path.is_file()]
    if not jobs:
        return set()
    pool = ProcessPoolExecutor(min(workers, len(jobs)), mp_context=mp.get_context("spawn"), initializer=_one_thread)
    try:
        for fut in as_completed([pool.submit(_render_part, j) for j in jobs]):
            n = fut.result()  # a worker's error is raised here, with the parts done so far kept
            if bar is not None:
                bar.update(n)
    finally:  # an error or a stop signal: the queued parts are cancelled, not rendered to the end
        pool.shutdown(wait=True, cancel_futures=True)
    return {j[3] for j in jobs}


def render_subset(config: DataConfig, caption: str, variant: int, *, bar=None) -> Dataset:
    """The views of one (caption, variant) of the data set of ``config``, exactly as in it."""
    from gdbench.assets.library import VARIANTS, build
    from gdbench.core.camera import SphericalPoses
    from renderers.pyrender_points.mesh import render_mesh

    caps = captions(config)
    if caption not in caps:
        raise ValueError(f"caption: unknown asset {caption!r}; known: {list(caps)}")
    c = caps.index(caption)
    g = torch.Generator().manual_seed(config.seed * 1000 + c * VARIANTS + variant)
    poses = SphericalPoses.sample(
        config.views,
        generator=g,
        radius=config.radius,
        fovy_range=config.fovy_range,
        elevation_range=config.elevation_range,
    )
    R = config.resolution
    pose_gl, K = poses.cameras(R, R).to_opengl()
    mesh = build(caption, variant)
    images = []
    chunk = 128  # one pyrender context per chunk keeps a progress bar moving
    for i in range(0, config.views, chunk):
        rgb, _, _ = render_mesh(
            mesh,
            pose_gl[i : i + chunk].double().numpy(),
            K[i : i + chunk].double().numpy(),
            R,
            R,
            background=config.background,
        )
        images.append(torch.from_numpy(np.round(rgb * 255).astype(np.uint8)))
        if bar is not None:
            bar.update(len(rgb))
    n = config.views
    return Dataset(
        torch.cat(images),
        torch.full((n,), c, dtype=torch.int64),
        torch.full((n,), variant, dtype=torch.int64),
        poses.azimuth.float(),
        poses.elevation.float(),
        poses.fovy.float(),
        caps,
    )


def load_dataset(config: DataConfig | None = None, *, progress: bool = True, workers: int = 1) -> Dataset:
    """The data set of ``config``, from the cache or rendered (in ``workers`` processes) and cached
    atomically."""
    config = config or DataConfig()
    path = data_dir() / f"views-{data_key(config)}.npz"
    if path.is_file():
        try:
            return _read_npz(path, captions(config))
        except Exception as e:  # a corrupt cache entry is rebuilt, never trusted
            print(f"learned-prior data cache {path} unreadable ({type(e).__name__}); rebuilding")
    t0 = time.perf_counter()
    parts = data_dir() / f"parts-{data_key(config)}"
    data = render_dataset(config, progress=progress, parts=parts, workers=workers)
    print(f"rendered {len(data)} views at {config.resolution} px in {time.perf_counter() - t0:.0f} s -> {path}")
    try:
        _write_npz(path, data)
    except OSError as e:
        print(f"GDBENCH_CACHE: cannot write {path.parent} ({e.strerror or e}); the data is rendered again next time")
    else:
        import shutil

        shutil.rmtree(parts, ignore_errors=True)  # the whole set is cached: its parts are not needed
    return data


def view_weights(azimuth: torch.Tensor, front_bias: float) -> torch.Tensor:
    """Sampling weights of views at ``azimuth`` (degrees): exp(kappa cos azimuth), normalised;
    kappa = 0 is uniform."""
    if not (math.isfinite(front_bias) and front_bias >= 0):
        raise ValueError(f"front_bias: expected kappa >= 0, got {front_bias}")
    w = torch.exp(front_bias * torch.cos(torch.deg2rad(azimuth.double())))
    return w / w.sum()


def to_model_images(images: torch.Tensor, size: int) -> torch.Tensor:
    """uint8 [N, H, W, 3] (or float in [0, 1]) -> float [N, 3, size, size] in [-1, 1], box-filtered
    when ``size`` divides H (the 64 px renders seen by a 32 px model)."""
    x = images.float() / 255.0 if images.dtype == torch.uint8 else images.float()
    x = x.permute(0, 3, 1, 2)
    H = x.shape[-1]
    if H != size:
        if H % size:
            raise ValueError(f"size: expected a divisor of the {H} px images, got {size}")
        x = torch.nn.functional.avg_pool2d(x, H // size)
    return x * 2 - 1
