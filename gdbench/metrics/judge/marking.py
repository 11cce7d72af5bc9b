"""The judge's fifth reading: a front-only marking seen from the sides.

The labelling rule (docs/results/v3/labelling/PROTOCOL.md) calls a result front_everywhere where
"a front-only marking (a printed torso, a window facing the camera) seen from the sides as well"
is there, and a blob where no side of the asset shows: a teapot's yellow label on every side is a
front everywhere, a plain blue ball with no label anywhere a blob, though the two look alike in
outline. No earlier reading names such a marking. This one does, from the ground truth alone (the
asset's renders, ``sameness.Templates``), never from a label:

- the asset's **front colours**: the colours (``LEVELS`` levels a channel) that its renders within
  ``FRONT_DEG`` of the front show more than ``RATIO`` times as often as those ``OTHER_DEG`` or more
  from it, and that cover more than ``SHARE`` of the front's object pixels (the teapot's label, the
  duck's beak, the owl's face);
- each view's **marking**: the share of its object pixels in the front colours, scaled so that the
  asset's sides and back read 0 and its front 1 (``scaled``);
- four numbers (``MARKING``) over the six sheet views (``reading.sheet_views``: every view where
  the cameras are not a sheet's six): the mean, the largest, the smallest and the
  share of views marked more than half as much as the front. A front everywhere reads high on all
  of them, a whole result high at its front only, a blob low everywhere. An asset whose front has
  no colour of its own reads 0 throughout: the other readings decide.

The rule's other sign of a front everywhere is "the frontal outline (narrow, symmetric, the head
centred over the body) ... seen from the sides as well", and a blob's is an outline that is no
side of the asset ("not the fish outline"). The sameness reading compares outlines only relative
to each other (the front's match less the sides'); three more numbers (``OUTLINE``) say how well
each view's silhouette matches the asset's at all: its best correlation (``sameness``' blurred
silhouettes) with the asset's front renders, averaged over the views, and with any of its renders,
averaged and at the worst view.
"""

from __future__ import annotations

import torch
from torch import Tensor

MARKING = ("marking_mean", "marking_max", "marking_min", "marking_views")
"""The names of ``marking_features``' values, in order (the eighth judge's on)."""
OUTLINE = ("outline_front_match", "outline_asset_match", "outline_asset_match_min")
"""The names of ``outline_features``' values, in order (the eighth judge's on)."""
FRONT = MARKING + OUTLINE
"""The names of ``front_features``' values: the marking's and the outline's."""
LEVELS = 6
"""Colour levels per channel (216 colours)."""
RATIO = 3.0
"""A colour is the front's when its share of the front's object pixels is more than this many times
its share of the sides' and back's (each share with one pixel added to every colour)."""
SHARE = 0.003
"""... and it covers more than this share of the front's object pixels (no stray pixel marks it)."""
FRONT_DEG, OTHER_DEG = 30.0, 60.0
"""The asset's renders within FRONT_DEG of azimuth 0 show its front; those OTHER_DEG or more away
its sides and back."""
FLOOR = 0.02
"""Added to the front's marking above the sides' before scaling by it, so that an asset whose front
shows little colour of its own reads near 0, not noise."""
CLIP = (-1.0, 3.0)
"""A view's scaled marking is kept within these bounds (a view of one colour can read far above 1)."""
HALF = 0.5
"""A view counts as marked (``marking_views``) when its scaled marking is above this."""


def colour_index(crops: Tensor) -> tuple[Tensor, Tensor]:
    """Crops [N, 3, H, W] in [0, 1] (white background) -> each pixel's colour (an index of
    ``LEVELS`` ** 3) [N, H, W] and whether it shows the object (``net.object_mask``) [N, H, W]."""
    from gdbench.metrics.judge.net import object_mask

    q = (crops.clamp(0, 1) * (LEVELS - 1e-4)).long()
    return q[:, 0] * LEVELS * LEVELS + q[:, 1] * LEVELS + q[:, 2], object_mask(crops, dim=1)


def _counts(colour: Tensor, ink: Tensor) -> Tensor:
    return torch.bincount(colour[ink > 0], minlength=LEVELS**3).double()


