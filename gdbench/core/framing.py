"""Framing a scene that did not come from a run: its bounds, and the orbit that shows it whole.

A run's scenes live in the unit ball around the origin and are shown from the run's turntable
orbit (``turntable.RUN_TURNTABLE``). A PLY from elsewhere (an Inria capture, a scene another
tool made) may sit anywhere at any size: ``frame(scene, fovy)`` moves its centre to the origin
and gives the orbit radius at which its bounding ball fills the frame.
"""

from __future__ import annotations

import dataclasses
import math

import torch

from gdbench.core.scene import GaussianScene


def bounds(scene: GaussianScene, quantile: float = 0.98, min_opacity: float = 0.05) -> tuple[torch.Tensor, float]:
    """(centre [3], radius) of the scene's visible Gaussians: the centre of their per-axis
    ``1 - quantile``..``quantile`` box, and the ``quantile`` of their distances from it plus three
    standard deviations of their largest axis (a few far-off floaters do not shrink the object)."""
    if len(scene) == 0:
        raise ValueError("scene: has no Gaussians to frame")
    visible = scene.opacities >= min_opacity
    if int(visible.sum()) < 1:
        visible = torch.ones_like(visible)
    m = scene.means[visible].double()
    s = scene.scales[visible].double().amax(dim=1)
    if len(m) > 1_000_000:  # torch.quantile takes at most 2^24 values: a fixed subsample
        keep = torch.randperm(len(m), generator=torch.Generator().manual_seed(0))[:1_000_000]
        m, s = m[keep.to(m.device)], s[keep.to(s.device)]
    q = torch.tensor([1.0 - quantile, quantile], dtype=m.dtype, device=m.device)
    box = torch.quantile(m, q, dim=0)
    centre = box.mean(0)
    d = (m - centre).norm(dim=1) + 3.0 * s
    radius = float(torch.quantile(d, quantile)) if len(d) > 1 else float(d[0])
    return centre.to(scene.means.dtype), max(radius, 1e-6)


def orbit_radius(object_radius: float, fovy: float, margin: float = 1.1) -> float:
    """Camera distance at which a ball of ``object_radius`` fills a ``fovy``-degree frame (with
    ``margin``)."""
    if not 0 < fovy < 180:
        raise ValueError(f"fovy: expected degrees in (0, 180), got {fovy}")
    return margin * object_radius / math.sin(math.radians(fovy) / 2)


def frame(scene: GaussianScene, fovy: float) -> tuple[GaussianScene, float]:
    """The scene moved so that its centre is the origin, and the orbit radius that frames it."""
    centre, radius = bounds(scene)
    moved = dataclasses.replace(scene, means=scene.means - centre)
    return moved, orbit_radius(radius, fovy)


def sphere_cameras(centre: torch.Tensor, distance: float, views: int, size: int, fovy: float = 45.0):
    """``views`` cameras on a Fibonacci lattice of the sphere of radius ``distance`` about
    ``centre``, each looking at it, ``size`` px square (``core.camera.Cameras``)."""
    from gdbench.core.camera import Cameras, intrinsics, look_at

    i = torch.arange(views, dtype=torch.float64) + 0.5
    z = 1.0 - 2.0 * i / views
    phi = i * math.pi * (3.0 - math.sqrt(5.0))
    r = torch.sqrt(1.0 - z * z)
    dirs = torch.stack([r * torch.cos(phi), r * torch.sin(phi), z], -1)
    c = centre.detach().to("cpu", torch.float64)
    eyes = c + distance * dirs
    viewmats = look_at(eyes, c.expand_as(eyes)).float()
    Ks = intrinsics(torch.full((views,), fovy), size, size)
    return Cameras(viewmats, Ks, size, size)
