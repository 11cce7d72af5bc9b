"""The reference trainer: score distillation (SJC) with structured noise and variational
Gaussians, on any ``Prior``. State goes in and out explicitly (``init_state``,
``train_step``); ``train`` adds the loop, the progress bar, atomic checkpoints, resume and
the run folder's outputs.

One step, for a random view pi (the paper's pose ranges) and a noise level sigma:

    theta' = jitter(theta, sigma)                       (VGS, if on)
    x      = 2 render(theta', pi) - 1                    in [-1, 1]
    n      = r_t n_s(pi) + sqrt(1 - r_t^2) n_iid         (structured noise, if on; else iid)
    g      = mean over K samples of (D(x + sigma n; sigma, cond) - x) / sigma
    x.backward(-weight * w(sigma) * g);  Adam;  densify on schedule

sigma is uniform over the prior's ticks in [sigma_min, sigma_max] (SJC), optionally annealed;
the ``sds`` guidance uses DreamGaussian's linearly annealed timestep and w = 1 - abar.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from ..camera import SphericalPoses
from ..noise import NoiseRenderer, NoiseState, advance_colors, init_colors, make_noise_cloud, mix, ratio_schedule
from ..scene import GaussianScene
from ..variational import jitter
from .config import TrainConfig
from .densify import PARAM_NAMES, DensifyState, DensifyStrategy
from .init import initial_scene

SCENE_RADIUS = 0.5


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
    latent: str | None = None
    """Stable Diffusion: 'rgb' (render RGB, encode with the VAE) or 'latent' (render latents)."""
    depth_points: Tensor | None = None
    """Stable Diffusion with depth conditioning: the initial point cloud whose projected depth
    conditions the ControlNet (3DFuse)."""
    latent_background: Tensor | None = None
    """Latent mode: the latent of the background colour."""


@dataclass
class TrainState:
    step: int
    params: dict[str, Tensor]
    optimizer: torch.optim.Adam
    densify: DensifyState
    noise_colors: Tensor | None
    generator: torch.Generator
    history: list[dict] = field(default_factory=list)
    bad_steps: int = 0

    def scene(self) -> GaussianScene:
        p = {k: self.params[k].detach() for k in PARAM_NAMES}
        if p["sh"].shape[-1] == 4:  # latent-mode features: colours by the linear latent preview
            from renderers.splat.sh import C0

            from ..priors.stable_diffusion import latent_to_rgb

            p["sh"] = ((latent_to_rgb(p["sh"][:, 0]) - 0.5) / C0)[:, None]
        return GaussianScene(*(p[k] for k in PARAM_NAMES))


class TrainingDiverged(RuntimeError):
    """Raised when parameters stop being finite or gradients stay non-finite."""


def make_sd_prior(cfg: TrainConfig):
    """The Stable Diffusion prior of a config, with its semantic code (made or reloaded)."""
    from ..priors.sd_3dfuse import SemanticCodeConfig, load_semantic_code, semantic_code
    from ..priors.stable_diffusion import StableDiffusionPrior

    kw = dict(
        guidance_scale=cfg.sd_guidance, view_prompting=cfg.view_prompting != "none", dtype=getattr(torch, cfg.sd_dtype)
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


def make_context(cfg: TrainConfig, prior=None) -> Context:
    if prior is None and cfg.prior == "sd":
        prior = make_sd_prior(cfg)
    if prior is None:
        from ..priors.empirical import EmpiricalPrior

        prior = EmpiricalPrior(
            view_mode=cfg.view_prompting,
            window_deg=cfg.view_window_deg,
            depth_weight=1.0 if cfg.depth_conditioning else 0.0,
        )
    cond = prior.encode(cfg.prompt)
    latent = cfg.sd_mode if hasattr(prior, "encode_images") else None
    noise = None
    if cfg.structured_noise:
        cloud = make_noise_cloud(cfg.noise, prior.channels, generator=torch.Generator().manual_seed(cfg.seed + 7919))
        noise = NoiseRenderer(cloud, v_min=cfg.noise.v_min, cache_size=0)
    depth_points, latent_bg = None, None
    if latent is not None and cfg.depth_conditioning:  # 3DFuse: depth of the initial cloud
        depth_points = initial_scene(cfg, generator=torch.Generator().manual_seed(cfg.seed)).means.detach()
    if latent == "latent":
        with torch.no_grad():
            bg = torch.tensor(cfg.background, dtype=torch.float32).expand(1, 8 * prior.factor, 8 * prior.factor, 3)
            latent_bg = prior.encode_images(bg * 2 - 1).mean((0, 1, 2)).cpu()
    return Context(
        cfg,
        prior,
        cond,
        DensifyStrategy(cfg.densify, SCENE_RADIUS),
        noise,
        torch.tensor(cfg.background, dtype=torch.float32),
        prior.sigmas.float(),
        latent,
        depth_points,
        latent_bg,
    )


def _optimizer(params: dict[str, Tensor], cfg: TrainConfig) -> torch.optim.Adam:
    lr = {
        "means": cfg.optim.means,
        "quats": cfg.optim.quats,
        "log_scales": cfg.optim.scales,
        "opacity_logits": cfg.optim.opacities,
        "sh": cfg.optim.colors,
    }
    return torch.optim.Adam([{"params": [params[k]], "lr": lr[k], "name": k} for k in PARAM_NAMES], eps=1e-15)


def init_state(ctx: Context) -> TrainState:
    cfg = ctx.cfg
    g = torch.Generator().manual_seed(cfg.seed)
    bank = getattr(ctx.prior, "_banks", {}).get(getattr(ctx.cond, "caption", None))
    scene = initial_scene(cfg, generator=g, bank=bank)
    params = {k: getattr(scene, k).detach().clone() for k in PARAM_NAMES}
    if ctx.latent == "latent":  # 4 latent features per Gaussian, the latent of the initial colour
        with torch.no_grad():
            grey = torch.full((1, 8 * ctx.prior.factor, 8 * ctx.prior.factor, 3), 2 * cfg.init_color - 1)
            z = ctx.prior.encode_images(grey).mean((0, 1, 2)).cpu()
        params["sh"] = z.expand(params["means"].shape[0], 1, 4).clone()
    params = {k: v.requires_grad_(True) for k, v in params.items()}
    colors = init_colors(ctx.noise.cloud, generator=g).colors if ctx.noise is not None else None
    return TrainState(0, params, _optimizer(params, cfg), ctx.strategy.init_state(len(scene)), colors, g)


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
    ticks = s[(s >= cfg.sigma_min) & (s <= max(hi, cfg.sigma_min))]
    if ticks.numel() == 0:
        ticks = s[torch.argmin((s - cfg.sigma_min).abs())][None]
    return float(ticks[torch.randint(ticks.numel(), (1,), generator=g)]), 1.0


def _means_lr(cfg: TrainConfig, step: int) -> float:
    t = min(step / max(cfg.steps - 1, 1), 1.0)
    return math.exp((1 - t) * math.log(cfg.optim.means) + t * math.log(cfg.optim.means_final))


def train_step(state: TrainState, ctx: Context, *, update: bool = True) -> dict:
    """One optimisation step; returns its metrics. Non-finite gradients skip the step.

    ``update=False`` evaluates the step without changing the parameters, the optimizer or the
    step count: the same random draws (view, sigma, jitter, noise) give the residual the current
    parameters have, so a caller can compare before and after an update."""
    from renderers.splat import rasterize

    cfg, g, p = ctx.cfg, state.generator, state.params
    t0 = time.perf_counter()
    R = cfg.resolution
    poses = SphericalPoses.sample(
        cfg.views_per_step,
        generator=g,
        radius=cfg.camera_radius,
        fovy_range=cfg.fovy_range,
        azimuth_range=cfg.azimuth_range,
        elevation_range=cfg.elevation_range,
    )
    cams = poses.cameras(R, R)
    # Stable Diffusion works on latents at 1/8: structured noise is rendered there, and the
    # latent mode renders the Gaussians there too
    lat = R // ctx.prior.factor if ctx.latent is not None else R
    cams_x = poses.cameras(lat, lat) if ctx.latent is not None else cams
    sigma, w = sample_sigma(ctx, state.step, g)
    means, log_scales = p["means"], p["log_scales"]
    if cfg.vgs:
        means, log_scales = jitter(
            means, log_scales, sigma, gamma=cfg.vgs_gamma, scene_radius=SCENE_RADIUS, generator=g
        )
    depth_from_render = cfg.depth_conditioning and ctx.latent is None
    outputs = ("rgb", "alpha", "means2d", "visible") + (("depth",) if depth_from_render else ())
    latent_mode = ctx.latent == "latent"
    rcams, RR = (cams_x, lat) if latent_mode else (cams, R)
    out = rasterize(
        means,
        p["quats"],
        log_scales.exp(),
        torch.sigmoid(p["opacity_logits"]),
        p["sh"][:, 0] if latent_mode else p["sh"],
        rcams.viewmats,
        rcams.Ks,
        RR,
        RR,
        sh_degree=None if latent_mode else cfg.sh_degree,
        background=ctx.latent_background if latent_mode else ctx.background,
        outputs=outputs,
    )
    out.means2d.retain_grad()
    if latent_mode:
        x = out.rgb  # the 4 latent channels themselves
    elif ctx.latent == "rgb":
        x = ctx.prior.encode_images(out.rgb * 2 - 1)  # differentiable: the VAE encoder is in the graph
    else:
        x = out.rgb * 2 - 1
    xd = x.detach()
    if ctx.noise is not None:
        colors = state.noise_colors
        if state.step > 0:  # step 0 uses the initial draw
            colors = advance_colors(NoiseState(colors), cfg.noise.redraw, beta=cfg.noise.ou_beta, generator=g).colors
        if update:
            state.noise_colors = colors
        n_s = ctx.noise.render(colors, cams_x, generator=g).noise
        ratio = ratio_schedule(state.step, cfg.steps, cfg.noise.ratio_start, cfg.noise.ratio_end)
    score = torch.zeros_like(xd)
    resid = 0.0
    depth = out.depth[..., 0].detach() if depth_from_render else None
    if ctx.depth_points is not None:
        depth = _point_depth(ctx.depth_points, cams)
    for _ in range(cfg.samples_per_step):
        if ctx.noise is not None:
            n = mix(n_s, ratio, generator=g)
        else:
            n = torch.randn(xd.shape, generator=g)
        D = ctx.prior.denoise(
            xd + sigma * n,
            torch.full((xd.shape[0],), sigma),
            ctx.cond,
            azimuth=poses.azimuth.float(),
            elevation=poses.elevation.float(),
            depth=depth,
        )
        score += (D - xd) / sigma / cfg.samples_per_step
        resid += float(((D - xd) ** 2).mean()) / cfg.samples_per_step
    metrics = {
        "step": state.step + 1,
        "sigma": sigma,
        "residual": resid,
        "n": int(p["means"].shape[0]),
        "alpha": float(out.alpha.detach().mean()),
    }
    if not update:
        return metrics
    for opt_group in state.optimizer.param_groups:
        opt_group["params"][0].grad = None
    # mean over pixels and channels: Adam does not care about the scale, but densification thresholds
    # on screen-space gradients then mean what they mean in 3DGS (per-pixel-averaged losses)
    (-(cfg.weight * w) * (score * x).mean()).backward()
    grads_ok = all(bool(torch.isfinite(p[k].grad).all()) for k in PARAM_NAMES if p[k].grad is not None)
    if not grads_ok:
        state.bad_steps += 1
        metrics["skipped"] = 1
        if state.bad_steps > cfg.max_bad_steps:
            raise TrainingDiverged(
                f"{state.bad_steps} consecutive steps had non-finite gradients (last at step {state.step + 1}); "
                "lower the learning rates or the guidance weight. The last checkpoint is intact."
            )
    else:
        state.bad_steps = 0
        for opt_group in state.optimizer.param_groups:
            if opt_group["name"] == "means":
                opt_group["lr"] = _means_lr(cfg, state.step)
        state.optimizer.step()
        if not all(bool(torch.isfinite(p[k]).all()) for k in PARAM_NAMES):
            raise TrainingDiverged(
                f"parameters became non-finite at step {state.step + 1}; lower the learning rates "
                "or the guidance weight. The last checkpoint is intact; nothing was written."
            )
        state.densify = ctx.strategy.accumulate(state.densify, out.means2d, out.visible, RR, RR)
        state.densify, info = ctx.strategy.step(p, state.optimizer, state.densify, state.step + 1, generator=g)
        metrics |= {k: v for k, v in info.items() if v}
    state.step += 1
    metrics["seconds"] = time.perf_counter() - t0
    state.history.append(metrics)
    return metrics


def _point_depth(points: Tensor, cams) -> Tensor:
    """Depth [C, H, W] (0 where empty) of a point cloud drawn as small opaque Gaussians."""
    from renderers.splat import rasterize

    n = points.shape[0]
    with torch.no_grad():
        out = rasterize(
            points,
            torch.tensor([1.0, 0.0, 0.0, 0.0]).expand(n, 4),
            torch.full((n, 3), 0.01),
            torch.full((n,), 0.99),
            torch.zeros(n, 1),
            cams.viewmats,
            cams.Ks,
            cams.width,
            cams.height,
            outputs=("alpha", "depth"),
        )
    return torch.where(out.alpha[..., 0] > 0.5, out.depth[..., 0], torch.zeros_like(out.depth[..., 0]))


# ----------------------------------------------------------------------------- checkpoints
def checkpoint_path(cfg: TrainConfig) -> Path:
    return Path(cfg.out) / "checkpoint.pt"


def save_checkpoint(state: TrainState, ctx: Context, path: Path) -> Path:
    """Atomic: written to a temporary file in the same folder, then renamed over ``path``."""
    from .outputs import config_dict

    blob = {
        "step": state.step,
        "params": {k: v.detach() for k, v in state.params.items()},
        "optimizer": state.optimizer.state_dict(),
        "densify": state.densify.state_dict(),
        "noise_colors": state.noise_colors,
        "generator": state.generator.get_state(),
        "history": state.history,
        "bad_steps": state.bad_steps,
        "config": config_dict(ctx.cfg),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=path.parent, suffix=".pt.tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            torch.save(blob, f)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


def load_checkpoint(path: Path, ctx: Context) -> TrainState:
    from .outputs import config_dict

    blob = torch.load(path, map_location="cpu", weights_only=False)
    saved, now = blob["config"], config_dict(ctx.cfg)
    ignore = {"out", "progress", "steps", "checkpoint_every", "log_every", "turntable_frames"}
    diff = sorted(k for k in set(saved) | set(now) if k not in ignore and saved.get(k) != now.get(k))
    if diff:
        raise ValueError(
            f"out: {path.parent} holds a run with a different config (fields {diff}); "
            "use another --out, or --no-resume to start over"
        )
    params = {k: v.clone().requires_grad_(True) for k, v in blob["params"].items()}
    opt = _optimizer(params, ctx.cfg)
    opt.load_state_dict(blob["optimizer"])
    g = torch.Generator()
    g.set_state(blob["generator"])
    dens = DensifyState(blob["densify"]["grad2d"], blob["densify"]["count"])
    return TrainState(blob["step"], params, opt, dens, blob["noise_colors"], g, blob["history"], blob["bad_steps"])
