"""The first part of a training step: its poses (the ``views`` stream) and its noise level (the
``sigma`` stream), the draws every preset with one seed shares (``trainer`` holds the step)."""

from __future__ import annotations

import bisect
import struct
from dataclasses import dataclass
from typing import TYPE_CHECKING, Annotated, ClassVar

import torch

from gdbench.core.camera import Cameras, SphericalPoses
from gdbench.core.constraints import AtLeast, Range, When, check_fields

if TYPE_CHECKING:
    from gdbench.train.state import Context, TrainState


@dataclass(frozen=True)
class ViewsConfig:
    """How many views one training step renders, and how far apart (its options:
    --views-per-step, --views-spread-deg). Where the cameras may be (radius, field of view,
    azimuth and elevation ranges) is the config's camera model, which the prior's bank and the
    scores share."""

    OPTIONS: ClassVar[tuple[str, ...]] = ("per_step", "spread_deg")
    """The fields that are command-line options (``core.constraints.flag`` names them)."""
    per_step: Annotated[int, AtLeast(1)] = 1
    """Views rendered per step; they share one jitter, one sigma and one draw of the noise cloud's
    colours (so one step already couples views through the structured noise)."""
    spread_deg: Annotated[float | None, Range(0, 180, lo_open=True, unit="degrees"), When("per_step", above=1)] = None
    """Views of one step (--views-per-step 2 or more): unset (the default) draws each anywhere in
    the pose ranges; a number keeps the others within +-this many degrees (azimuth and elevation)
    of the step's first view, so they see the same structured noise at the same surface points
    (docs/noise.md, "Does the noise reach two views?")."""

    def __post_init__(self) -> None:
        check_fields(self, "views.")  # every field against its declared type and range


@dataclass(frozen=True)
class Views:
    """The draws of one step that every preset with the same seed shares."""

    poses: SphericalPoses
    cams: Cameras
    """Cameras of the render (the latent resolution in sd-latent mode)."""
    prior_cams: Cameras
    """Cameras at the prior's input resolution (where the noise lives)."""
    sigma: float
    weight: float


def sample_sigma(ctx: Context, step: int, g: torch.Generator) -> tuple[float, float]:
    """(sigma, weight) for 0-based ``step``."""
    cfg = ctx.cfg
    s = ctx.sigmas
    if cfg.guidance == "sds":  # DreamGaussian: t from 0.98 T down to 0.02 T, linearly; w = 1 - abar
        frac = step / max(cfg.steps - 1, 1)
        i = round(((1 - frac) * 0.98 + frac * 0.02) * (len(s) - 1))
        sigma = float(s[i])
        return sigma, sigma * sigma / (1 + sigma * sigma)
    hi = cfg.sigma_max
    if cfg.anneal:
        hi = cfg.sigma_max + (cfg.sigma_min - cfg.sigma_max) * step / max(cfg.steps - 1, 1)
    # the ticks in [sigma_min, max(hi, sigma_min)], compared in float32 as the tensor comparison
    # s >= sigma_min would, found by bisection in the ascending list (no tensor operations)
    vals = ctx.sigma_values
    i0 = bisect.bisect_left(vals, _f32(cfg.sigma_min))
    i1 = bisect.bisect_right(vals, _f32(max(hi, cfg.sigma_min)))
    if i1 <= i0:
        return float(s[torch.argmin((s - cfg.sigma_min).abs())]), 1.0
    return vals[i0 + int(torch.randint(i1 - i0, (1,), generator=g))], 1.0


def _f32(x: float) -> float:
    """``x`` rounded to float32 (as a tensor comparison with a float32 tensor rounds it)."""
    return struct.unpack("f", struct.pack("f", x))[0]


def sample_views(ctx: Context, state: TrainState) -> Views:
    """Poses (``views`` stream) and the noise level (``sigma`` stream) of this step."""
    cfg = ctx.cfg
    poses = SphericalPoses.sample(
        cfg.views.per_step,
        generator=state.streams["views"],
        radius=cfg.camera_radius,
        fovy_range=cfg.fovy_range,
        azimuth_range=cfg.azimuth_range,
        elevation_range=cfg.elevation_range,
        spread_deg=cfg.views.spread_deg,
    )
    R, r = cfg.resolution, cfg.resolution // ctx.factor
    prior_cams = poses.cameras(r, r)
    cams = prior_cams if ctx.mode == "sd-latent" or r == R else poses.cameras(R, R)
    if ctx.device.type != "cpu":  # the poses stay on the CPU (the priors read them there)
        prior_cams = prior_cams.to(ctx.device)
        cams = prior_cams if ctx.mode == "sd-latent" or r == R else cams.to(ctx.device)
    sigma, w = sample_sigma(ctx, state.step, state.streams["sigma"])
    return Views(poses, cams, prior_cams, sigma, w)
