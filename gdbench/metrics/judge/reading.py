"""The judge's reading of a result: each view's apparent azimuth, then the turntable as a whole.

Each view at camera azimuth a gets the eye's distribution q(b) over which side of the asset it
shows (``net.Eye``). Along the turntable a person's four classes leave different traces:

- **fine**: the apparent azimuth follows the camera: b = a - t for one turn t of the whole result
  (a result may be turned about the vertical axis);
- **front_everywhere**: the apparent azimuth stays at the front (or, with no face drawn, at the
  front's outline, which the back shares) whatever the camera: no view reads as a profile;
- **second_face**: it follows the camera, except that near the back it reads the front again;
- **blob**: no confident azimuth, or profiles at the sides with no front anywhere (front and back
  left undecided: the outline follows the camera only up to a half turn).

``turntable_features`` turns the readings into a few numbers that say how far each trace holds
(means over the views, so that six views and thirty-six read alike), which ``head.py`` maps to a
label.

A second reading needs no network: the outline's elongation (``log_aspect``: half the log ratio of
the object's horizontal to vertical variance) against the asset's own at every azimuth
(``AspectCurves``, measured on the same renders the eye learns from). It cannot tell front from back
or left from right, but it reads an end-on outline from a profile on results too blurred for any
feature to survive (measured on v3's sheets: docs/scoring.md, "The Janus judge").
"""

from __future__ import annotations

import torch
from torch import Tensor

from gdbench.metrics.judge.net import BINS

WINDOW = 1
"""Bins either side counted as the same reading (15 degrees a bin: +-22.5 degrees in all)."""

ASPECT_TOLERANCE = 0.2
"""Spread (log aspect) added to the asset's own spread at an azimuth when a view's outline is
compared with it: a result's outline is not the asset's."""

FEATURES = (
    "follow",
    "follow_half",
    "constant",
    "constant_half",
    "end_on",
    "profile_max",
    "front",
    "back_reads_front",
    "confidence",
    "entropy",
)
"""The names of ``turntable_features``' values, in order."""


def _near(q: Tensor) -> Tensor:
    """q [V, BINS] -> the mass within ``WINDOW`` bins of each bin [V, BINS] (circular)."""
    return sum(torch.roll(q, s, -1) for s in range(-WINDOW, WINDOW + 1))


def _shifted(q: Tensor, azimuths: Tensor) -> Tensor:
    """[V, BINS] -> [T, V]: for each turn t (a bin), the mass each view puts on b = a - t."""
    step = 360.0 / BINS
    k = torch.round(azimuths / step).long() % BINS  # the camera's bin
    t = torch.arange(BINS)
    idx = (k[None, :] - t[:, None]) % BINS  # [T, V]
    return q.gather(1, idx.T).T


