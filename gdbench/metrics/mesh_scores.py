"""A mesh against the asset's own mesh: Chamfer distance and normal consistency (docs/export.md,
"Meshes"), at the turn about +Z that fits best, as the GT PSNR is (``gt.turned_deg``).

Both surfaces are sampled uniformly by area (``samples`` points each, seeded); each sample's
nearest sample on the other surface gives a distance and the |cosine| of the two face normals.
The asset's mesh is built of overlapping parts (a head sphere half inside a body), so a quarter
of its area is inside the object, where no image and no Gaussian can be: its samples are kept
only where they are seen (``visible``: within ``VISIBLE_TOL`` of the depth the mesh renders to,
pyrender, in one of 64 views around it).
``chamfer`` is the mean of the two directions' mean distances (scene units; the assets fit a
ball of radius 0.45), ``normal_consistency`` the mean |cosine| over both directions (1: the
same orientation everywhere; unsigned, so an inward-facing face counts as aligned).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class MeshScore:
    chamfer: float
    """Mean of the two directions' mean nearest-sample distances, scene units."""
    normal_consistency: float
    """Mean |cos| between the normals of nearest samples, both directions."""
    turned_deg: float
    """The mesh's turn about +Z against the reference, in (-180, 180] (``gt.turned_deg``'s
    convention: a point of the reference at azimuth a lies at a + turned_deg in the mesh)."""
    chamfer_unturned: float
    """``chamfer`` of the mesh as it is."""


VISIBLE_TOL = 0.004
"""Scene units (about 1% of an asset's radius, a third of a pixel at 256 px) between a sample's
depth and the rendered depth for the sample to count as seen."""


def visible(mesh, points: np.ndarray, *, views: int = 64, size: int = 256) -> np.ndarray:
    """[P] bool: whether each of ``points`` (on ``mesh``'s surface) is seen in one of ``views``
    views spread over a sphere around the mesh (``core.framing.sphere_cameras``, framed as the mesh
    export frames a scene), by the depth pyrender renders (``renderers.pyrender_points.mesh``)."""
    import torch

    from gdbench.core.framing import orbit_radius, sphere_cameras
    from renderers.pyrender_points.mesh import render_mesh

    lo, hi = mesh.bounds
    centre = torch.from_numpy((lo + hi) / 2)
    radius = float(np.linalg.norm(hi - lo) / 2)
    cams = sphere_cameras(centre, orbit_radius(radius, 45.0), views, size)
    pose_gl, K = cams.to_opengl()
    _, depth, _ = render_mesh(mesh, pose_gl.double().numpy(), K.double().numpy(), size, size, supersample=1)
    seen = np.zeros(len(points), dtype=bool)
    V = cams.viewmats.double().numpy()
    Ks = cams.Ks.double().numpy()
    for k in range(views):
        cam = points @ V[k, :3, :3].T + V[k, :3, 3]
        z = cam[:, 2]
        uv = cam[:, :2] / np.maximum(z, 1e-9)[:, None] * [Ks[k, 0, 0], Ks[k, 1, 1]] + [Ks[k, 0, 2], Ks[k, 1, 2]]
        px = np.floor(uv).astype(np.int64)
        inside = (z > 0) & (px[:, 0] >= 0) & (px[:, 0] < size) & (px[:, 1] >= 0) & (px[:, 1] < size)
        d = np.zeros(len(points))
        d[inside] = depth[k, px[inside, 1], px[inside, 0]]
        seen |= inside & (d > 0) & (np.abs(d - z) <= VISIBLE_TOL)
    return seen


def _sample(mesh, samples: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    import trimesh

    points, faces = trimesh.sample.sample_surface(mesh, samples, seed=seed)
    return np.asarray(points, dtype=np.float64), np.asarray(mesh.face_normals[faces], dtype=np.float64)


def _directional(a: np.ndarray, na: np.ndarray, tree_b, nb: np.ndarray) -> tuple[float, float]:
    d, j = tree_b.query(a)
    return float(d.mean()), float(np.abs((na * nb[j]).sum(1)).mean())


def mesh_scores(mesh, reference, *, samples: int = 20000, seed: int = 0, step_deg: float = 5.0) -> MeshScore:
    """``mesh`` against ``reference`` (both ``trimesh.Trimesh``, +Z up, the same frame): Chamfer and
    normal consistency of ``mesh`` turned about +Z by the multiple of ``step_deg`` that gives the
    lowest Chamfer distance (module docstring)."""
    from scipy.spatial import cKDTree

    for name, m in (("mesh", mesh), ("reference", reference)):
        if len(getattr(m, "faces", ())) == 0:
            raise ValueError(f"{name}: expected a triangle mesh with faces")
    if isinstance(samples, bool) or not isinstance(samples, int) or samples < 100:
        raise ValueError(f"samples: expected an int >= 100, got {samples!r}")
    p, n = _sample(mesh, samples, seed)
    q, nq = _sample(reference, 2 * samples, seed + 1)
    seen = visible(reference, q)
    q, nq = q[seen][:samples], nq[seen][:samples]
    tree_q = cKDTree(q)
    best = None
    unturned = math.nan
    for k in range(round(360 / step_deg)):
        t = math.radians(k * step_deg)
        rot = np.array([[math.cos(t), -math.sin(t), 0.0], [math.sin(t), math.cos(t), 0.0], [0.0, 0.0, 1.0]])
        pr, nr = p @ rot.T, n @ rot.T
        d_pq, c_pq = _directional(pr, nr, tree_q, nq)
        d_qp, c_qp = _directional(q, nq, cKDTree(pr), nr)
        chamfer = 0.5 * (d_pq + d_qp)
        if k == 0:
            unturned = chamfer
        if best is None or chamfer < best[0]:
            best = (chamfer, 0.5 * (c_pq + c_qp), k * step_deg)
    from gdbench.metrics.gt import turned_deg

    # the mesh turned back by t fits: it lies turned by -t against the reference
    return MeshScore(best[0], best[1], turned_deg(-best[2]), unturned)


def surface_gaussians(mesh, n: int, *, colours=None, seed: int = 0):
    """``n`` flat opaque Gaussians (0.006 across, 0.0005 thick, opacity 0.95) laid on ``mesh``'s
    surface (area-uniform samples, seeded), facing along its face normals: a scene whose right
    mesh is ``mesh``, the floor of what a fusion of its renders can give. Coloured by
    ``colours(points)`` ([n, 3] in [0, 1]), or by the mesh's face colours."""
    import torch
    import trimesh
    from scipy.spatial.transform import Rotation

    from gdbench.core.scene import GaussianScene

    pts, faces = trimesh.sample.sample_surface(mesh, n, seed=seed)
    z = np.asarray(mesh.face_normals[faces], dtype=np.float64)
    a = np.where(np.abs(z[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]])
    x = np.cross(a, z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    xyzw = Rotation.from_matrix(np.stack([x, np.cross(z, x), z], -1)).as_quat()
    rgb = colours(pts) if colours is not None else np.asarray(mesh.visual.face_colors[faces][:, :3]) / 255
    return GaussianScene.from_activated(
        torch.from_numpy(np.asarray(pts, dtype=np.float32)),
        torch.tensor([0.006, 0.006, 0.0005]).expand(n, 3).clone(),
        torch.full((n,), 0.95),
        torch.from_numpy(np.asarray(rgb, dtype=np.float32)),
        quats=torch.from_numpy(xyzw[:, [3, 0, 1, 2]].astype(np.float32)),
    )
