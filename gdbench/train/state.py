"""What a training run holds: its fixed context (config, prior, noise renderer, schedules) and
its state (step, parameters, optimizer, densification, noise colours, random streams). The
step's parts (``views``, ``distill``, ``update``) read both; ``trainer`` builds them."""

from __future__ import annotations

import functools
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from gdbench.core.scene import GaussianScene
from gdbench.mechanisms.noise import NoiseRenderer
from gdbench.train.adam import Adam
from gdbench.train.config import TrainConfig
from gdbench.train.densify import PARAM_NAMES, SCENE_NAMES, DensifyState, DensifyStrategy, sh_coeffs
from gdbench.train.streams import set_stream_states, stream_states

Mode = Literal["rgb", "sd-rgb", "sd-latent"]


@dataclass
class Context:
    """What a run needs besides its state: fixed for the run, never checkpointed."""

    cfg: TrainConfig
    prior: object
    cond: object
    strategy: DensifyStrategy
    noise: NoiseRenderer | None
    background: Tensor
    sigmas: Tensor
    """All of the prior's ticks, ascending."""
    mode: Mode = "rgb"
    """rgb: pixel prior; sd-rgb: render RGB and encode it with the VAE (GaussianDiffusion);
    sd-latent: render the 4 latent channels directly at 1/8 resolution (SJC)."""
    factor: int = 1
    """The prior's input is the render downsampled by this (8 for SD latents)."""
    depth_points: Tensor | None = None
    """Stable Diffusion with depth conditioning: the initial point cloud whose projected depth
    conditions the ControlNet (3DFuse)."""
    latent_background: Tensor | None = None
    """sd-latent: the latent of the background colour."""
    jitter_length: float = 0.5
    """World length of one VGS unit for the means (``vgs_unit``)."""
    extent: float = 0.5
    """The scene's radius (``init.scene_extent``): world-size settings are fractions of it."""
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    """Where the parameters, renders and noise live (``cfg.device`` resolved); the random streams
    stay on the CPU, so every device draws the same numbers."""
    guidance: Callable | None = None
    """The user's guidance (``mechanisms.methods``), None for the built-in sjc and sds."""
    noise_source: Callable | None = None
    """The user's noise source (``mechanisms.methods``), None for the built-in cloud and pose."""

    @functools.cached_property
    def sigma_values(self) -> list[float]:
        """``sigmas`` as Python floats (the per-step draw bisects them)."""
        return self.sigmas.tolist()


@dataclass
class TrainState:
    step: int
    params: dict[str, Tensor]
    optimizer: Adam
    densify: DensifyState
    noise_colors: Tensor | None
    streams: dict[str, torch.Generator]
    history: list[dict] = field(default_factory=list)
    bad_steps: int = 0

    def scene(self) -> GaussianScene:
        """The current Gaussians, on the CPU (outputs and scores are made there)."""
        p = {k: self.params[k].detach().cpu() for k in PARAM_NAMES}
        sh = sh_coeffs(p)
        if sh.shape[-1] == 4:  # latent-mode features: colours by the linear latent preview
            from gdbench.priors.sd.prior import latent_to_rgb
            from renderers.splat.sh import C0

            sh = ((latent_to_rgb(sh[:, 0]) - 0.5) / C0)[:, None]
        return GaussianScene(*(p[k] for k in SCENE_NAMES), sh)

    def rng_state(self) -> dict[str, Tensor]:
        return stream_states(self.streams)

    def set_rng_state(self, states: dict[str, Tensor]) -> None:
        set_stream_states(self.streams, states)