def turntable_features(q: Tensor, azimuths: Tensor) -> Tensor:
    """The readings q [V, BINS] (rows summing to 1) of views at camera ``azimuths`` [V] (degrees)
    -> [len(FEATURES)] numbers, each a mean over the views:

    - follow: the best turn's share, max_t mean_v Q_v(a_v - t) (Q: q summed over +-``WINDOW``);
    - follow_half: the same, front and back not told apart (Q_v(a_v - t) + Q_v(a_v - t + 180));
    - constant: the best fixed reading's share, max_b mean_v Q_v(b) (the same side from every camera);
    - constant_half: the same for a fixed end-on or side axis (Q_v(b) + Q_v(b + 180));
    - end_on: the mass on the front and back quadrants (|b| < 45 or |b| > 135);
    - profile_max: the largest mass any one view puts on the side quadrants;
    - front: the mass on the front quadrant (|b| < 45);
    - back_reads_front: under the best turn, the front quadrant's mass in the views whose camera
      sees the result's back (within 45 degrees), over those views (0 where none);
    - confidence: the mean largest bin; entropy: the mean entropy of q (nats).
    """
    if q.ndim != 2 or q.shape[1] != BINS or len(azimuths) != len(q):
        raise ValueError(f"q: expected [V, {BINS}] readings of the {len(azimuths)} azimuths, got {tuple(q.shape)}")
    near = _near(q)
    half = near + torch.roll(near, BINS // 2, -1)
    follow_t = _shifted(near, azimuths).mean(1)
    follow, t = follow_t.max(0)
    follow_half = _shifted(half, azimuths).mean(1).max()
    constant = near.mean(0).max()
    constant_half = half.mean(0).max()
    b = torch.arange(BINS) * (360.0 / BINS)
    d = (b + 180.0) % 360.0 - 180.0
    front_q, back_q = d.abs() < 45, d.abs() > 135
    end_on = q[:, front_q | back_q].sum(1)
    front = q[:, front_q].sum(1)
    turn = float(t) * (360.0 / BINS)
    shows = (azimuths - turn + 180.0) % 360.0 - 180.0  # the asset's azimuth each camera sees under the turn
    at_back = shows.abs() > 135
    back_reads_front = front[at_back].mean() if bool(at_back.any()) else torch.tensor(0.0)
    entropy = -(q * q.clamp(min=1e-12).log()).sum(1)
    return torch.stack([
        follow, follow_half, constant, constant_half, end_on.mean(), (1 - end_on).max(), front.mean(),
        back_reads_front, q.max(1).values.mean(), entropy.mean(),
    ]).float()  # fmt: skip


def read_views(eye, crops: Tensor, caption: str) -> Tensor:
    """The eye's readings [V, BINS] (softmax) of ``crops`` [V, 3, SIZE, SIZE] of one result."""
    if caption not in eye.config.captions:
        raise ValueError(f"caption: the judge's eye knows no {caption!r}; it knows {len(eye.config.captions)} captions")
    c = torch.full((len(crops),), eye.config.captions.index(caption), dtype=torch.int64)
    with torch.no_grad():
        return torch.softmax(eye(crops, c), -1)


def best_turn(q: Tensor, azimuths: Tensor) -> float:
    """The turn t (degrees, in (-180, 180]) under which the readings follow the camera best."""
    t = int(_shifted(_near(q), azimuths).mean(1).argmax())
    turn = t * (360.0 / BINS)
    return turn - 360.0 if turn > 180.0 else turn


def log_aspect(views: Tensor) -> Tensor:
    """[V, H, W, 3] views (uint8 or [0, 1], white background) -> [V] half the log ratio of the
    object's (``net.INK``) horizontal to vertical second moment: 0 for a round outline, positive
    for a wide one (a profile of a long animal), negative for a tall one."""
    from gdbench.metrics.judge.net import object_mask

    x = views.float() / 255.0 if views.dtype == torch.uint8 else views.float()
    m = object_mask(x[..., :3])
    _, h, w = m.shape
    ys = torch.arange(h, dtype=torch.float32)[None, :, None]
    xs = torch.arange(w, dtype=torch.float32)[None, None, :]
    tot = m.sum((1, 2)).clamp(min=1)
    my = (m * ys).sum((1, 2)) / tot
    mx = (m * xs).sum((1, 2)) / tot
    vy = (m * (ys - my[:, None, None]) ** 2).sum((1, 2)) / tot
    vx = (m * (xs - mx[:, None, None]) ** 2).sum((1, 2)) / tot
    return 0.5 * (vx.clamp(min=1e-3).log() - vy.clamp(min=1e-3).log())


def aspect_readings(aspect: Tensor, mean: Tensor, spread: Tensor) -> Tensor:
    """[V] views' ``log_aspect`` against an asset's [BINS] mean and spread of it per azimuth bin ->
    [V, BINS] readings: a Gaussian likelihood (spread widened by ``ASPECT_TOLERANCE``), normalised."""
    s = (spread**2 + ASPECT_TOLERANCE**2).sqrt()
    return torch.softmax(-0.5 * ((aspect[:, None] - mean[None]) / s[None]) ** 2, -1)


def aspect_curves(aspect: Tensor, caption: Tensor, azimuth: Tensor, captions: tuple[str, ...]) -> dict:
    """The assets' elongation by azimuth bin from their renders (``log_aspect`` [N] of views of
    caption index [N] at azimuth [N]): {caption: {"mean": [BINS], "spread": [BINS]}}."""
    b = torch.round((azimuth % 360.0) / (360.0 / BINS)).long() % BINS
    out = {}
    for ci, c in enumerate(captions):
        mean, spread = [], []
        for k in range(BINS):
            a = aspect[(caption == ci) & (b == k)]
            mean.append(float(a.mean()) if len(a) else 0.0)
            spread.append(float(a.std()) if len(a) > 1 else 1.0)
        out[c] = {"mean": mean, "spread": spread}
    return out


def result_features(eye, curves: dict, views: Tensor, azimuths: Tensor, caption: str,
                    templates=None) -> tuple[Tensor, Tensor]:  # fmt: skip
    """One result's features: ``turntable_features`` of the eye's readings, then of the outline's
    (``aspect_readings`` against ``curves[caption]``), then, with ``templates``, the views' sameness
    (``sameness.sameness_features``), their look (``look.look_numbers``) and their front marking
    and outline (``marking.front_features``); and the eye's readings [V, BINS]. ``views`` [V, H, W, 3] at
    camera ``azimuths`` [V]. A judge reads the first of them that its head was fitted on
    (``Judge.n_features``), or, the seventh, the first 50 and the same less the asset's references
    (``Judge.head_rows``)."""
    from gdbench.metrics.judge.net import crop_views

    crops = crop_views(views)
    q = read_views(eye, crops, caption)
    c = curves[caption]
    qa = aspect_readings(log_aspect(views), torch.tensor(c["mean"]), torch.tensor(c["spread"]))
    parts = [turntable_features(q, azimuths), turntable_features(qa, azimuths)]
    if templates is not None:
        from gdbench.metrics.judge.look import look_numbers
        from gdbench.metrics.judge.marking import front_features
        from gdbench.metrics.judge.sameness import sameness_features

        six = sheet_views(azimuths)
        parts += [sameness_features(crops, azimuths, templates, caption), look_numbers(views[six], crops[six]),
                  front_features(crops[six], templates, caption)]  # fmt: skip
    return torch.cat(parts), q


def sheet_views(azimuths: Tensor) -> Tensor:
    """The indices of the views at a sheet's six azimuths (0, 60, ..., 300, within a degree) where
    ``azimuths`` [V] hold all six (a run turntable's 36 frames do), else every view: the look is
    read on the views a sheet shows, so that a run folder and its sheet give the same numbers (over
    36 frames the look's spreads differ from the six views' by up to 0.3 of their spread)."""
    from gdbench.metrics.judge.sameness import SHEET, sheet_picks

    pick = sheet_picks(azimuths.float())
    off = (azimuths.float()[pick] - torch.tensor(SHEET) + 180.0) % 360.0 - 180.0
    return pick if bool((off.abs() < 1.0).all()) else torch.arange(len(azimuths))
