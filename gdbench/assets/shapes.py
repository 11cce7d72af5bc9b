"""Mesh primitives with procedural vertex colours, for the built-in assets.

Every part is a trimesh mesh whose vertices carry RGBA colours from a colour function
``f(points [V, 3] in the part's local frame) -> rgb [V, 3]`` in [0, 1]. Patterns (spots,
stripes, checks, value noise) give SIFT something to hold on to.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

ColorFn = Callable[[np.ndarray], np.ndarray]


def solid(rgb) -> ColorFn:
    c = np.asarray(rgb, dtype=np.float64)
    return lambda p: np.broadcast_to(c, (len(p), 3)).copy()


def value_noise(p: np.ndarray, freq: float, seed: int) -> np.ndarray:
    """Smooth deterministic noise in [-1, 1]: a sum of 6 random plane waves."""
    rng = np.random.default_rng(seed)
    dirs = rng.normal(size=(6, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    phase = rng.uniform(0, 2 * np.pi, 6)
    return np.sin(freq * p @ dirs.T + phase).mean(1) * 1.6


def mottled(rgb, amount: float = 0.12, freq: float = 25.0, seed: int = 0) -> ColorFn:
    """A base colour with a smooth brightness texture."""
    base = np.asarray(rgb, dtype=np.float64)
    return lambda p: np.clip(base[None] * (1 + amount * value_noise(p, freq, seed))[:, None], 0, 1)


def spots(base, spot, radius: float = 0.025, count: int = 40, extent: float = 0.5, seed: int = 0) -> ColorFn:
    rng = np.random.default_rng(seed)
    centres = rng.uniform(-extent, extent, size=(count, 3))
    b, s = np.asarray(base, float), np.asarray(spot, float)

    def f(p):
        d = np.linalg.norm(p[:, None, :] - centres[None], axis=-1).min(1)
        t = np.clip((radius - d) / (0.3 * radius), 0, 1)[:, None]
        return (1 - t) * b + t * s

    return f


def stripes(c1, c2, axis: int = 2, period: float = 0.06) -> ColorFn:
    a, b = np.asarray(c1, float), np.asarray(c2, float)
    return lambda p: np.where(((p[:, axis] / period) % 1.0 < 0.5)[:, None], a, b)


def checker(c1, c2, period: float = 0.08) -> ColorFn:
    a, b = np.asarray(c1, float), np.asarray(c2, float)
    return lambda p: np.where((np.floor(p / period).sum(1) % 2 == 0)[:, None], a, b)


SPECKLES_PER_AREA = 450
"""Dark and light speckles (each) per unit of surface area on every part. Without them SIFT finds
only 20-60 features per 256 px view of these smooth toys and COLMAP registers 2 views of 100
(measured); speckles a few pixels wide are the blobs SIFT detects."""


def _detail(mesh, seed: int) -> np.ndarray:
    """Brightness factor per vertex: 0.5 inside dark speckles, 1.4 inside light ones, else 1."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(seed)
    v = np.asarray(mesh.vertices)
    n = max(4, int(SPECKLES_PER_AREA * float(mesh.area)))
    out = np.ones(len(v))
    for factor, radius in ((0.5, 0.012), (1.4, 0.009)):
        centres = v[rng.choice(len(v), size=min(n, len(v)), replace=False)]
        d, _ = cKDTree(centres).query(v)
        t = np.clip((radius - d) / (0.4 * radius), 0, 1)
        out = out * (1 + (factor - 1) * t)
    return out


def _finish(mesh, color: ColorFn, transform: np.ndarray | None):
    p = np.asarray(mesh.vertices)
    base = color(p)
    seed = int(abs(hash(tuple(np.round(base.mean(0), 3)))) % 10_000)  # varies with the part's colour, deterministic
    rgb = np.clip(base * _detail(mesh, seed)[:, None], 0, 1)
    mesh.visual.vertex_colors = np.concatenate([np.round(rgb * 255), np.full((len(rgb), 1), 255)], 1).astype(np.uint8)
    if transform is not None:
        mesh.apply_transform(transform)
    return mesh


def pose(center=(0, 0, 0), rotate: tuple[str, float] | None = None) -> np.ndarray:
    """4x4 transform: optional rotation (axis letter, degrees) then translation."""
    import trimesh

    T = np.eye(4)
    if rotate is not None:
        axis = {"x": [1, 0, 0], "y": [0, 1, 0], "z": [0, 0, 1]}[rotate[0]]
        T = trimesh.transformations.rotation_matrix(np.deg2rad(rotate[1]), axis)
    T[:3, 3] = center
    return T


def ellipsoid(center, radii, color: ColorFn, rotate=None, subdivisions: int = 5):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=1.0)
    m.vertices = m.vertices * np.asarray(radii)[None]
    return _finish(m, color, pose(center, rotate))


def box(center, extents, color: ColorFn, rotate=None, subdivisions: int = 4):
    import trimesh

    m = trimesh.creation.box(extents=extents)
    for _ in range(subdivisions):
        m = m.subdivide()
    return _finish(m, color, pose(center, rotate))


def cylinder(center, radius, height, color: ColorFn, rotate=None, sections: int = 48):
    import trimesh

    m = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    m = m.subdivide().subdivide().subdivide()
    return _finish(m, color, pose(center, rotate))


def cone(center, radius, height, color: ColorFn, rotate=None, sections: int = 40):
    import trimesh

    m = trimesh.creation.cone(radius=radius, height=height, sections=sections)
    m = m.subdivide().subdivide()
    return _finish(m, color, pose(center, rotate))


def front(mesh):
    """``mesh`` marked as a part of the asset's front (a face, a beak: ``assets.library.FRONTS``);
    ``combine`` keeps the mark per vertex in ``metadata['front']`` (the Janus classes' front test,
    ``metrics.views``). The geometry and colours are unchanged."""
    mesh.metadata["front"] = True
    return mesh


def _front_marks(part) -> np.ndarray:
    """A bool per vertex of ``part``: whether it belongs to the asset's front (``front``)."""
    mark = part.metadata.get("front", False)
    return np.full(len(part.vertices), bool(mark)) if np.ndim(mark) == 0 else np.asarray(mark, bool)


def combine(parts, fit_radius: float = 0.45):
    """Concatenate parts, centre the bounding box at the origin and scale to ``fit_radius``; the
    vertices of parts marked by ``front`` are listed in ``metadata['front']`` (a bool per vertex)."""
    import trimesh

    marks = np.concatenate([_front_marks(p) for p in parts])
    m = trimesh.util.concatenate(parts)
    m.metadata["front"] = marks
    lo, hi = m.bounds
    m.apply_translation(-(lo + hi) / 2)
    r = np.linalg.norm(m.vertices, axis=1).max()
    m.apply_scale(fit_radius / r)
    return m
