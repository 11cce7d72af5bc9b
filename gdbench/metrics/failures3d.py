"""Renderable failure fixtures: Gaussian scenes of the procedural assets, whole or broken the
way a trained result can be, to calibrate the view metrics and COLMAP on (docs/scoring.md).

Every fixture is one Gaussian scene, so every view of it is a view of one 3D object, as a
trained result's are (unlike per-frame image edits, which no scene can render). The asset's
scene: flat discs on its mesh surface (area-uniform samples, each disc in the surface's
tangent plane), coloured from the asset's image bank: SH of degree 2 fitted to the bank views
that see the point (in front of the camera, facing it, and at the depth the bank recorded
there), so a face seen obliquely darkens as pyrender's headlight darkens it and the scene's
views are the asset's under the bank's lighting. The failure fixtures cut and move those discs
(and turn or mirror their SH with them):

- ``asset``; ``turned-90``, ``turned-180``: the asset turned about +Z;
- ``two-faced``: the front half (x > 0) and its mirror image in the plane x = 0, the front on
  both sides; ``four-faced``: the front half squeezed into the front quarter (each Gaussian
  turned from azimuth a to a / 2), four times, turned by 0, 90, 180 and 270 degrees;
- ``chimera-front-back``: variant 0 in front (x > 0), variant 1 behind; ``chimera-left-right``:
  variant 0 on the left (y > 0), variant 2 on the right. The variants differ in shape and
  colour (``assets/library.py``);
- ``spun``: every disc turned about +Z by a random angle: a featureless solid of revolution;
- ``front-everywhere``: the front half squeezed into a wedge of 30 degrees (each Gaussian turned
  from azimuth a to a / 6), twelve times around: from every side a face looks at the camera,
  with the next ones beside it;
- ``back-everywhere``: the same with the back half (turned to face +X first): the asset's back
  from every side and its front nowhere (a faceless result whose silhouette may still match
  the front's);
- ``blob``: ``spun`` in the asset's mean colour (no view-dependent colour): no face anywhere;
- ``outline-everywhere``: ``blob`` with the asset first squeezed along its front axis (x) to its
  width (y) where it is longer than wide: the end-on outline (a head over a body) from every
  side, and no face: the labelling rule's front_everywhere without a face;
- ``blurred``: every Gaussian moved by 0.01 (each axis, normal) and widened to a ball of
  standard deviation 0.02 (1.2 px at 64 px), at opacity 0.5;
- ``floaters``: the asset with 40 opaque grey blobs scattered around it (0.42-0.6 from the
  centre).

``flicker_colors`` gives per-view colour jitter of a scene, the view-to-view inconsistency a
3D scene can show (COLMAP's calibration).
"""

from __future__ import annotations

import dataclasses
import functools
import math

import torch
from torch import Tensor

from gdbench.core.camera import quat_mul
from gdbench.core.scene import GaussianScene

KINDS = (
    "asset",
    "turned-90",
    "turned-180",
    "two-faced",
    "four-faced",
    "chimera-front-back",
    "chimera-left-right",
    "spun",
    "blurred",
    "floaters",
    "front-everywhere",
    "back-everywhere",
    "blob",
    "outline-everywhere",
)
POINTS = 24000
"""Discs per asset: about 4 per pixel's area of surface at the metric's 64 px (the duck's surface
is 1.5 square units; a pixel is 0.016 wide at distance 1)."""


SH_DEGREE = 2
"""The fixtures' view-dependent colour: degree 2 fits the bank's headlight shading (a cosine
lobe about the view direction), so a face seen obliquely is as dark as pyrender draws it."""


def _surface(bank, variant: int, n: int, seed: int) -> tuple[Tensor, Tensor, Tensor, float]:
    """(points [n, 3], normals [n, 3], SH coefficients [n, K, 3], spacing) of the surface of the
    asset variant ``variant`` whose image bank is ``bank``."""
    import numpy as np
    import trimesh

    from gdbench.assets.library import build

    mesh = build(bank.caption, variant)
    pts, face = trimesh.sample.sample_surface(mesh, n, seed=seed)
    normals = np.asarray(mesh.face_normals)[face]
    p = torch.from_numpy(np.asarray(pts)).double()
    nrm = torch.nn.functional.normalize(torch.from_numpy(normals).double(), dim=-1)
    return p, nrm, _bank_sh(bank, p, nrm), math.sqrt(float(mesh.area) / n)


