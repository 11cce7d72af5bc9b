"""The judge's eye: a small network that reads which side of the asset a view shows.

Trained on the assets' own renders alone (no label of a result; ``judge/train.py``), it maps one
view of an object, cropped to the object and shrunk to ``SIZE`` px, to a distribution over the
asset's azimuth in ``BINS`` bins of ``360 / BINS`` degrees (bin 0 centred on the front, azimuth 0),
one head per caption. The crop (``crop_views``) removes what a result does not share with its asset
(how large it came out, where it sits in the frame) and keeps what a person reads a side from: the
outline's shape, where the features sit, the colours.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F

SIZE = 32
"""Width and height (px) of the network's input."""
BINS = 24
"""Azimuth bins (15 degrees each; bin b is centred on b * 360 / BINS)."""
INK = 0.1
"""A pixel belongs to the object when some channel is darker than white by this much (the results'
faint haze of stray Gaussians is lighter)."""


@dataclass(frozen=True)
class EyeConfig:
    captions: tuple[str, ...] = ()
    """The captions it knows, one output head each."""
    widths: tuple[int, ...] = (32, 64, 96, 128)
    """Channels of the convolutional stages (each halves the size: 32 -> 16 -> 8 -> 4 -> 2 px)."""
    hidden: int = 256
    inputs: str = "rgb"
    """What the eye sees: 'rgb' (the view) or 'mask' (only the object's outline, ``INK``: blind to
    colour and texture, which a distilled result shares least with its asset)."""

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, d: dict) -> EyeConfig:
        return cls(captions=tuple(d["captions"]), widths=tuple(d["widths"]), hidden=int(d["hidden"]),
                   inputs=d.get("inputs", "rgb"))  # fmt: skip


class Eye(nn.Module):
    """Views [B, 3, SIZE, SIZE] in [0, 1] (white background) and caption indices [B] -> azimuth
    logits [B, BINS]."""

    def __init__(self, config: EyeConfig):
        super().__init__()
        self.config = config
        layers, c = [], 3
        for w in config.widths:
            layers += [nn.Conv2d(c, w, 3, padding=1), nn.GroupNorm(8, w), nn.SiLU()]
            layers += [nn.Conv2d(w, w, 3, stride=2, padding=1), nn.GroupNorm(8, w), nn.SiLU()]
            c = w
        self.trunk = nn.Sequential(*layers)
        side = SIZE // 2 ** len(config.widths)
        self.mlp = nn.Sequential(nn.Flatten(), nn.Linear(c * side * side, config.hidden), nn.SiLU(), nn.Dropout(0.2))
        self.heads = nn.Linear(config.hidden, len(config.captions) * BINS)

    def forward(self, views: Tensor, caption: Tensor) -> Tensor:
        ink = 1.0 - views  # ink, not light: a zero background
        if self.config.inputs == "mask":
            ink = object_mask(views, 1, keepdim=True).expand_as(ink)
        h = self.heads(self.mlp(self.trunk(ink)))
        return h.view(-1, len(self.config.captions), BINS)[torch.arange(len(caption)), caption]


def object_mask(x: Tensor, dim: int = -1, keepdim: bool = False) -> Tensor:
    """1.0 where images ``x`` in [0, 1] (white background; channels along ``dim``) show the object
    (some channel darker than white by more than ``INK``), else 0.0."""
    return ((1.0 - x.min(dim, keepdim=keepdim).values) > INK).float()


def crop_views(views: Tensor, size: int = SIZE, margin: float = 0.08) -> Tensor:
    """Views [N, H, W, 3] (uint8 or float in [0, 1], white background) -> [N, 3, size, size]
    float: each cropped to a square about its object's extent (the 1st to 99th percentile of the
    object's pixels in x and y, ``INK``), widened by ``margin`` of that square on every side, padded
    with white and box-filtered to ``size``. A view with no object pixel is left whole."""
    x = views.float() / 255.0 if views.dtype == torch.uint8 else views.float()
    _, h, w, _ = x.shape
    ink = object_mask(x)
    total = ink.sum((1, 2))
    lo_y, hi_y = _quantiles(ink.sum(2), total)
    lo_x, hi_x = _quantiles(ink.sum(1), total)
    side = torch.maximum(torch.maximum(hi_y - lo_y, hi_x - lo_x), torch.tensor(2.0)) * (1 + 2 * margin)
    boxes = torch.stack([(lo_x + hi_x) / 2, (lo_y + hi_y) / 2, side], 1)
    empty = total < 4
    boxes[empty] = torch.tensor([w / 2, h / 2, float(max(h, w))])
    return _resample(x.permute(0, 3, 1, 2), boxes, size)


def _quantiles(mass: Tensor, total: Tensor, q: float = 0.01) -> tuple[Tensor, Tensor]:
    """The q and 1 - q quantiles (pixel coordinates, centres at +0.5) of each row of ``mass`` [N, L]."""
    cdf = mass.cumsum(1) / total.clamp(min=1)[:, None]
    lo = torch.searchsorted(cdf, torch.full((len(mass), 1), q)).squeeze(1).float() + 0.5
    hi = torch.searchsorted(cdf, torch.full((len(mass), 1), 1 - q)).squeeze(1).float() + 0.5
    return lo, hi.clamp(max=mass.shape[1] - 0.5)


def _resample(images: Tensor, boxes: Tensor, size: int) -> Tensor:
    """images [N, 3, H, W]; boxes [N, 3] (centre x, centre y, side, in pixels) -> [N, 3, size, size],
    white outside the image, box-filtered (an oversampled bilinear grid averaged down)."""
    n, _, h, w = images.shape
    over = 4
    t = (torch.arange(size * over, dtype=torch.float32) + 0.5) / (size * over) - 0.5  # [-0.5, 0.5)
    gx = (boxes[:, 0, None] + t[None] * boxes[:, 2, None]) / w * 2 - 1
    gy = (boxes[:, 1, None] + t[None] * boxes[:, 2, None]) / h * 2 - 1
    grid = torch.stack(
        [gx[:, None, :].expand(n, t.numel(), t.numel()), gy[:, :, None].expand(n, t.numel(), t.numel())], -1
    )
    out = F.grid_sample(images - 1.0, grid, mode="bilinear", padding_mode="zeros", align_corners=False) + 1.0
    return F.avg_pool2d(out, over)


def bin_centres() -> Tensor:
    """[BINS] azimuths (degrees) of the bins' centres."""
    return torch.arange(BINS, dtype=torch.float32) * (360.0 / BINS)
