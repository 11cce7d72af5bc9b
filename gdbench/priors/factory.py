"""The prior a training config asks for: the embedded empirical prior, with a bank that matches
the trainer's cameras, or Stable Diffusion with its optional ControlNet and semantic code."""

from __future__ import annotations

from pathlib import Path

import torch


def make_prior(cfg):
    """The prior of a ``TrainConfig`` (``cfg.prior``: 'empirical', 'learned' or 'sd'). The empirical prior's
    bank is rendered at the trainer's camera distance, background and widest field of view, so it
    sees the object from where the trainer's cameras do (the object keeps its size in the world)."""
    if cfg.prior == "sd":
        return make_sd_prior(cfg)
    if cfg.prior == "learned":
        from gdbench.priors.learned.prior import LearnedPrior, model_for_front_bias

        model = model_for_front_bias(cfg.front_bias) if cfg.learned_model == "auto" else cfg.learned_model
        prior = LearnedPrior(
            model,
            device=_device(cfg),
            guidance_scale=cfg.learned_guidance,
            view_mode=cfg.view_prompting,
            variants=cfg.variants,
            resolution=cfg.resolution,
        )
        prior.check_cameras(cfg.camera_radius, cfg.background, cfg.fovy_range, cfg.elevation_range)
        return prior
    from gdbench.priors.empirical import EmpiricalPrior, bank_config_for

    return EmpiricalPrior(
        view_mode=cfg.view_prompting,
        window_deg=cfg.view_window_deg,
        depth_weight=1.0 if cfg.depth_conditioning else 0.0,
        front_bias=cfg.front_bias,
        variants=cfg.variants,
        bank_config=bank_config_for(
            cfg.resolution, cfg.fovy_range, background=tuple(cfg.background), radius=float(cfg.camera_radius)
        ),
    )


def _device(cfg) -> torch.device | None:
    """Where a network prior (learned, SD) runs: on the trainer's device when that is a GPU, else
    on CUDA when torch sees one (None: the prior's own choice; the renders stay on the CPU and the
    prior moves its inputs and outputs). The empirical prior's bank stays in host memory."""
    from gdbench.core.devices import resolve_device

    dev = resolve_device(cfg.device, "device (--device)")
    return dev if dev.type != "cpu" else None


def make_sd_prior(cfg):
    """The Stable Diffusion prior of a config, with its semantic code (made or reloaded)."""
    from gdbench.priors.sd.prior import StableDiffusionPrior
    from gdbench.priors.sd.threedfuse import SemanticCodeConfig, load_semantic_code, semantic_code

    kw = dict(
        guidance_scale=cfg.sd_guidance,
        view_prompting=cfg.view_prompting != "none",
        dtype=getattr(torch, cfg.sd_dtype),
        device=_device(cfg),
    )
    if cfg.sd_model == "tiny":
        prior = StableDiffusionPrior.tiny(seed=0, controlnet=cfg.depth_conditioning, **kw)
    else:
        controlnet = cfg.sd_controlnet if cfg.depth_conditioning else None
        if cfg.depth_conditioning and controlnet is None:
            raise ValueError("sd_controlnet: depth_conditioning with Stable Diffusion needs a depth ControlNet folder")
        prior = StableDiffusionPrior.from_pretrained(cfg.sd_model, controlnet=controlnet, **kw)
    if cfg.semantic_code:
        folder = Path(cfg.out) / "semantic"
        if (folder / "semantic.json").is_file():
            load_semantic_code(prior, folder)
        else:
            sc = SemanticCodeConfig(
                size=max(64, cfg.resolution), ti_steps=cfg.semantic_steps, lora_steps=cfg.semantic_steps, seed=cfg.seed
            )
            semantic_code(prior, cfg.prompt, folder, sc)
    return prior
