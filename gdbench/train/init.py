"""Initial Gaussians: the paper's sphere, a point cloud from a PLY file (Open3D), or the
prompt's bank depth maps unprojected to points (standing in for Point-E, whose weights are
not available here)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from gdbench.core.scene import GaussianScene, sphere_init


def from_points(points: torch.Tensor, colors: torch.Tensor, n: int, opacity: float, *, generator) -> GaussianScene:
    """n Gaussians on a random subset of the points, isotropic at half the mean spacing."""
    if points.shape[0] == 0:
        raise ValueError("points: the point cloud is empty")
    idx = torch.randperm(points.shape[0], generator=generator)[:n]
    if idx.numel() < n:  # fewer points than requested: repeat with replacement
        extra = torch.randint(points.shape[0], (n - idx.numel(),), generator=generator)
        idx = torch.cat([idx, extra])
    p = points[idx].float()
    extent = float((p.amax(0) - p.amin(0)).max().clamp_min(1e-3))
    s = 0.5 * extent * (1.0 / n) ** (1 / 3)
    return GaussianScene.from_activated(
        p, torch.full((n, 3), s), torch.full((n,), opacity), colors[idx].float().clamp(0, 1)
    )


def from_ply_points(path: Path, n: int, opacity: float, *, generator) -> GaussianScene:
    """A plain point cloud (any PLY/PCD Open3D reads) to n Gaussians; colours default to grey. A
    file that records its up axis (every scene file gdbench writes: ``core.filetags``) is turned
    to +Z up; any other is taken as +Z up."""
    from gdbench.core.filetags import read_tags, up_rotation

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"init_ply: no file at {path}")
    try:
        import open3d as o3d
    except ImportError as e:
        raise ImportError("init='ply' reads point clouds with Open3D: pip install open3d-cpu") from e
    pc = o3d.io.read_point_cloud(str(path))
    pts = torch.from_numpy(np.asarray(pc.points)).float() if len(pc.points) else torch.zeros(0, 3)
    if pts.shape[0] == 0:
        raise ValueError(f"init_ply: {path} holds no points")
    up = read_tags(path).up
    if up not in (None, "+z"):  # rows x R^T turn the file's up axis to +Z: x_ours = R^T x_file
        pts = (pts.double() @ up_rotation(up)).float()
    cols = torch.from_numpy(np.asarray(pc.colors)).float() if pc.has_colors() else torch.full_like(pts, 0.5)
    return from_points(pts, cols, n, opacity, generator=generator)


def from_bank_depth(bank, n: int, opacity: float, *, generator, views: int = 8) -> GaussianScene:
    """Unproject ``views`` evenly spaced bank depth maps (elevation nearest 0) to coloured points."""
    el0 = bank.elevation.abs().min()
    ring = torch.nonzero((bank.elevation.abs() - el0).abs() < 1e-3).squeeze(1)
    pick = ring[torch.linspace(0, ring.numel() - 1, min(views, ring.numel())).round().long()]
    cams = bank.cameras()
    pts, cols = [], []
    H = W = bank.config.resolution
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    for i in pick.tolist():
        z = bank.depth[i]
        ok = (z > 0) & (bank.alpha[i] > 0.99)
        K, V = cams.Ks[i].double(), cams.viewmats[i].double()
        x = (xs[ok] - K[0, 2]) / K[0, 0] * z[ok]
        y = (ys[ok] - K[1, 2]) / K[1, 1] * z[ok]
        pc = torch.stack([x, y, z[ok].double()], -1)
        world = (pc - V[:3, 3]) @ V[:3, :3]  # R^T (p - t)
        pts.append(world.float())
        cols.append(bank.images[i][ok])
    return from_points(torch.cat(pts), torch.cat(cols), n, opacity, generator=generator)


SPHERE_RADIUS = 0.5
"""Radius of the paper's initial ball (the object of interest lies inside radius 0.5)."""


def initial_scene(cfg, *, generator, bank=None) -> GaussianScene:
    if cfg.init == "sphere":
        s = sphere_init(cfg.init_points, SPHERE_RADIUS, cfg.init_color, cfg.init_opacity, generator=generator)
    elif cfg.init == "ply":
        s = from_ply_points(cfg.init_ply, cfg.init_points, cfg.init_opacity, generator=generator)
    elif cfg.init == "bank-depth":
        if bank is None:
            raise ValueError("init='bank-depth' needs the prompt's image bank (the empirical prior)")
        s = from_bank_depth(bank, cfg.init_points, cfg.init_opacity, generator=generator)
    else:
        raise ValueError(f"init: expected 'sphere', 'ply' or 'bank-depth', got {cfg.init!r}")
    return s.with_sh_degree(cfg.sh_degree)


def scene_extent(cfg, *, generator, bank=None) -> float:
    """The scene's radius, the length every world-size setting of the trainer is a fraction of
    (clone/split and world-size prune thresholds, the means' learning rate, the VGS jitter in
    'scene' units): the radius of the paper's initial ball (0.5) for ``init='sphere'``, else the
    radius of the initial point cloud about its centroid: the 99th percentile of the distances (3DGS
    takes the largest distance of its cameras; a percentile lets no stray point of a PLY rescale
    every setting). The cameras' distance does not enter: the prior fixes the object's size in
    world units, and the cameras only look at it from further away."""
    if cfg.init == "sphere":
        return SPHERE_RADIUS
    means = initial_scene(cfg, generator=generator, bank=bank).means.detach().double()
    return max(float(torch.quantile((means - means.mean(0)).norm(dim=-1), 0.99)), 1e-3)