def _bank_sh(bank, p: Tensor, nrm: Tensor, tol: float = 0.02, ridge: float = 1.0) -> Tensor:
    """Each point's colour as SH of degree ``SH_DEGREE`` [N, K, 3], fitted by least squares to
    the views of ``bank`` that see it (facing the camera, and within ``tol`` of the depth the bank
    recorded at its pixel), with a ``ridge`` on the view-dependent terms; grey where none does."""
    from gdbench.core.camera import Cameras
    from renderers.splat.sh import sh_basis

    c = bank.cameras()
    cams = Cameras(c.viewmats.double(), c.Ks.double(), c.width, c.height)
    centres = cams.centers
    H = W = bank.config.resolution
    K = (SH_DEGREE + 1) ** 2
    ata = torch.zeros(len(p), K, K, dtype=torch.float64)
    atb = torch.zeros(len(p), K, 3, dtype=torch.float64)
    for v in range(len(bank)):
        uv, z = cams[v : v + 1].project(p)
        u, w = uv[0, :, 0].floor().long(), uv[0, :, 1].floor().long()
        z = z[0]
        inside = (u >= 0) & (u < W) & (w >= 0) & (w < H) & (z > 0)
        u, w = u.clamp(0, W - 1), w.clamp(0, H - 1)
        facing = ((centres[v] - p) * nrm).sum(-1) > 0
        depth = bank.depth[v, w, u].double()
        seen = inside & facing & (bank.alpha[v, w, u] > 0.99) & ((depth - z).abs() < tol)
        y = sh_basis(SH_DEGREE, torch.nn.functional.normalize(p[seen] - centres[v], dim=-1))  # [M, K]
        ata[seen] += y[:, :, None] * y[:, None, :]
        atb[seen] += y[:, :, None] * (bank.images[v, w[seen], u[seen]].double() - 0.5)[:, None, :]
    reg = torch.full((K,), ridge, dtype=torch.float64)
    reg[0] = 1e-6
    sh = torch.linalg.solve(ata + torch.diag(reg), atb)
    sh[ata[:, 0, 0] == 0] = 0.0  # seen by no view: grey (0.5)
    return sh


def _turn_sh(sh: Tensor, M: Tensor) -> Tensor:
    """SH coefficients [N, K, 3] of colour functions moved by the orthogonal ``M`` ([3, 3] or one
    per point [N, 3, 3]): the new function at d is the old one at M^T d. Exact within a degree
    (rotations and mirrors keep each degree's space), solved on 64 fixed directions."""
    from renderers.splat.sh import sh_basis

    g = torch.Generator().manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(64, 3, generator=g, dtype=torch.float64), dim=-1)
    Y = sh_basis(SH_DEGREE, d)  # [J, K]
    moved = torch.einsum("...ji,kj->...ki", M, d)  # M^T d for every direction: [(N,) J, 3]
    T = torch.linalg.pinv(Y) @ sh_basis(SH_DEGREE, moved)  # [(N,) K, K]: c' = T c
    return T @ sh if T.dim() == 3 else torch.einsum("ij,njc->nic", T, sh)


def _rot_z(deg: float | Tensor) -> Tensor:
    a = torch.deg2rad(torch.as_tensor(deg, dtype=torch.float64))
    c, s, o, i = torch.cos(a), torch.sin(a), torch.zeros_like(a), torch.ones_like(a)
    return torch.stack([torch.stack([c, -s, o], -1), torch.stack([s, c, o], -1), torch.stack([o, o, i], -1)], -2)


def _discs(p: Tensor, nrm: Tensor, sh: Tensor, radius: float, opacity: float = 0.97) -> GaussianScene:
    """Flat Gaussians at ``p``, their thin axis (local z) along ``nrm``, coloured by ``sh`` [N, K, 3]."""
    z = nrm
    q = torch.stack([1.0 + z[:, 2], -z[:, 1], z[:, 0], torch.zeros_like(z[:, 0])], -1)  # rotates +z onto n
    flip = z[:, 2] < -1 + 1e-9
    q[flip] = torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=q.dtype)
    q = torch.nn.functional.normalize(q, dim=-1)
    n = len(p)
    scales = torch.tensor([radius, radius, 0.15 * radius], dtype=torch.float64).expand(n, 3)
    logit = torch.logit(torch.tensor(opacity, dtype=torch.float32))
    return GaussianScene(p.float(), q.float(), scales.float().log(), torch.full((n,), float(logit)), sh.float())


FIELDS = tuple(f.name for f in dataclasses.fields(GaussianScene))

FIT_STEPS, FIT_VIEWS, FIT_VERSION = 200, 8, 1
"""The asset's discs are then fitted to its bank (every parameter, Adam, 200 steps of 8 views at
64 px, seeded): splatting widens a silhouette where many discs line up edge-on (about a pixel at
64 px), which the fit takes back, as training does. The duck's scene reads 20 dB against the
asset's turntable before the fit and 26 after. Bump FIT_VERSION when the fit changes: cached
scenes are then rebuilt."""


def asset_scene(caption: str, variant: int = 0, *, n: int = POINTS, seed: int = 0) -> GaussianScene:
    """The asset (procedural variant ``variant``) as ``n`` Gaussians fitted to its bank, cached
    on disk beside the banks (``$GDBENCH_CACHE``)."""
    return _fitted(caption, variant, n, seed)


