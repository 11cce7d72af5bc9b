"""Priors D(x; sigma, cond): the denoisers score distillation queries.

``Prior`` is the protocol; ``EmpiricalPrior`` (``empirical.py``) is the embedded CPU prior
built from procedural assets; the Stable Diffusion prior implements the same protocol.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Protocol, runtime_checkable

import torch
from torch import Tensor


@dataclass(frozen=True)
class RunView:
    """What a prior reads from the training run, and nothing else: its prompt and seed, the render
    size, the cameras' model (distance, fields of view, elevations) and background, the device and
    the run folder. A prior's config builds its prior from it (``make(run)``); the trainer's
    config gives it (``TrainConfig.run_view``)."""

    prompt: str
    seed: int
    resolution: int
    camera_radius: float
    fovy_range: tuple[float, float]
    elevation_range: tuple[float, float]
    background: tuple[float, float, float]
    device: str
    out: Path


@runtime_checkable
class Prior(Protocol):
    """A denoiser in the VE parametrisation: y = x + sigma n, D(y; sigma) estimates x.

    Images are [B, H, W, C] in [-1, 1] (C = ``channels``). ``sigmas`` are the noise levels
    the prior knows (ascending); score distillation samples among them.
    """

    channels: int
    sigmas: Tensor
    factor: int
    """The prior's input is the render downsampled by this (1 for pixels, 8 for SD latents)."""
    encode_images: object
    """None for pixel priors; else a function mapping RGB renders [B, H, W, 3] in [-1, 1] to the
    prior's input space (the VAE encoder of Stable Diffusion), differentiable."""

    def bank(self, cond: object) -> object | None:
        """The image bank behind a condition (initialisation from its depth maps), or None."""
        ...

    def encode(self, prompt: str) -> object:
        """Condition of a prompt (raises ValueError with a clear message for unusable prompts)."""
        ...

    def denoise(
        self,
        x: Tensor,
        sigma: Tensor,
        cond: object,
        *,
        azimuth: Tensor | None = None,
        elevation: Tensor | None = None,
        depth: Tensor | None = None,
        fovy: Tensor | None = None,
    ) -> Tensor:
        """x0 estimate [B, H, W, C] for noisy images x [B, H, W, C] at noise levels sigma [B].

        ``azimuth``/``elevation`` [B] (degrees) drive view-dependent prompting; ``depth``
        [B, H, W] the depth conditioning; ``fovy`` [B] (degrees) is the query camera's vertical
        field of view; priors that do not use them ignore them."""
        ...


def sd_abar(beta_start: float = 0.00085, beta_end: float = 0.012, steps: int = 1000) -> Tensor:
    """Cumulative alphas abar_t [steps] (float64) of Stable Diffusion's scaled-linear DDPM betas."""
    betas = torch.linspace(beta_start**0.5, beta_end**0.5, steps, dtype=torch.float64) ** 2
    return torch.cumprod(1 - betas, 0)


def ve_sigmas_from_betas(beta_start: float = 0.00085, beta_end: float = 0.012, steps: int = 1000) -> Tensor:
    """VE noise levels sigma_t = sqrt((1 - abar_t) / abar_t) of Stable Diffusion's scaled-linear
    DDPM schedule (as SJC converts them), ascending; about 0.029 to 14.6."""
    abar = sd_abar(beta_start, beta_end, steps)
    return torch.sqrt((1 - abar) / abar)


def nearest_tick(sigmas: Tensor, sigma) -> Tensor:
    """Index [B] (long) of the tick of ``sigmas`` nearest to each sigma, in log sigma; ValueError
    for a sigma that is not positive and finite."""
    s = torch.as_tensor(sigma, dtype=torch.float64).reshape(-1)
    if bool((s <= 0).any()) or not bool(torch.isfinite(s).all()):
        raise ValueError(f"sigma: expected positive finite noise levels, got {s.tolist()}")
    return (s.log()[:, None] - sigmas.double().log()[None]).abs().argmin(1)


def network_device(device: str) -> torch.device | None:
    """Where a network prior (learned, SD) runs for a trainer on ``device`` ('cpu', 'cuda' or
    'auto'): on the trainer's device when that is a GPU, else None (the prior's own choice: CUDA
    when torch sees one; the renders stay on the CPU and the prior moves its inputs and outputs).
    The empirical prior's bank stays in host memory."""
    from gdbench.core.devices import resolve_device

    dev = resolve_device(device, "device (--device)")
    return dev if dev.type != "cpu" else None