def marked_share(colour: Tensor, ink: Tensor, front: Tensor) -> Tensor:
    """[N] the share of each crop's object pixels whose colour is in ``front`` [LEVELS ** 3] (bool);
    0 for a crop with no object pixel."""
    hits = (front[colour] & (ink > 0)).sum((1, 2)).double()
    return (hits / ink.sum((1, 2)).double().clamp(min=1)).float()


def front_colours(crops: Tensor, azimuth: Tensor) -> tuple[Tensor, float, float]:
    """An asset's renders (crops [K, 3, H, W] uint8 or [0, 1], at ``azimuth`` [K] degrees) -> (its
    front colours [LEVELS ** 3] bool, the front renders' mean ``marked_share``, the sides' and
    back's)."""
    from gdbench.metrics.judge.sameness import _wrap

    x = crops.float() / 255.0 if crops.dtype == torch.uint8 else crops.float()
    colour, ink = colour_index(x)
    off = _wrap(azimuth.float()).abs()
    front, other = off <= FRONT_DEG, off >= OTHER_DEG
    if not bool(front.any()) or not bool(other.any()):
        raise ValueError(f"azimuth: expected renders within {FRONT_DEG:g} degrees of the front and "
                         f"{OTHER_DEG:g} or more from it, got {azimuth.tolist()}")  # fmt: skip
    cf, co = _counts(colour[front], ink[front]), _counts(colour[other], ink[other])
    share = cf / cf.sum().clamp(min=1)
    pf, po = (cf + 1) / (cf.sum() + LEVELS**3), (co + 1) / (co.sum() + LEVELS**3)
    mask = (pf / po > RATIO) & (share > SHARE)
    s = marked_share(colour, ink, mask)
    return mask, float(s[front].mean()), float(s[other].mean())


def _known(templates, caption: str) -> None:
    if caption not in templates.crops:
        raise ValueError(f"caption: the templates hold no renders of {caption!r}")


def asset_marking(templates, caption: str) -> tuple[Tensor, float, float]:
    """``front_colours`` of ``caption``'s templates, computed once per caption and kept on the
    templates object itself (so it lives and goes with them, and no other object is handed it)."""
    _known(templates, caption)
    kept = templates.__dict__.setdefault("_front_colours", {})
    if caption not in kept:
        kept[caption] = front_colours(templates.crops[caption], templates.azimuth[caption])
    return kept[caption]


def scaled(share: Tensor, front: float, other: float) -> Tensor:
    """Views' ``marked_share`` -> 0 at the asset's sides' and back's level, 1 at its front's
    (``FLOOR`` added to the difference, which counts as 0 where the front marks less than the
    sides), within ``CLIP``."""
    return ((share - other) / (max(front - other, 0.0) + FLOOR)).clamp(*CLIP)


def marking_features(crops: Tensor, templates, caption: str) -> Tensor:
    """The views' crops [V, 3, H, W] in [0, 1] (``net.crop_views``; the six sheet views) of one
    result of ``caption`` -> [len(MARKING)] numbers."""
    mask, front, other = asset_marking(templates, caption)
    colour, ink = colour_index(crops.float())
    m = scaled(marked_share(colour, ink, mask), front, other)
    return torch.stack([m.mean(), m.max(), m.min(), (m > HALF).float().mean()]).float()


def outline_features(crops: Tensor, templates, caption: str) -> Tensor:
    """The views' crops [V, 3, H, W] in [0, 1] (the six sheet views) of one result of ``caption`` ->
    [len(OUTLINE)]: each view's best silhouette correlation with the asset's renders within
    ``FRONT_DEG`` of its front, averaged over the views; with any render, averaged and the least."""
    from gdbench.metrics.judge.sameness import _colour_and_outline, _wrap

    _known(templates, caption)
    _, views = _colour_and_outline(crops.float())
    _, renders = _colour_and_outline(templates.crops[caption].float() / 255.0)
    front = _wrap(templates.azimuth[caption].float()).abs() <= FRONT_DEG
    sim = views @ renders.T
    best = sim.amax(1)
    return torch.stack([sim[:, front].amax(1).mean(), best.mean(), best.min()]).float()


def front_features(crops: Tensor, templates, caption: str) -> Tensor:
    """[len(FRONT)]: ``marking_features`` then ``outline_features`` of the six sheet views' crops."""
    return torch.cat([marking_features(crops, templates, caption), outline_features(crops, templates, caption)])