@functools.lru_cache(maxsize=8)
def _fitted(caption: str, variant: int, n: int, seed: int) -> GaussianScene:
    import hashlib
    import json

    from gdbench.assets.bank import ASSET_VERSION, BankConfig, cache_dir, load_bank
    from gdbench.core.io import atomic_write

    key = json.dumps([caption, variant, n, seed, SH_DEGREE, FIT_STEPS, FIT_VIEWS, FIT_VERSION, ASSET_VERSION])
    path = (
        cache_dir().parent
        / "fixtures"
        / f"{caption.replace(' ', '_')}-{hashlib.sha256(key.encode()).hexdigest()[:16]}.pt"
    )
    if path.is_file():
        try:
            return GaussianScene(**torch.load(path, weights_only=True))
        except Exception:  # a corrupt cache entry is rebuilt, never trusted
            pass
    bank = load_bank(caption, BankConfig(), variant=variant, verbose=False)
    p, nrm, sh, spacing = _surface(bank, variant, n, seed)
    scene = _fit(_discs(p, nrm, sh, 0.8 * spacing), bank, seed)
    try:
        atomic_write(path, lambda f: torch.save({k: getattr(scene, k) for k in FIELDS}, f))
    except OSError:
        pass  # a cache folder that cannot be written costs the cache, not the fixture
    return scene


def _fit(scene: GaussianScene, bank, seed: int) -> GaussianScene:
    import torch.nn.functional as F

    from renderers.splat import rasterize

    size = bank.config.resolution // 2
    cams = bank.config.poses().cameras(size, size)
    target = F.avg_pool2d(bank.images.permute(0, 3, 1, 2), 2).permute(0, 2, 3, 1)
    bg = torch.tensor(bank.config.background, dtype=torch.float32)
    params = {k: getattr(scene, k).detach().clone().requires_grad_(True) for k in FIELDS}
    rates = {"means": 2e-4, "quats": 1e-3, "log_scales": 5e-3, "opacity_logits": 5e-2, "sh": 5e-3}
    opt = torch.optim.Adam([{"params": [params[k]], "lr": rates[k]} for k in FIELDS])
    g = torch.Generator().manual_seed(seed)
    for _ in range(FIT_STEPS):
        pick = torch.randint(len(bank), (FIT_VIEWS,), generator=g)
        c = cams[pick]
        out = rasterize(
            means=params["means"],
            quats=params["quats"],
            scales=params["log_scales"].exp(),
            opacities=torch.sigmoid(params["opacity_logits"]),
            colors=params["sh"],
            sh_degree=SH_DEGREE,
            viewmats=c.viewmats,
            Ks=c.Ks,
            width=size,
            height=size,
            background=bg,
            outputs=("rgb",),
        )
        loss = ((out.rgb - target[pick]) ** 2).mean()
        opt.zero_grad()
        loss.backward()
        opt.step()
    return GaussianScene(**{k: v.detach() for k, v in params.items()})


def _turned(scene: GaussianScene, deg: float | Tensor) -> GaussianScene:
    """``scene`` turned about +Z by ``deg`` (one angle, or one per Gaussian): means, orientations
    and view-dependent colour (computed on the CPU, returned on the scene's device)."""
    device, scene = scene.means.device, scene.to("cpu")
    a = torch.deg2rad(torch.as_tensor(deg, dtype=torch.float64).cpu())
    R = _rot_z(torch.rad2deg(a))
    qz = torch.stack([torch.cos(a / 2), *(torch.zeros_like(a),) * 2, torch.sin(a / 2)], -1)
    q = torch.nn.functional.normalize(scene.quats.double(), dim=-1)
    means = scene.means.double() @ R.T if R.dim() == 2 else torch.einsum("nij,nj->ni", R, scene.means.double())
    return GaussianScene(
        means.float(),
        quat_mul(qz.expand_as(q), q).float(),
        scene.log_scales,
        scene.opacity_logits,
        _turn_sh(scene.sh.double(), R).float(),
    ).to(device)


def _mirrored(scene: GaussianScene) -> GaussianScene:
    """``scene`` mirrored in the plane x = 0: a Gaussian's rotation R becomes M R M (M the mirror;
    its axes' lengths stay), the quaternion (w, x, -y, -z); computed on the CPU."""
    device, scene = scene.means.device, scene.to("cpu")
    M = torch.diag(torch.tensor([-1.0, 1.0, 1.0], dtype=torch.float64))
    q = scene.quats * torch.tensor([1.0, 1.0, -1.0, -1.0])
    return GaussianScene(
        scene.means * M.diagonal().float(),
        q,
        scene.log_scales,
        scene.opacity_logits,
        _turn_sh(scene.sh.double(), M).float(),
    ).to(device)


