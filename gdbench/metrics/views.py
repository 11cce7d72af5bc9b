"""Ground-truth view metrics for runs on the empirical prior: one number per failure class
(docs/scoring.md).

A result is rendered at 36 turntable views (azimuths 0, 10, ..., 350 at elevation 20, fovy 55,
radius 1, 64 px, on the run's background). The reference is an image bank of that ring: every
variant's views at 72 azimuths, 5 degrees apart, rendered by pyrender with the same camera.
Each turntable view is matched to the reference view (variant, azimuth) of least squared error;
the global azimuth offset that puts the most matches within 45 degrees of their view's true
azimuth is the result's turn. Then, per class:

- **turned_deg**: the turn of the result about +Z, in (-180, 180]: its view from azimuth t is
  the asset's view from t - turned_deg. Where view prompting defines the front, a turn of more
  than 45 degrees is a failure of its own (the sweep's ``turned`` column).
- **the failure classes of a view**, disjoint (``view_class``; each result's rates in ``views``):
  a view is *self-similar* when its mean squared difference to the result's views 60 or more
  degrees away is under ``FEATURELESS`` of the asset's at the same azimuth (it looks like the
  result's other sides). A self-similar view is **front_everywhere** when the best match of its
  centre band (the vertical band at the middle of the image, what faces the camera) among the
  asset's views is the front (|azimuth| <= 45) and clear (``FRONT_CONTRAST``) while the view
  itself is more than 90 degrees from the front (the front seen from behind: the Janus failure
  as the literature names it), and a **blob** when that match is not the front (no face at all). Of the
  other views, **second_face** ones show a second face (below); every other view is **fine**.
  A self-similar view of the front side that matches the front is fine. ``janus_rate`` is
  front_everywhere + second_face; ``featureless_rate`` is front_everywhere + blob (the name of
  older tables). An asset without a declared front (``assets.library.FRONTS``: the hamburger)
  has no Janus classes: its self-similar views are blobs, and front_everywhere, second_face
  and janus rates are None.
- **multi-face rate** (second_face): the share of views, self-similar ones excepted, that show a second face:
  a part (a vertical band ``BAND`` px wide) that is distinctive (matched far better than by the
  typical azimuth) and explained by a reference view more than 45 degrees from its (turned)
  azimuth with under ``SECOND`` of the error of every view within 45 degrees. A two-faced
  object shows its mirrored head in a side view's band and its front from behind.
- **instance consistency**: part-aware. Inside the object (the result's silhouette eroded by 2
  px), each pixel's error against every variant's view at its (turned) azimuth, averaged over a
  window, votes for a variant when the best is clearly ahead and explains the pixel (``VOTE``);
  the share of votes for the majority variant. A 3D chimera of two variants scores about 0.5, a
  single variant about 1 (docs/scoring.md's table).
- **floaters**: the share of rendered opacity outside the largest connected piece of each
  view's silhouette (alpha over 0.1, dilated by ``dilate`` px): opacity detached from the
  object. A second face, another variant's part or a blur is attached to the body, so it is
  shape error, not floaters.
- **front share**: the share of views matched to the front (|azimuth| <= 45; a correct object
  gives ~0.25, a multi-faced one more).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor

from gdbench.core.camera import SphericalPoses

ELEVATION, FOVY, SIZE, FRAMES = 20.0, 55.0, 64, 36

BAND = 16
"""Width in pixels of the vertical bands (parts) each view is matched by, half a band apart: at
64 px a band is a quarter of the image, about a third of the object across."""
SECOND = 0.5
"""A band shows a second face when a reference view more than 45 degrees from its (turned)
azimuth explains it with under half the error of the best view within 45 degrees."""
GAP = 0.003
"""... and by at least GAP in mean squared error (an RMS of 0.055): a second face makes the view
from the true side clearly wrong (the two-faced objects' flagged bands: 0.01-0.03 at the median),
where a blur only blunts it (the blurred penguin read 0.31 second faces without the gap, 0 with)."""
VOTE, EXPLAINED, WINDOW, MIN_VOTES = 0.5, 0.01, 7, 200
"""A pixel votes for a variant when that variant's squared error (summed over RGB, averaged over
a WINDOW x WINDOW window) is under VOTE of the next variant's and under EXPLAINED (an RMS of
0.058 per channel: a clean run's pixels, not a blur's). Fewer than MIN_VOTES votes over all
views (a featureless or blurred result): the whole views' variants decide. Calibrated on the
3D fixtures of the six assets (docs/scoring.md): single variants 0.98-1.0 (blurred 0.78-1.0),
left/right chimeras 0.42-0.75, front/back 0.52-0.86 (the views from the front see one variant);
clean runs 0.98-1.0."""
DISTINCT = 0.6
"""A band is distinctive when its best match's error is under 0.4 of the median over azimuths
(1 - min / median >= 0.6); with SECOND and GAP it separates the two- and four-faced fixtures
(0.58-1.0 of views) from the others (0-0.03, the blurred hamburger 0.28) in docs/scoring.md's
table."""
FEATURELESS = 0.3
"""A view is featureless when it differs from the result's views 60 or more degrees away by
under 0.3 of what the asset's view differs from the asset's (mean squared error). Calibrated
(the ratio's median): blobs trained on the duck 0.08-0.10 and on the hamburger 0.25-0.27, clean
runs 0.5 and more, a half-failed duck (a face at the front, a blur behind) 0.40; the 3D fixtures:
the spun assets 1 featureless, the four-faced ones up to 0.28 (faces 90 degrees apart look
alike), every other 0 (docs/scoring.md)."""


FRONT_CONTRAST = 0.15
"""The centre band's best match counts as the front only when it is clear: its error under 0.85
of the median over azimuths. A uniform blob's centre matches every azimuth about alike (the Lego
figure's blob fixture: 0.09, where its nearest azimuth happens to be the front); the fixtures'
fronts seen from behind read 0.28-0.57 (docs/scoring.md)."""


@dataclass(frozen=True)
class Reference:
    images: Tensor
    """[V, A, H, W, 3] in [0, 1]: variant, azimuth."""
    alpha: Tensor
    """[V, A, H, W] coverage."""
    azimuth: Tensor
    """[A] degrees."""


CLASSES = ("front_everywhere", "second_face", "blob", "fine")
"""The failure classes of a view, disjoint (module docstring)."""


@dataclass(frozen=True)
class ViewScore:
    multi_face_rate: float | None
    """The second_face class's rate (None for an asset without a front)."""
    featureless_rate: float
    """front_everywhere + blob."""
    front_everywhere_rate: float | None
    blob_rate: float
    janus_rate: float | None
    """front_everywhere + second_face (None for an asset without a front)."""
    view_class: list[str]
    """Each view's class (``CLASSES``)."""
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
    from gdbench.assets.bank import BankConfig, load_bank

    if variants < 1:
        raise ValueError(f"variants: expected at least 1, got {variants}")
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


def _errors(images: Tensor, ref: Reference) -> tuple[Tensor, Tensor]:
    """Mean squared errors of every view against every reference view: whole views [F, V, A] and
    bands [F, B, V, A] (vertical strips ``BAND`` px wide, or the image's width if narrower, half
    a band apart), float64."""
    F, H, W, _ = images.shape
    V, A = ref.images.shape[:2]
    width = min(BAND, W)
    starts = list(range(0, W - width + 1, max(1, width // 2)))
    whole = torch.empty(F, V, A, dtype=torch.float64)
    band = torch.empty(F, len(starts), V, A, dtype=torch.float64)
    refs = ref.images.float()
    for f in range(F):
        cols = ((images[f].float() - refs) ** 2).sum((2, 4)).double()  # [V, A, W]
        whole[f] = cols.sum(-1) / (H * W * 3)
        for b, x in enumerate(starts):
            band[f, b] = cols[..., x : x + width].sum(-1) / (H * width * 3)
    return whole, band


def _self_difference(images: Tensor, azimuth: Tensor) -> Tensor:
    """[F]: the mean squared difference of each view to the views 60 or more degrees away."""
    x = images.double().flatten(1)
    sq = (x * x).sum(1)
    d = (sq[:, None] + sq[None] - 2 * x @ x.T).clamp_min(0) / x.shape[1]
    far = _circ(azimuth[:, None] - azimuth[None]) >= 60.0
    return (d * far).sum(1) / far.sum(1).clamp_min(1)


def score_views(images: Tensor, alpha: Tensor, ref: Reference, *, dilate: int = 2, front: bool = True) -> ViewScore:
    """Metrics of turntable views ``images`` [F, H, W, 3] / ``alpha`` [F, H, W] taken at
    ``turntable_poses(F)`` against ``ref``; ``front``: whether the asset has a front (else no
    Janus classes: module docstring)."""
    if images.dim() != 4 or images.shape[0] == 0 or images.shape[-1] != 3:
        raise ValueError(f"images: expected [F >= 1, H, W, 3] turntable views, got {tuple(images.shape)}")
    if tuple(alpha.shape) != tuple(images.shape[:3]):
        raise ValueError(f"alpha: expected {tuple(images.shape[:3])} like images, got {tuple(alpha.shape)}")
    if not (bool(torch.isfinite(images).all()) and bool(torch.isfinite(alpha).all())):
        raise ValueError("images, alpha: expected finite values (a broken render is no result to score)")
    images, alpha = images.detach().cpu(), alpha.detach().cpu()  # small: the scoring runs on the CPU
    F, H, W, _ = images.shape
    V, A = ref.images.shape[:2]
    if ref.images.shape[2:4] != (H, W):
        raise ValueError(f"images: expected {tuple(ref.images.shape[2:4])} px like the reference, got {(H, W)}")
    whole, band = _errors(images, ref)  # [F, V, A], [F, B, V, A]
    mse = whole.reshape(F, V * A)
    best = mse.argmin(1)  # [F] over variant-major (variant, azimuth)
    variant, az_idx = best // A, best % A
    matched = ref.azimuth[az_idx].double()
    truth = turntable_poses(F).azimuth.double()
    offsets = torch.arange(0.0, 360.0, 5.0, dtype=torch.float64)
    err = _circ(matched[None] - (truth[None] + offsets[:, None]))  # [O, F]
    ok = (err <= 45.0).sum(1)
    score = ok * 1e6 - err.sum(1)  # most views within 45 degrees, then the smallest total error
    k = int(score.argmax())
    offset = float(offsets[k])
    # featureless: the view is about as its views from other sides (the asset's differ more)
    apart = _circ(ref.azimuth.double()[None] - (truth[:, None] + offset))  # [F, A]: from each turned view
    near, at = apart <= 45.0, apart.argmin(1)
    majority_view = int(torch.mode(variant).values)
    featureless = _self_difference(images, truth) < FEATURELESS * _self_difference(ref.images[majority_view, at], truth)
    # parts: each band against every azimuth, the best variant at each
    per_az = band.min(2).values  # [F, B, A]
    has = per_az.median(2).values > 1e-6  # bands that are not background in every view
    contrast = 1.0 - per_az.min(2).values / per_az.median(2).values.clamp_min(1e-12)
    distinct = has & (contrast >= DISTINCT) & ~featureless[:, None]  # [F, B]
    inf = torch.tensor(float("inf"), dtype=torch.float64)
    e_near = torch.where(near[:, None], per_az, inf).min(2).values
    e_far = torch.where(~near[:, None], per_az, inf).min(2).values
    second = distinct & (e_far < SECOND * e_near) & (e_near - e_far > GAP)  # better explained from > 45 deg away
    # instance: each explained pixel inside the object votes for a variant at its azimuth
    votes = _pixel_votes(images, alpha, ref, at)[~featureless]  # [F', H, W], -1: no vote
    votes = votes[votes >= 0]
    if votes.numel() >= MIN_VOTES:
        counts = torch.bincount(votes, minlength=V)
        majority = int(counts.argmax())
        consistency = float(counts[majority]) / float(counts.sum())
    else:  # no part decides between variants: the whole views do
        majority = majority_view
        consistency = float((variant == majority).double().mean())
    # the front is seen where the view's centre band (the part facing the camera) is best
    # explained by the asset's front: a whole view's match also weighs the silhouette's sides
    mid = per_az[:, per_az.shape[1] // 2]  # [F, A]
    centre = ref.azimuth.double()[mid.argmin(1)]
    clear = 1.0 - mid.min(1).values / mid.median(1).values.clamp_min(1e-12) >= FRONT_CONTRAST
    match_front = (_circ(centre) <= 45.0) & clear
    away = _circ(truth) > 90.0  # the view itself, seen from more than 90 degrees off the front
    front_everywhere = featureless & match_front & away if front else torch.zeros_like(featureless)
    blob = featureless & ~match_front if front else featureless
    second_face = second.any(1) & ~featureless
    cls = [
        "front_everywhere" if fe else "blob" if b else "second_face" if sf else "fine"
        for fe, b, sf in zip(front_everywhere.tolist(), blob.tolist(), second_face.tolist())
    ]

    def rate(mask: Tensor) -> float:
        return float(mask.double().mean())

    return ViewScore(
        multi_face_rate=rate(second_face) if front else None,
        featureless_rate=rate(front_everywhere | blob),
        front_everywhere_rate=rate(front_everywhere) if front else None,
        blob_rate=rate(blob),
        janus_rate=rate(front_everywhere | second_face) if front else None,
        view_class=cls,
        front_share=float((_circ(matched) <= 45.0).double().mean()),
        instance_consistency=consistency,
        majority_variant=majority,
        floaters=_detached(alpha, dilate),
        offset_deg=offset,
        turned_deg=-((offset + 180.0) % 360.0 - 180.0) or 0.0,  # matched = truth + offset = truth - turn
        matched_azimuth=matched.tolist(),
        matched_variant=variant.tolist(),
    )


def _pixel_votes(images: Tensor, alpha: Tensor, ref: Reference, at: Tensor) -> Tensor:
    """[F, H, W]: the variant each pixel inside the object votes for (module docstring), -1 for
    none. ``at`` [F]: the reference azimuth index of each view."""
    import torch.nn.functional as F

    V = ref.images.shape[0]
    inside = -F.max_pool2d(-(alpha > 0.5).float()[:, None], 5, 1, 2)[:, 0] > 0.5  # eroded by 2 px
    if V < 2:
        return torch.where(inside, 0, -1)
    err = ((images[None].float() - ref.images[:, at].float()) ** 2).sum(-1)  # [V, F, H, W]
    err = F.avg_pool2d(err.reshape(-1, 1, *err.shape[2:]), WINDOW, 1, WINDOW // 2).reshape(err.shape)
    two = err.topk(2, dim=0, largest=False)
    ok = inside & (two.values[0] < VOTE * two.values[1]) & (two.values[0] < EXPLAINED)
    return torch.where(ok, two.indices[0], -1)


def _detached(alpha: Tensor, dilate: int) -> float:
    """The share of opacity outside the largest connected piece of each view's silhouette. Equal,
    bit for bit, to scipy.ndimage's label (4-connected), sum by label (per-label float64 sums in
    raster order), the first largest piece and binary_dilation by the cross (nothing outside the
    image), without importing scipy: scipy.ndimage's import is a slow part of every scoring
    process, and nothing else there needs scipy."""
    import numpy as np

    total = float(alpha.sum())
    if total <= 0:
        return 0.0
    A = alpha.double().numpy()
    F, H, W = A.shape
    pixels, label, first = _components(A > 0.1)
    sizes = np.bincount(label, weights=A.reshape(-1)[pixels], minlength=len(first))  # as ndimage.sum sums
    bounds = np.searchsorted(first // (H * W), np.arange(F + 1))  # each view's pieces
    views = [f for f in range(F) if bounds[f + 1] - bounds[f] > 1]
    if not views:
        return 0.0
    chosen = np.zeros(len(first), bool)
    for f in views:
        chosen[bounds[f] + int(np.argmax(sizes[bounds[f] : bounds[f + 1]]))] = True
    body = np.zeros(F * H * W, bool)
    body[pixels[chosen[label]]] = True
    body = body.reshape(F, H, W)[views]
    for _ in range(min(dilate, H + W)):  # within L1 distance ``dilate``; H + W steps cover the image
        grown = body.copy()
        grown[:, 1:] |= body[:, :-1]
        grown[:, :-1] |= body[:, 1:]
        grown[:, :, 1:] |= body[:, :, :-1]
        grown[:, :, :-1] |= body[:, :, 1:]
        body = grown
    out = 0.0
    for a, b in zip(A[views], body):
        out += float(a[~b].sum())
    return out / total


def _components(mask):
    """(pixels, label, first) of a boolean [..., H, W] ``mask``: the flat indices of its set pixels
    in raster order, the 4-connected piece of each (connected within its [H, W] plane) and each
    piece's first pixel. Pieces are numbered 0, 1, ... in the raster order of their first pixels,
    as scipy.ndimage.label numbers them from 1. Union-find over the horizontal runs: each round
    hooks the larger root of every pair of touching runs (a run and one in the next row) to the
    smaller and flattens the trees by pointer jumping, so a long snake or spiral costs a few rounds
    (2 up to 1024 px; 6 for 1024 px noise), not its length; the work per round grows with the runs
    (faster than scipy on the metric's silhouettes, slower on large noise images)."""
    import numpy as np

    W = mask.shape[-1]
    start = mask.copy()  # the first pixel of each horizontal run
    start[..., 1:] &= ~mask[..., :-1]
    pixels, starts = np.flatnonzero(mask), np.flatnonzero(start)
    below = np.zeros_like(mask)
    below[..., :-1, :] = mask[..., :-1, :] & mask[..., 1:, :]
    overlap = below.copy()  # the first column of each overlap of a run with one in the next row
    overlap[..., 1:] &= ~below[..., :-1]
    top = np.flatnonzero(overlap)
    u, w = np.searchsorted(starts, top, "right") - 1, np.searchsorted(starts, top + W, "right") - 1
    parent = np.arange(len(starts))
    while not np.array_equal(pu := parent[u], pw := parent[w]):
        lo = np.minimum(pu, pw)
        np.minimum.at(parent, pu, lo)
        np.minimum.at(parent, pw, lo)
        deep = np.flatnonzero(parent[parent] != parent)  # jump until every run's parent is a root
        while len(deep):
            parent[deep] = parent[parent[deep]]
            deep = deep[parent[deep] != parent[parent[deep]]]
    root = parent == np.arange(len(parent))
    run = np.cumsum(start.reshape(-1)[pixels]) - 1  # the run of each set pixel
    return pixels, (np.cumsum(root) - 1)[parent][run], starts[root]


def render_turntable(
    scene, frames: int = FRAMES, size: int = SIZE, background=(1.0, 1.0, 1.0)
) -> tuple[Tensor, Tensor]:
    """(images [F, H, W, 3], alpha [F, H, W]) of a GaussianScene at the metric's views (on the CPU,
    wherever the scene is)."""
    from gdbench.core.turntable import render_views_alpha

    return render_views_alpha(scene, turntable_poses(frames).cameras(size, size), background)


def score_scene(
    scene, caption: str, variants: int = 1, ref: Reference | None = None, background=(1.0, 1.0, 1.0)
) -> ViewScore:
    """The view metrics of ``scene``, rendered and compared on ``background`` (a run's own); the
    Janus classes only where the asset declares a front."""
    from gdbench.assets.library import has_front

    ref = ref if ref is not None else reference(caption, variants, background=background)
    return score_views(*render_turntable(scene, background=background), ref, front=has_front(caption))


def fixture_views(caption: str, mode: str, *, frames: int = FRAMES, size: int = SIZE, seed: int = 0):
    """Per-frame views with an exact answer, rendered by pyrender: (images, alpha). ``asset``:
    the asset itself; ``jittered``: each view turned by a random +-30 degrees, which no single
    scene renders (the failure fixtures that a scene can show are ``failures3d``)."""
    import math

    import numpy as np

    from gdbench.assets.library import build
    from renderers.pyrender_points.mesh import render_mesh

    modes = ("asset", "jittered")
    if mode not in modes:
        raise ValueError(f"mode: expected one of {modes}, got {mode!r}")
    poses = turntable_poses(frames)
    cams = poses.cameras(size, size)
    pose_gl, Ks = cams.to_opengl()
    g = torch.Generator().manual_seed(seed)
    view_poses = []
    for i in range(frames):
        turn = float((torch.rand(1, generator=g) * 2 - 1) * 30.0) if mode == "jittered" else 0.0
        c, s = math.cos(math.radians(turn)), math.sin(math.radians(turn))
        Rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        view_poses.append(np.linalg.inv(Rz) @ pose_gl[i].double().numpy())  # turning the object = the camera back
    rgb, _, alpha = render_mesh(build(caption), np.stack(view_poses), Ks.double().numpy(), size, size)
    return torch.from_numpy(rgb), torch.from_numpy(alpha)


RESULT_RATES = {"front_everywhere": 0.25, "second_face": 0.25, "blob": 0.5}
"""A result is of a failure class when that class's rate reaches this share of its views: a
quarter for the Janus classes (a front seen from behind can only show in the half of the views
more than 90 degrees off the front: the front-everywhere fixtures read about 0.45), half for
blobs. Set before the labelled set was read (docs/scoring.md)."""


def result_class(views: dict) -> str:
    """The class of a whole result from its ``views`` block (scores.json): among the classes whose
    rate reaches ``RESULT_RATES``, the one furthest past its threshold (rate over threshold);
    'fine' when none does. An asset without a front has no Janus classes (their rates None)."""
    rates = {
        "front_everywhere": views.get("front_everywhere_rate"),
        "second_face": views.get("multi_face_rate"),
        "blob": views.get("blob_rate"),
    }
    over = {k: v / RESULT_RATES[k] for k, v in rates.items() if v is not None and v == v and v >= RESULT_RATES[k]}
    return max(over, key=over.get) if over else "fine"
