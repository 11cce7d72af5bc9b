"""Gaussian centres as OpenGL points (pyrender, offscreen): an independent check of the camera,
projection and depth conventions.

Each centre is drawn as a 1-pixel point, unlit, its index encoded in its 24-bit colour, at
``supersample`` times the resolution. A point at window position (x, y) lands in the pixel
containing it, so the decoded centre ``(i + 0.5) / supersample`` is within ``0.5 /
supersample`` px of the true projection (0.03 px at the default 16); depth comes from
pyrender's linearised depth buffer (camera z). Centres hidden behind another centre in the
same subpixel, behind the camera or outside the image come back as NaN.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor

from ._lib import import_pyrender

_GL_FROM_CV = np.diag([1.0, -1.0, -1.0, 1.0])


class PointsOutput(NamedTuple):
    means2d: Tensor
    """[C, N, 2] pixel coordinates of the centres (pixel centres at +0.5), NaN where not seen."""
    depths: Tensor
    """[C, N] camera z of the centres, NaN where not seen."""


def render_points(
    means: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    supersample: int = 16,
    znear: float | None = None,
    zfar: float | None = None,
) -> PointsOutput:
    """Project centres by OpenGL rasterisation. ``znear``/``zfar`` default to half the nearest
    and twice the farthest centre depth of each camera: the depth buffer has 24 bits, and its
    resolution at z is about z^2 / znear * 2^-24, so a tight range keeps depths within ~1e-7."""
    pr = import_pyrender()
    N, C = means.shape[0], viewmats.shape[0]
    if N >= 2**24 - 1:
        raise ValueError(f"means: at most {2**24 - 2} points can be told apart by colour, got {N}")
    ids = np.arange(1, N + 1)
    cols = np.stack([(ids >> 16) & 255, (ids >> 8) & 255, ids & 255], 1) / 255.0
    scene = pr.Scene(bg_color=[0.0, 0.0, 0.0, 0.0], ambient_light=[1.0, 1.0, 1.0])
    scene.add(pr.Mesh.from_points(means.detach().double().cpu().numpy(), colors=cols))
    S = supersample
    r = pr.OffscreenRenderer(width * S, height * S, point_size=1.0)
    uv = torch.full((C, N, 2), float("nan"), dtype=torch.float64)
    z = torch.full((C, N), float("nan"), dtype=torch.float64)
    try:
        for c in range(C):
            K = Ks[c].double().cpu().numpy()
            zc = means.detach().double().cpu() @ viewmats[c, 2, :3].double().cpu() + float(viewmats[c, 2, 3])
            front = zc[zc > 1e-6]
            if front.numel() == 0:
                continue
            near = znear if znear is not None else max(1e-4, 0.5 * float(front.min()))
            far = zfar if zfar is not None else 2.0 * float(front.max()) + 1e-3
            cam = pr.IntrinsicsCamera(K[0, 0] * S, K[1, 1] * S, K[0, 2] * S, K[1, 2] * S, znear=near, zfar=far)
            pose = np.linalg.inv(viewmats[c].double().cpu().numpy()) @ _GL_FROM_CV
            node = scene.add(cam, pose=pose)
            color, depth = r.render(scene, flags=pr.RenderFlags.FLAT)
            scene.remove_node(node)
            ys, xs = np.nonzero(depth > 0)
            idx = (
                (color[ys, xs, 0].astype(np.int64) << 16) | (color[ys, xs, 1].astype(np.int64) << 8) | color[ys, xs, 2]
            )
            good = (idx >= 1) & (idx <= N)
            n = idx[good] - 1
            uv[c, n, 0] = torch.from_numpy((xs[good] + 0.5) / S)
            uv[c, n, 1] = torch.from_numpy((ys[good] + 0.5) / S)
            z[c, n] = torch.from_numpy(depth[ys[good], xs[good]].astype(np.float64))
    finally:
        r.delete()
    return PointsOutput(uv, z)