def failure_scene(caption: str, kind: str, *, n: int = POINTS, seed: int = 0) -> GaussianScene:
    """The fixture ``kind`` (one of ``KINDS``) of the asset ``caption`` as a Gaussian scene."""
    if kind not in KINDS:
        raise ValueError(f"kind: expected one of {KINDS}, got {kind!r}")
    if n < 1000:
        raise ValueError(f"n: expected at least 1000 discs (the surface must be closed at 64 px), got {n}")
    asset = asset_scene(caption, 0, n=n, seed=seed)
    x = asset.means[:, 0]
    g = torch.Generator().manual_seed(seed)
    if kind == "asset":
        return asset.clone()  # the cached scene stays as fitted
    if kind.startswith("turned-"):
        return _turned(asset, float(kind.split("-")[1]))
    if kind == "two-faced":
        front = asset.subset(torch.nonzero(x > 0).squeeze(1))
        return GaussianScene.cat([front, _mirrored(front)])
    if kind in ("four-faced", "front-everywhere", "back-everywhere"):  # a half squeezed, 4 or 12 times around
        copies = 4 if kind == "four-faced" else 12
        if kind == "back-everywhere":
            front = _turned(asset.subset(torch.nonzero(x < 0).squeeze(1)), 180.0)  # the back, facing +X
        else:
            front = asset.subset(torch.nonzero(x > 0).squeeze(1))
        azimuth = torch.rad2deg(torch.atan2(front.means[:, 1], front.means[:, 0]).double())
        wedge = _turned(front, -azimuth / 2 if copies == 4 else -azimuth * (1 - 2 / copies))
        return GaussianScene.cat([_turned(wedge, 360.0 / copies * k) for k in range(copies)])
    if kind in ("blob", "outline-everywhere"):
        if kind == "outline-everywhere":
            xy = asset.means[:, :2]
            squeeze = min(1.0, float((xy[:, 1].max() - xy[:, 1].min()) / (xy[:, 0].max() - xy[:, 0].min())))
            asset = dataclasses.replace(asset, means=asset.means * torch.tensor([squeeze, 1.0, 1.0]))
        spun = _turned(asset, torch.rand(len(asset), generator=g, dtype=torch.float64) * 360.0)
        sh = torch.zeros_like(spun.sh)
        sh[:, 0] = spun.sh[:, 0].mean(0)  # the asset's mean colour, the same from every side
        return dataclasses.replace(spun, sh=sh)
    if kind.startswith("chimera-"):
        other, axis = (1, 0) if kind == "chimera-front-back" else (2, 1)
        second = asset_scene(caption, other, n=n, seed=seed)
        return GaussianScene.cat(
            [
                asset.subset(torch.nonzero(asset.means[:, axis] > 0).squeeze(1)),
                second.subset(torch.nonzero(second.means[:, axis] <= 0).squeeze(1)),
            ]
        )
    if kind == "spun":
        return _turned(asset, torch.rand(len(asset), generator=g, dtype=torch.float64) * 360.0)
    if kind == "blurred":
        moved = asset.means + 0.01 * torch.randn(asset.means.shape, generator=g)
        scales = torch.full_like(asset.log_scales, math.log(0.02))
        opacity = torch.full_like(asset.opacity_logits, 0.0)  # 0.5
        return GaussianScene(moved, torch.zeros_like(asset.quats), scales, opacity, asset.sh)
    # floaters
    d = torch.nn.functional.normalize(torch.randn(40, 3, generator=g, dtype=torch.float64), dim=-1)
    centres = d * (0.42 + 0.18 * torch.rand(40, 1, generator=g, dtype=torch.float64))
    blobs = GaussianScene.from_activated(
        centres.float(),
        torch.full((40, 3), 0.015),
        torch.full((40,), 0.99),
        torch.full((40, 3), 0.5),
        sh_degree=SH_DEGREE,
    )
    return GaussianScene.cat([asset, blobs])


def flicker_colors(scene: GaussianScene, view: int, *, amount: float = 0.15, seed: int = 0) -> GaussianScene:
    """``scene`` with its SH DC jittered for view ``view``: each Gaussian's colour moved by a
    random +-``amount`` per channel, drawn anew per view (view-to-view colour inconsistency, as
    view-dependent colour left unconstrained between views shows it)."""
    g = torch.Generator().manual_seed(seed * 1_000_003 + view)
    sh = scene.sh.clone()
    jitter = (torch.rand(sh[:, 0].shape, generator=g) * 2 - 1).to(sh.device, sh.dtype)
    from renderers.splat.sh import C0

    sh[:, 0] = sh[:, 0] + jitter * amount / C0
    return GaussianScene(scene.means, scene.quats, scene.log_scales, scene.opacity_logits, sh)
