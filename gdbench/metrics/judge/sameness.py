"""The judge's third reading, which goes through no azimuth: how alike a result's views are, and
how much more they look like the asset's front than its sides.

A person tells front_everywhere from fine by seeing the same picture from every camera, and a
blob by seeing no side of the asset at all. The eye (``net.Eye``) reads each view's azimuth,
which fails where a result is too blurred or too featureless for any side to be read; these six
numbers compare the views as pictures instead (``SAMENESS``):

- ``same_colour``, ``same_outline``: the mean correlation between every two of the six views (the
  sheet's azimuths 0, 60, ..., 300), cropped as the eye crops them and blurred, in colour and in
  silhouette;
- ``front_over_side``, ``front_over_side_outline``: how much better each view matches the asset's
  own renders within 30 degrees of its front than those 60 to 120 degrees either side, at best,
  averaged over the views (a front from every camera matches the front everywhere);
- ``same_colour_rel``, ``same_outline_rel``: the first two less the asset's own six views' (a
  teapot's views are alike by nature, a corgi's are not), so that the numbers mean the same on
  every kind;
- from the judge's third version, four more in colour (``ALIGNED``), each view against the asset's
  renders where its camera is (within ``ALIGNED_DEG`` of its azimuth): how well they match
  (``aligned``, a mean over the views), that less the best match at any azimuth
  (``aligned_over_best``: 0 where each view shows what its camera should see, below 0 where some
  other side of the asset fits it better), less the best match with the asset's front
  (``aligned_over_front``, over the five views that are not the front: below 0 where the front is
  seen from the side) and the worst view's match (``aligned_min``, of those five; of every view
  where all are bunched at the front). A result that
  shows the asset as it is matches it where it should; a front everywhere matches the front; a
  blob matches nothing well.

The asset's renders are ``Templates``: for every caption, each procedural variant at ``BINS``
azimuths about the turntables' elevation, cropped as the eye crops them (uint8, shipped in the
judge's folder as templates.safetensors and hashed into its version). Measured on v3's and the
spent fresh set's sheets, leave-kind-out (docs/scoring.md, "The Janus judge").
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import torch
from torch import Tensor

SAMENESS = (
    "same_colour",
    "same_outline",
    "front_over_side",
    "front_over_side_outline",
    "same_colour_rel",
    "same_outline_rel",
    "aligned",
    "aligned_over_best",
    "aligned_over_front",
    "aligned_min",
)
"""The names of ``sameness_features``' values, in order (the second judge read the first six)."""
ALIGNED = 4
"""The last ``ALIGNED`` of ``SAMENESS`` are the views matched where their cameras are (the third judge's)."""
ALIGNED_DEG = 15.0
"""A template is where a view's camera is when their azimuths are within this many degrees (and shows
the front within this many of 0)."""
BLUR_PX = 1.5
"""The blur (Gaussian sigma, pixels of the 32 px crop) before views are compared: a result's
detail is not the asset's."""
ELEVATION = 15.0
"""The turntables' and sheets' elevation (degrees), about which the templates are drawn."""
BINS = 36
"""Template azimuths per caption and variant (10 degrees apart)."""
SHEET = (0.0, 60.0, 120.0, 180.0, 240.0, 300.0)
"""The azimuths whose views are compared with each other (a label sheet's six)."""
FRONT_DEG, SIDE_DEG = 30.0, (60.0, 120.0)
"""A template shows the front within FRONT_DEG of azimuth 0, a side between SIDE_DEG either way."""


@dataclass
class Templates:
    """The assets' renders the views are compared with: per caption, crops [K, 3, 32, 32] (uint8)
    at azimuths [K] (degrees) and the variant each shows [K]."""

    crops: dict[str, Tensor]
    azimuth: dict[str, Tensor]
    variant: dict[str, Tensor]

    @classmethod
    def from_data(cls, crops: Tensor, data) -> Templates:
        """From the eye's data (``judge_build.eye_crops``): for every caption and variant, the render
        nearest each of ``BINS`` azimuths at ``ELEVATION`` (distance: azimuth and elevation
        degrees added)."""
        targets = torch.arange(BINS, dtype=torch.float32) * (360.0 / BINS)
        out: dict[str, list] = {"crops": {}, "azimuth": {}, "variant": {}}
        for ci, caption in enumerate(data.captions):
            picks = []
            for v in data.variant[data.caption == ci].unique().tolist():
                sel = ((data.caption == ci) & (data.variant == v)).nonzero().flatten()
                d = _wrap(data.azimuth[sel][None] - targets[:, None]).abs()
                d = d + (data.elevation[sel][None] - ELEVATION).abs()
                picks.append(sel[d.argmin(1)])
            idx = torch.cat(picks)
            out["crops"][caption] = (crops[idx] * 255.0).round().clamp(0, 255).to(torch.uint8)
            out["azimuth"][caption] = data.azimuth[idx].float()
            out["variant"][caption] = data.variant[idx]
        return cls(**out)

    def save(self, path: Path, metadata: dict | None = None) -> bytes:
        """The templates as safetensors bytes (written to ``path`` atomically)."""
        from safetensors.torch import save

        from gdbench.core.io import atomic_write

        state = {f"{kind}/{caption}": getattr(self, kind)[caption].contiguous()
                 for kind in ("crops", "azimuth", "variant") for caption in self.crops}  # fmt: skip
        blob = save(state, metadata={k: str(v) for k, v in (metadata or {}).items()})
        atomic_write(Path(path), lambda f: f.write(blob))
        return blob

    @classmethod
    def load(cls, path: Path) -> Templates:
        from safetensors.torch import load_file

        out: dict[str, dict] = {"crops": {}, "azimuth": {}, "variant": {}}
        for key, value in load_file(str(path)).items():
            kind, caption = key.split("/", 1)
            out[kind][caption] = value
        return cls(**out)


