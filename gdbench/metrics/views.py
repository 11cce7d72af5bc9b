"""Ground-truth view metrics for runs on the empirical prior: multi-face rate, instance
consistency and floaters (docs/scoring.md).

A result is rendered at 36 turntable views (azimuths 0, 10, ..., 350 at elevation 20, fovy 55,
radius 1, 64 px, on the run's background). The reference is an image bank of that ring: every
variant's views at 72 azimuths, 5 degrees apart, rendered by pyrender with the same camera.
Each turntable view is matched to the reference view
(variant, azimuth) of highest PSNR. Then, after the global azimuth offset that puts the most
matches within 45 degrees of their view's true azimuth (results may settle turned about +Z):

- **featureless rate**: the share of views that are not distinctive: their best match is not
  clearly better than the typical azimuth (``DISTINCT``): a blob or a solid of revolution looks
  the same from every side;
- **multi-face rate**: the share of views, distinctive ones, whose matched azimuth is more than
  45 degrees from the truth (a Janus result, its front on several sides, matches its back views
  to front views; a featureless view is not counted as a second face);
- **front share**: the share of views matched to the front (|azimuth| <= 45; a correct object
  gives ~0.25, a multi-faced one more);
- **instance consistency**: the share of views matched to the majority variant;
- **floaters**: the share of rendered opacity outside the silhouette of the reference view each
  frame matched, dilated by ``dilate`` pixels: opacity no view of the asset explains, kept apart
  from shape error (a two-faced result matches its back views to front views, whose silhouettes
  it fills);
- **turned_deg**: the turn of the result about +Z, in (-180, 180]: its view from azimuth t is
  the asset's view from t - turned_deg (the global offset above, signed). Where view prompting
  defines the front, a turn of more than 45 degrees is a failure of its own (the sweep's
  ``turned`` column).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from ..camera import SphericalPoses

ELEVATION, FOVY, SIZE, FRAMES = 20.0, 55.0, 64, 36

DISTINCT = 0.5
"""A view is distinctive when its best match's error is under half the median error over its
variant's azimuths (1 - min / median >= 0.5). Calibrated: the asset, two-faced, chimera, jittered
and floater fixtures score 0.75-1.0 per view, the spun asset 0.26, a flat silhouette 0.09; runs:
the default duck 0.87-0.97, blurred failed ducks median 0.40-0.43, the hamburger's blob 0.16-0.39."""


@dataclass(frozen=True)
class Reference:
    images: Tensor
    """[V, A, H, W, 3] in [0, 1]: variant, azimuth."""
    alpha: Tensor
    """[V, A, H, W] coverage."""
    azimuth: Tensor
    """[A] degrees."""


@dataclass(frozen=True)
class ViewScore:
    multi_face_rate: float
    featureless_rate: float
    front_share: float
    instance_consistency: float
    majority_variant: int
    floaters: float
    offset_deg: float
    turned_deg: float
    """The result's turn about +Z in (-180, 180] (module docstring)."""
    matched_azimuth: list[float]
    matched_variant: list[int]

    def as_dict(self) -> dict:
        return asdict(self)


def turntable_poses(frames: int = FRAMES) -> SphericalPoses:
    return SphericalPoses.orbit(frames, radius=1.0, elevation=ELEVATION, fovy=FOVY)


def reference(caption: str, variants: int = 1, size: int = SIZE, background=(1.0, 1.0, 1.0)) -> Reference:
    """The caption's views on the elevation-20 ring (72 azimuths, fovy 55), every variant, on
    ``background``: an image bank of that one ring, rendered by pyrender and cached like the
    prior's banks."""
    from ..assets.bank import BankConfig, load_bank

    cfg = BankConfig(resolution=size, fovy=FOVY, elevations=(ELEVATION,), background=tuple(background))
    imgs, alphas, az = [], [], None
    for v in range(variants):
        bank = load_bank(caption, cfg, variant=v, verbose=False)
        order = torch.argsort(bank.azimuth)
        az = bank.azimuth[order]
        imgs.append(bank.images[order])
        alphas.append(bank.alpha[order])
    return Reference(torch.stack(imgs), torch.stack(alphas), az)


def _circ(d: Tensor) -> Tensor:
    return ((d + 180.0) % 360.0 - 180.0).abs()


