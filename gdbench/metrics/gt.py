"""Ground-truth scores for runs on the empirical prior: PSNR (and SSIM) of the scene against
its procedural asset at held-out poses, after the best azimuth alignment.

Held-out poses avoid the bank's grid: elevation 15 degrees (the bank has -40, -20, 0, 20,
40) and azimuths 17.5 + 30 k (the bank's are multiples of 5 from 0; 15 + 30 k before
2026-11-25 lay on them). SSIM is the standard one (11x11 Gaussian window; a 7x7 uniform window
before 2026-11-25, so earlier SSIM figures are not comparable). Score distillation may
produce the object turned about +Z, so the scene is scored at every azimuth offset in
``offsets`` (degrees) and the best mean PSNR is kept; the offset is reported.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from gdbench.core.camera import SphericalPoses
from gdbench.core.scene import GaussianScene


@dataclass(frozen=True)
class GTScore:
    psnr: float
    """Mean PSNR (dB) over held-out views at the best azimuth offset."""
    ssim: float
    offset_deg: float
    psnr_unaligned: float
    """Mean PSNR at offset 0."""


def heldout_poses(n: int = 12, elevation: float = 15.0, radius: float = 1.0, fovy: float = 55.0) -> SphericalPoses:
    """``n`` poses on a ring at ``elevation``, azimuths 17.5 + k 360/n: midway between the bank's
    5-degree azimuths (and its elevations -40, -20, 0, 20, 40), so no held-out view is a bank view."""
    return SphericalPoses.orbit(n, radius=radius, elevation=elevation, fovy=fovy, start=17.5)


def psnr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """PSNR per image of [C, H, W, 3] images in [0, 1]."""
    mse = ((a - b) ** 2).flatten(1).mean(1).clamp_min(1e-10)
    return -10 * torch.log10(mse)


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM per image of [C, H, W, 3] images in [0, 1]: the standard one (Wang et al. 2004,
    as papers report it): an 11x11 Gaussian window of sigma 1.5 over the valid region, per
    channel, K1 = 0.01, K2 = 0.03, data range 1 (pytorch-msssim's ``ssim``, its test oracle)."""
    import torch.nn.functional as F

    x, y = a.permute(0, 3, 1, 2).double(), b.permute(0, 3, 1, 2).double()
    r = torch.arange(window, dtype=torch.float64) - (window - 1) / 2
    g = torch.exp(-(r**2) / (2 * sigma**2))
    g = (g / g.sum()).to(x.device)
    ch = x.shape[1]

    def blur(t):  # separable Gaussian, valid region, each channel on its own
        t = F.conv2d(t, g.view(1, 1, 1, -1).expand(ch, 1, 1, window), groups=ch)
        return F.conv2d(t, g.view(1, 1, -1, 1).expand(ch, 1, window, 1), groups=ch)

    mx, my = blur(x), blur(y)
    vx, vy, cxy = blur(x * x) - mx**2, blur(y * y) - my**2, blur(x * y) - mx * my
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mx * my + c1) * (2 * cxy + c2)) / ((mx**2 + my**2 + c1) * (vx + vy + c2))
    return s.flatten(1).mean(1).float()


def asset_views(
    caption: str, poses: SphericalPoses, size: int, background=(1.0, 1.0, 1.0), variant: int = 0
) -> torch.Tensor:
    """The asset (procedural variant ``variant``) rendered by pyrender at ``poses``: [C, H, W, 3] in
    [0, 1]; cached on disk beside the banks (the same bits: a render takes 1-2 s with the mesh)."""
    from gdbench.assets.bank import cached_arrays

    def build() -> dict:
        from gdbench.assets.library import build
        from renderers.pyrender_points.mesh import render_mesh

        cams = poses.cameras(size, size)
        pose_gl, K = cams.to_opengl()
        mesh = build(caption, variant)
        rgb, _, _ = render_mesh(mesh, pose_gl.double().numpy(), K.double().numpy(), size, size, background=background)
        return {"rgb": rgb}

    key = {"caption": caption, "variant": variant, "size": size, "background": [float(c) for c in background]}
    key |= {k: getattr(poses, k).double().tolist() for k in ("azimuth", "elevation", "radius", "fovy")}
    return torch.from_numpy(cached_arrays("heldout", key, build, version=1, fields=("rgb",))["rgb"])


def score_against_asset(
    scene: GaussianScene,
    caption: str,
    *,
    size: int = 64,
    n_views: int = 12,
    offsets: torch.Tensor | None = None,
    background=(1.0, 1.0, 1.0),
    reference: torch.Tensor | None = None,
    variant: int = 0,
) -> GTScore:
    """PSNR/SSIM of ``scene`` against the asset at held-out poses, best over azimuth offsets.

    ``reference`` (the asset views) can be passed to score many scenes against one rendering.
    """
    from gdbench.core.turntable import render_views

    poses = heldout_poses(n_views)
    ref = reference if reference is not None else asset_views(caption, poses, size, background, variant)
    offsets = offsets if offsets is not None else torch.arange(0, 360, 5, dtype=torch.float64)
    if len(offsets) == 0:
        raise ValueError("offsets: expected at least one azimuth offset")
    # every offset's views are azimuths + offset: with the default ring and offsets, 138 distinct
    # angles among 864 views (17.5 + 30 k + 5 j). Each distinct angle is rendered once (a view's
    # render does not depend on the others in its call) and gathered per offset: the same images
    shifted = poses.azimuth[None, :].double() + offsets.double()[:, None]  # [O, n]
    angles, index = torch.unique(shifted, return_inverse=True)
    if not all(bool((getattr(poses, k) == getattr(poses, k)[0]).all()) for k in ("elevation", "radius", "fovy")):
        raise ValueError("poses: expected one ring (one elevation, radius and fovy)")
    rendered = []
    for i in range(0, len(angles), CHUNK):
        a = angles[i : i + CHUNK]
        ring = SphericalPoses(a, *(getattr(poses, k)[:1].expand(len(a)) for k in ("elevation", "radius", "fovy")))
        rendered.append(render_views(scene, ring.cameras(size, size), background=background))
    rendered = torch.cat(rendered)
    best = None
    at0 = None
    for j, off in enumerate(offsets.tolist()):
        img = rendered[index[j]]
        p = float(psnr(img, ref).mean())
        if off == 0:
            at0 = p
        if best is None or p > best[0]:
            best = (p, off, img)
    assert best is not None
    return GTScore(best[0], float(ssim(best[2], ref).mean()), best[1], at0 if at0 is not None else float("nan"))


def turned_deg(offset_deg: float) -> float:
    """The result's turn about +Z in (-180, 180] from the GT score's best azimuth offset (its view
    from azimuth t is the asset's from t - turn: the view metrics' ``turned_deg`` convention)."""
    t = (float(offset_deg) + 180.0) % 360.0 - 180.0
    return 180.0 if t == -180.0 else t + 0.0  # + 0.0: no -0


CHUNK = 24
"""Views per render call of the ground-truth score."""