def _wrap(deg: Tensor) -> Tensor:
    return (deg + 180.0) % 360.0 - 180.0


def _unit(x: Tensor) -> Tensor:
    """Rows of ``x`` flattened, centred and scaled to unit length (correlation by dot product)."""
    x = x.flatten(1)
    x = x - x.mean(1, keepdim=True)
    return x / x.norm(dim=1, keepdim=True).clamp(min=1e-6)


def _colour_and_outline(crops: Tensor) -> tuple[Tensor, Tensor]:
    """Crops [N, 3, S, S] in [0, 1] -> (blurred colour, silhouette of the blurred crop), unit rows."""
    from gdbench.metrics.judge.train import _blur

    c = _blur(crops.float(), torch.full((len(crops),), BLUR_PX))
    sil = (c.mean(1, keepdim=True) < 0.9).float()
    return _unit(c), _unit(sil)


def _mean_off_diagonal(u: Tensor) -> Tensor:
    n = len(u)
    return (u @ u.T)[~torch.eye(n, dtype=torch.bool)].mean()


def sheet_picks(azimuths: Tensor) -> Tensor:
    """Indices of the views nearest the sheet's six azimuths (all of a sheet's; six of a turntable's)."""
    return torch.stack([_wrap(azimuths - a).abs().argmin() for a in SHEET])


def sameness_features(crops: Tensor, azimuths: Tensor, templates: Templates, caption: str) -> Tensor:
    """[len(SAMENESS)] for one result: ``crops`` [V, 3, 32, 32] (``net.crop_views`` of its views)
    at camera ``azimuths`` [V] (degrees)."""
    pick = sheet_picks(azimuths)
    v, vs = _colour_and_outline(crops[pick])
    r, rs = _colour_and_outline(templates.crops[caption].float() / 255.0)
    a = _wrap(templates.azimuth[caption])
    front = a.abs() <= FRONT_DEG
    side = (a.abs() >= SIDE_DEG[0]) & (a.abs() <= SIDE_DEG[1])
    if not front.any() or not side.any():
        raise ValueError(f"templates: no render of the asset within {FRONT_DEG:g} degrees of its front or between "
                         f"{SIDE_DEG[0]:g} and {SIDE_DEG[1]:g} of it, for {caption!r}; draw them again")  # fmt: skip
    same, same_sil = _mean_off_diagonal(v), _mean_off_diagonal(vs)
    sim, sim_sil = v @ r.T, vs @ rs.T
    over = (sim[:, front].amax(1) - sim[:, side].amax(1)).mean()
    over_sil = (sim_sil[:, front].amax(1) - sim_sil[:, side].amax(1)).mean()
    own, own_sil = [], []
    for variant in templates.variant[caption].unique():
        away = 1000.0 * (templates.variant[caption] != variant)
        mine = torch.stack([(_wrap(a - t).abs() + away).argmin() for t in SHEET])
        own.append(_mean_off_diagonal(r[mine]))
        own_sil.append(_mean_off_diagonal(rs[mine]))
    rel, rel_sil = same - torch.stack(own).mean(), same_sil - torch.stack(own_sil).mean()
    return torch.cat([torch.stack([same, same_sil, over, over_sil, rel, rel_sil]), _aligned(sim, a, azimuths[pick])])


def _aligned(sim: Tensor, a: Tensor, view_az: Tensor) -> Tensor:
    """The ``ALIGNED`` numbers from the views' colour similarity to the templates ``sim`` [6, K],
    the templates' azimuths ``a`` [K] and the views' camera azimuths [6] (degrees). Where no view
    is away from the front (views bunched within ``ALIGNED_DEG`` of it), the last two are over
    every view."""
    here = _wrap(a[None] - view_az[:, None]).abs() <= ALIGNED_DEG
    at_front = a.abs() <= ALIGNED_DEG
    if not here.any(1).all() or not at_front.any():
        gap = float(_wrap(a[None] - view_az[:, None]).abs().amin(1).max())
        raise ValueError(f"templates: no render of the asset within {ALIGNED_DEG:g} degrees of a view's azimuth or of "
                         f"the front (the nearest is {gap:.1f} degrees off); draw the templates again")  # fmt: skip
    floor = torch.tensor(-2.0)  # below any correlation: excluded from a max
    aligned = torch.where(here, sim, floor).amax(1)
    front = torch.where(at_front[None], sim, floor).amax(1)
    away = _wrap(view_az).abs() > ALIGNED_DEG
    if not away.any():
        away = torch.ones_like(away)
    return torch.stack([aligned.mean(), (aligned - sim.amax(1)).mean(), (aligned - front)[away].mean(),
                        aligned[away].min()])  # fmt: skip
