"""Pose-locked noise: a control of structured noise that persists but has no 3D correspondence.

The ``gd-pose-locked`` preset (``--noise-source pose``) replaces each view's structured noise
n_s(pi) by a 2D field that is a fixed function of the camera pose pi = (azimuth, elevation):

    F(pi)(u) = sum_i w_i(u) c_i(pi) / sqrt(V(u)),   c(pi) = sum_k a_k(pi) c_k,

where w_i(u), V(u) = sum_i w_i(u)^2 are the blending weights of the run's noise cloud seen from
one *canonical* camera (azimuth 0, elevation 0, the view's own radius and field of view), c_k
~ N(0, I) are independent colours of pose anchors k on a grid of ``width`` degrees, and
a_k(pi) ~ exp(-d_k(pi)^2 / (2 width^2)) are Gaussian weights with sum_k a_k^2 = 1. So:

- marginals and spectrum are exactly those of structured noise: for every pose, c(pi) ~ N(0, I)
  and F(pi) is the cloud's normalised render, N(0, 1) per pixel with the cloud's correlation
  length (uncovered pixels take fresh iid noise every step, as structured noise's do);
- persistence: one pose sees the same field (where the cloud covers it) at every step of the run;
- between poses Delta degrees apart the fields correlate, pixel for pixel, as
  sum_k a_k(pi) a_k(pi') ~ exp(-Delta^2 / (4 width^2)): 0.75 at 5 degrees with the default width
  (structured noise at one *surface point* correlates 0.75 at 5 degrees, docs/decisive.md), and
  about 0 beyond 20 degrees;
- no 3D correspondence: the field is locked to the image, not to the object. Two nearby views
  share noise at the same pixel, where the object has moved; structured noise shares it at the
  same surface point, wherever that lands in the image.

What it removes from the paper's mechanism is therefore only the 3D sharing; what it keeps is
the persistence of a noise image per camera. The statistics are measured at the denoiser by
``gdbench.experiments.controls`` (docs/decisive.md, "The controls").

Anchor k's colours come from a generator seeded by (run seed, k): no state beyond the seed, so a
resumed run draws the same fields.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from gdbench.core.camera import Cameras, SphericalPoses
from gdbench.core.rand import randn
from gdbench.mechanisms.noise import NoiseCloud, NoiseRenderer, StructuredNoise

POSE_WIDTH_DEG = 4.66
"""Width of the anchors' Gaussian weights (degrees): fields of poses Delta apart correlate as
exp(-Delta^2 / (4 width^2)), 0.75 at 5 degrees."""
REACH = 3.5
"""Anchors farther than REACH widths from a pose get no weight (exp(-REACH^2 / 2) < 0.003)."""


def anchor_weights(
    azimuth: float, elevation: float, width: float = POSE_WIDTH_DEG
) -> tuple[list[tuple[int, int]], Tensor]:
    """(anchors, weights) of one pose: the grid anchors (i, j) within REACH widths (azimuth step
    360 / round(360 / width) degrees, wrapping; elevation step ``width``), and their weights
    a_k, float64 with sum a_k^2 = 1. Distances are on the sphere's local chart at the pose
    (azimuth differences shrink by cos(elevation))."""
    if not (math.isfinite(azimuth) and math.isfinite(elevation)):
        raise ValueError(f"pose: expected finite azimuth and elevation, got {(azimuth, elevation)}")
    if not width > 0:
        raise ValueError(f"width: expected > 0 degrees, got {width}")
    n_az = max(1, round(360.0 / width))
    step_az = 360.0 / n_az
    shrink = max(math.cos(math.radians(elevation)), 1e-3)
    j0, j1 = math.floor((elevation - REACH * width) / width), math.ceil((elevation + REACH * width) / width)
    span = min(math.ceil(REACH * width / (step_az * shrink)) + 1, n_az // 2 + 1)
    i_mid = round(azimuth / step_az)
    d2: dict[tuple[int, int], float] = {}  # anchor -> squared distance, each anchor once (azimuth wraps)
    for j in range(j0, j1 + 1):
        de = j * width - elevation
        for i in range(i_mid - span, i_mid + span + 1):
            da = (i * step_az - azimuth + 180.0) % 360.0 - 180.0
            dist2 = (da * shrink) ** 2 + de * de
            if dist2 <= (REACH * width) ** 2:
                d2.setdefault((i % n_az, j), dist2)
    a = torch.exp(-torch.tensor(list(d2.values()), dtype=torch.float64) / (2 * width * width))
    return list(d2), a / a.norm()


def _anchor_seed(seed: int, anchor: tuple[int, int]) -> int:
    i, j = anchor
    return (int(seed) * 1_000_003 + (j + 100_000) * 65_537 + i) % (2**63 - 1)


class PoseLockedNoise:
    """Renders pose-locked noise (see the module docstring) for a step's poses and cameras."""

    def __init__(self, cloud: NoiseCloud, *, seed: int, width_deg: float = POSE_WIDTH_DEG, v_min: float = 1e-6):
        if not width_deg > 0:
            raise ValueError(f"width_deg: expected > 0 degrees, got {width_deg}")
        self.renderer = NoiseRenderer(cloud, v_min=v_min, cache_size=0)
        self.cloud = cloud
        self.seed = int(seed)
        self.width = float(width_deg)

    def pose_colors(self, azimuth: float, elevation: float) -> Tensor:
        """c(pi) [M, D] of one pose: the anchors' colours weighted by a_k (N(0, I) for any pose)."""
        anchors, a = anchor_weights(azimuth, elevation, self.width)
        m, d = len(self.cloud), self.cloud.channels
        colors = torch.zeros(m, d, dtype=torch.float64)
        for k, w in zip(anchors, a.tolist()):
            g = torch.Generator().manual_seed(_anchor_seed(self.seed, k))
            colors += w * randn((m, d), generator=g, dtype=torch.float64)
        return colors.float()

    def render(self, poses: SphericalPoses, cams: Cameras, *, generator: torch.Generator) -> StructuredNoise:
        """The pose-locked field of every view [C, H, W, D] (``cams`` give the size and device;
        ``generator`` the iid noise of uncovered pixels)."""
        from renderers.splat import normalised_features

        if len(poses) != len(cams):
            raise ValueError(f"poses, cams: expected one pose per camera, got {len(poses)} and {len(cams)}")
        canon = SphericalPoses(
            torch.zeros_like(poses.azimuth), torch.zeros_like(poses.elevation), poses.radius, poses.fovy
        ).cameras(cams.width, cams.height)
        noise, cover = [], []
        with torch.no_grad():
            for c in range(len(poses)):
                colors = self.pose_colors(float(poses.azimuth[c]), float(poses.elevation[c]))
                fill = randn((1, cams.height, cams.width, self.cloud.channels), generator=generator)
                prepared = self.renderer.prepared(canon[c : c + 1])
                n, cov = normalised_features(prepared, colors, fill, v_min=self.renderer.v_min, check_values=False)
                noise.append(n)
                cover.append(cov)
        device = cams.viewmats.device
        return StructuredNoise(torch.cat(noise).to(device), torch.cat(cover).to(device))
