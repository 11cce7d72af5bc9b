"""Render vertex-coloured meshes with pyrender: rgb, camera-space depth z and coverage.

Cameras come in as OpenGL camera-to-world poses and pinhole intrinsics (pixels, top-left
origin, as ``gdbench.core.camera.Cameras.to_opengl`` gives them). Lighting: ambient plus a
headlight, so shading depends on the view like a real capture but the colours stay
recognisable. ``supersample`` renders at that factor and box-filters down (antialiasing).
"""

from __future__ import annotations

import numpy as np

from ._lib import import_pyrender


def render_mesh(
    mesh,
    poses_gl: np.ndarray,
    Ks: np.ndarray,
    width: int,
    height: int,
    *,
    background=(1.0, 1.0, 1.0),
    ambient: float = 0.45,
    headlight: float = 2.2,
    supersample: int = 2,
    znear: float = 0.01,
    zfar: float = 100.0,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Returns rgb [C, H, W, 3] float32 in [0, 1], depth [C, H, W] (z, 0 where empty) and
    alpha [C, H, W] (fraction of subsamples covered)."""
    pr = import_pyrender()
    s = supersample
    scene = pr.Scene(bg_color=[*background, 0.0], ambient_light=[ambient] * 3)
    scene.add(pr.Mesh.from_trimesh(mesh, smooth=False))
    renderer = pr.OffscreenRenderer(width * s, height * s)
    rgbs, depths, alphas = [], [], []
    try:
        for pose, K in zip(poses_gl, Ks):
            cam = pr.IntrinsicsCamera(K[0, 0] * s, K[1, 1] * s, K[0, 2] * s, K[1, 2] * s, znear=znear, zfar=zfar)
            cn = scene.add(cam, pose=pose)
            ln = scene.add(pr.DirectionalLight(color=np.ones(3), intensity=headlight), pose=pose)
            color, depth = renderer.render(scene, flags=pr.RenderFlags.RGBA)
            scene.remove_node(cn)
            scene.remove_node(ln)
            rgb = color[..., :3].astype(np.float32) / 255.0
            hit = depth > 0
            rgb = np.where(hit[..., None], rgb, np.asarray(background, np.float32))
            pool = lambda x: x.reshape(height, s, width, s, *x.shape[2:]).mean((1, 3))  # noqa: E731
            cover = pool(hit.astype(np.float32))
            dsum = pool(depth.astype(np.float64))
            rgbs.append(pool(rgb))
            alphas.append(cover)
            depths.append(np.where(cover > 0, dsum / np.maximum(cover, 1e-9), 0.0).astype(np.float32))
    finally:
        renderer.delete()
    return np.stack(rgbs), np.stack(depths), np.stack(alphas)