def score_views(images: Tensor, alpha: Tensor, ref: Reference, *, dilate: int = 2) -> ViewScore:
    """Metrics of turntable views ``images`` [F, H, W, 3] / ``alpha`` [F, H, W] taken at
    ``turntable_poses(F)`` against ``ref``."""
    F, H, W, _ = images.shape
    V, A = ref.images.shape[:2]
    if ref.images.shape[2:4] != (H, W):
        raise ValueError(f"images: expected {tuple(ref.images.shape[2:4])} px like the reference, got {(H, W)}")
    mse = ((images[:, None].double() - ref.images.reshape(1, V * A, H, W, 3).double()) ** 2).mean((2, 3, 4))
    best = mse.argmin(1)  # [F] over variant-major (variant, azimuth)
    variant, az_idx = best // A, best % A
    # distinctive: the best match clearly beats the typical azimuth of its variant
    per_az = mse.reshape(F, V, A)[torch.arange(F), variant]  # [F, A]
    contrast = 1.0 - per_az.min(1).values / per_az.median(1).values.clamp_min(1e-12)
    distinct = contrast >= DISTINCT
    matched = ref.azimuth[az_idx].double()
    truth = turntable_poses(F).azimuth.double()
    offsets = torch.arange(0.0, 360.0, 5.0, dtype=torch.float64)
    err = _circ(matched[None] - (truth[None] + offsets[:, None]))  # [O, F]
    ok = (err <= 45.0).sum(1)
    score = ok * 1e6 - err.sum(1)  # most views within 45 degrees, then the smallest total error
    k = int(score.argmax())
    offset = float(offsets[k])
    majority = int(torch.mode(variant).values)
    # floaters: opacity outside the (dilated) silhouette of the reference view each frame matched,
    # so a wrong view (a second face, another variant) is shape error, not floaters
    mask = ref.alpha[variant, az_idx] > 0.5
    if dilate > 0:
        mask = torch.nn.functional.max_pool2d(mask[:, None].float(), 2 * dilate + 1, 1, dilate)[:, 0] > 0
    total = float(alpha.sum())
    floaters = float((alpha * (~mask)).sum()) / total if total > 0 else 0.0
    second_face = (err[k] > 45.0) & distinct  # a featureless view is not a second face
    return ViewScore(
        multi_face_rate=float(second_face.double().mean()),
        featureless_rate=float((~distinct).double().mean()),
        front_share=float((_circ(matched) <= 45.0).double().mean()),
        instance_consistency=float((variant == majority).double().mean()),
        majority_variant=majority,
        floaters=floaters,
        offset_deg=offset,
        turned_deg=-((offset + 180.0) % 360.0 - 180.0) or 0.0,  # matched = truth + offset = truth - turn
        matched_azimuth=matched.tolist(),
        matched_variant=variant.tolist(),
    )


def render_turntable(
    scene, frames: int = FRAMES, size: int = SIZE, background=(1.0, 1.0, 1.0)
) -> tuple[Tensor, Tensor]:
    """(images [F, H, W, 3], alpha [F, H, W]) of a GaussianScene at the metric's views."""
    from ..turntable import render_views_alpha

    return render_views_alpha(scene, turntable_poses(frames).cameras(size, size), background)


def score_scene(
    scene, caption: str, variants: int = 1, ref: Reference | None = None, background=(1.0, 1.0, 1.0)
) -> ViewScore:
    """The view metrics of ``scene``, rendered and compared on ``background`` (a run's own)."""
    ref = ref if ref is not None else reference(caption, variants, background=background)
    return score_views(*render_turntable(scene, background=background), ref)


def fixture_views(caption: str, mode: str, *, frames: int = FRAMES, size: int = SIZE, seed: int = 0):
    """Calibration views with a known answer, rendered by pyrender: (images, alpha).

    ``asset``: the asset itself; ``two-faced``: views from the back half see the asset turned 180
    degrees (its front on both sides); ``chimera``: the front half of the turntable sees variant 0,
    the back half variant 1; ``jittered``: each view turned by a random +-30 degrees; ``floaters``:
    the asset with 40 opaque blobs scattered around it; ``spun``: every view the mean of the
    asset's turntable (the asset spun into a solid of revolution: the same from every side)."""
    import math

    import numpy as np

    from renderers.pyrender_points.mesh import render_mesh

    from ..assets import shapes as S
    from ..assets.library import build

    modes = ("asset", "two-faced", "chimera", "jittered", "floaters", "spun")
    if mode not in modes:
        raise ValueError(f"mode: expected one of {modes}, got {mode!r}")
    poses = turntable_poses(frames)
    cams = poses.cameras(size, size)
    pose_gl, Ks = cams.to_opengl()
    g = torch.Generator().manual_seed(seed)
    meshes = {0: build(caption), 1: build(caption, 1) if mode == "chimera" else None}
    if mode == "floaters":
        rng = np.random.default_rng(seed)
        blobs = []
        for _ in range(40):
            d = rng.normal(size=3)
            p = d / np.linalg.norm(d) * rng.uniform(0.42, 0.6)
            blobs.append(S.ellipsoid(tuple(p), (0.02, 0.02, 0.02), S.solid((0.5, 0.5, 0.5)), subdivisions=2))
        import trimesh

        meshes[0] = trimesh.util.concatenate([meshes[0], *blobs])
    which, view_poses = [], []
    for i in range(frames):
        az = float(poses.azimuth[i])
        turn = 0.0
        if mode == "two-faced" and abs(az) > 90.0:
            turn = 180.0
        elif mode == "jittered":
            turn = float((torch.rand(1, generator=g) * 2 - 1) * 30.0)
        which.append(1 if mode == "chimera" and abs(az) > 90.0 else 0)
        c, s = math.cos(math.radians(turn)), math.sin(math.radians(turn))
        Rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        view_poses.append(np.linalg.inv(Rz) @ pose_gl[i].double().numpy())  # turning the object = the camera back
    rgb = np.zeros((frames, size, size, 3), np.float32)
    alpha = np.zeros((frames, size, size), np.float32)
    for m in {0, 1} & set(which):
        sel = [i for i in range(frames) if which[i] == m]
        r, _, a = render_mesh(meshes[m], np.stack([view_poses[i] for i in sel]), Ks[sel].double().numpy(), size, size)
        rgb[sel], alpha[sel] = r, a
    rgb, alpha = torch.from_numpy(rgb), torch.from_numpy(alpha)
    if mode == "spun":  # every view the mean of the turntable: a solid of revolution's look
        rgb, alpha = (
            rgb.mean(0, keepdim=True).expand_as(rgb).clone(),
            alpha.mean(0, keepdim=True).expand_as(alpha).clone(),
        )
    return rgb, alpha
