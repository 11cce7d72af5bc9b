"""The look of a result's views, as numbers the fourth judge's head reads beside the turntable's:
how sharp its edges are, how its colours spread, how saturated and how soft it is, how much of the
view it fills. None of them says where the front is; they say what kind of image the eye's readings
come from. The empirical prior draws thin, flat, often pale outlines and the learned prior soft,
full bodies, and the same outline reading means a front_everywhere on one and a blob on the other
(docs/scoring.md, the prior split): the trees (``trees.py``) read the look first.

Each number is read per view, at the turntables' 128 px (views of another size are box-filtered
to it first), then given as its mean and its spread over the views (``LOOK``).
"""

from __future__ import annotations

import torch
from torch import Tensor
from torch.nn import functional as F

SIZE = 128
"""The views' side the look is read at (the turntables' and the sheets')."""
PAPER = 0.92
"""A pixel whose grey is below this is the object's (the background is white)."""
PER_VIEW = ("edge_q90", "edge_q99", "edge_q999", "spread_r", "spread_g", "spread_b", "saturation", "soft",
            "area", "crop_detail")  # fmt: skip
"""Per view: quantiles 0.9, 0.99, 0.999 of the grey's neighbour differences over the whole view; the
object's colour spread (standard deviation per channel); its mean saturation (max minus min
channel); the share of its pixels that are partly covered (grey 0.6 to ``PAPER``); the share of
the view it fills; the mean vertical difference of its crop (``net.crop_views``)."""
LOOK = tuple(f"look_{k}" for k in PER_VIEW) + tuple(f"look_{k}_spread" for k in PER_VIEW)
"""The look numbers: each per-view number's mean over the views, then its standard deviation."""


def look_numbers(views: Tensor, crops: Tensor | None = None) -> Tensor:
    """[len(LOOK)] the look of ``views`` [V, H, W, 3] (uint8 or float in [0, 1], white background;
    V >= 2); ``crops`` [V, 3, S, S] are ``net.crop_views(views)`` where the caller has them."""
    from gdbench.metrics.judge.net import crop_views

    v = views.float() / 255.0 if views.dtype == torch.uint8 else views.float()
    v = v[..., :3]
    if crops is None:
        crops = crop_views(views)
    if v.shape[1:3] != (SIZE, SIZE):
        v = F.interpolate(v.permute(0, 3, 1, 2), size=(SIZE, SIZE), mode="area").permute(0, 2, 3, 1)
    grey = v.mean(-1)
    obj = (grey < PAPER).float()
    n = obj.sum((1, 2)).clamp(min=1)
    dx = (grey[:, :, 1:] - grey[:, :, :-1]).abs().flatten(1)
    dy = (grey[:, 1:, :] - grey[:, :-1, :]).abs().flatten(1)
    edges = torch.quantile(torch.cat([dx, dy], 1), torch.tensor([0.9, 0.99, 0.999]), dim=1).T  # [V, 3]
    m = obj[..., None]
    mean = (v * m).sum((1, 2)) / n[:, None]
    spread = ((v - mean[:, None, None]) ** 2 * m).sum((1, 2)).div(n[:, None]).sqrt()  # [V, 3]
    saturation = ((v.max(-1).values - v.min(-1).values) * obj).sum((1, 2)) / n
    soft = ((grey > 0.6) & (grey < PAPER)).float().sum((1, 2)) / n
    area = obj.mean((1, 2))
    detail = (crops[:, :, 1:, :] - crops[:, :, :-1, :]).abs().mean((1, 2, 3))
    per_view = torch.cat([edges, spread, saturation[:, None], soft[:, None], area[:, None], detail[:, None]], 1)
    return torch.cat([per_view.mean(0), per_view.std(0)])
