"""Variational Gaussian splatting (paper section 3.3): jitter of positions and scales.

    theta' = theta + gamma * s(sigma) * eps,   eps ~ N(0, I),   s(sigma) = sigma / sqrt(1 + sigma^2)

applied to the means (times the scene radius, so the jitter is scale-free) and to the
log-scales. ``s`` is the VP noise level of the VE noise level sigma: the jitter follows the
diffusion noise level and stays bounded by gamma. Only the training render uses theta';
``eps`` carries no gradient, so d theta'/d theta = I and the gradient reaching theta is the
gradient at theta' (paper eq. 17).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal

import torch
from torch import Tensor

from gdbench.core.constraints import AtLeast, check_fields
from gdbench.core.rand import randn


@dataclass(frozen=True)
class VGSConfig:
    """The paper's variational Gaussians in a training run (its options: --vgs, --vgs-gamma,
    --vgs-unit)."""

    OPTIONS: ClassVar[tuple[str, ...]] = ("enabled", "gamma", "unit")
    """The fields that are command-line options (``core.constraints.flag`` names them)."""
    enabled: bool = True
    """Use the paper's variational Gaussians (section 3.3)."""
    gamma: Annotated[float, AtLeast(0)] = 0.05
    """gamma of the jitter theta' = theta + gamma s(sigma) eps (means in --vgs-unit lengths,
    log-scales as is)."""
    unit: Literal["scene", "pixel"] = "scene"
    """Length unit of the means' jitter: the scene radius (0.5) or the training pixel's footprint at
    the origin (2 r tan(fovy/2) / resolution at the middle fovy), which follows the resolution."""

    def __post_init__(self) -> None:
        check_fields(self, "vgs.")  # every field against its declared type, range and choices


def vp_level(sigma: float) -> float:
    """s(sigma) = sigma / sqrt(1 + sigma^2), in [0, 1)."""
    return sigma / math.sqrt(1.0 + sigma * sigma)


def jitter(
    means: Tensor,
    log_scales: Tensor,
    sigma: float,
    *,
    gamma: float = 0.05,
    scene_radius: float = 0.5,
    generator: torch.Generator,
    parts: Sequence[str] = ("means", "log_scales"),
) -> tuple[Tensor, Tensor]:
    """Jittered (means', log_scales'); gradients flow to the inputs unchanged."""
    if not math.isfinite(sigma) or sigma < 0:
        raise ValueError(f"sigma: expected a finite noise level >= 0, got {sigma}")
    if not math.isfinite(gamma) or gamma < 0:
        raise ValueError(f"gamma: expected a finite value >= 0, got {gamma}")
    if not scene_radius > 0:
        raise ValueError(f"scene_radius: expected a positive radius, got {scene_radius}")
    bad = set(parts) - {"means", "log_scales"}
    if bad:
        raise ValueError(f"parts: unknown names {sorted(bad)}; expected 'means' and/or 'log_scales'")
    if means.shape[:-1] != log_scales.shape[:-1]:
        raise ValueError(f"log_scales: expected shape {list(means.shape)}, got {list(log_scales.shape)}")
    amp = gamma * vp_level(sigma)

    def noise(x: Tensor) -> Tensor:
        return randn(x.shape, generator=generator).to(x)

    m = means + (amp * scene_radius) * noise(means) if "means" in parts else means
    s = log_scales + amp * noise(log_scales) if "log_scales" in parts else log_scales
    return m, s
