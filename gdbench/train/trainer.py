"""The reference trainer: score distillation (SJC) with structured noise and variational
Gaussians, on any ``Prior``. State goes in and out explicitly (``init_state``,
``train_step``); ``run.train`` adds the loop, the progress bar, checkpoints and outputs.

One step renders ``views_per_step`` random views pi (the paper's pose ranges) at one noise
level sigma:

    theta' = jitter(theta, sigma)                       (VGS, if on)
    x      = 2 render(theta', pi) - 1                    in [-1, 1]
    n      = a_t n_s(pi) + sqrt(1 - a_t^2) n_iid         (structured noise, if on; else iid)
    g      = mean over K samples of (D(x + sigma n; sigma, cond, pi) - x) / sigma
    x.backward(-weight * w(sigma) * g);  Adam;  densify on schedule

in four parts, each in its own module: ``views.sample_views`` (poses and sigma),
``distill.render_for_prior`` (jitter and render, in the prior's space), ``distill.distill``
(noise and the score) and ``update.apply_update`` (backward, the non-finite skip, Adam,
densification). This module holds the run's context and state, their set-up and the step.
Every kind of draw has its own random stream (``streams.py``), so presets with one seed are
paired.
"""

from __future__ import annotations

import math
import time

import torch
from torch import Tensor

from gdbench.mechanisms.noise import NoiseRenderer, init_colors, make_noise_cloud
from gdbench.train.adam import Adam
from gdbench.train.config import TrainConfig
from gdbench.train.densify import PARAM_NAMES, SCENE_NAMES, DensifyStrategy
from gdbench.train.distill import distill, render_for_prior
from gdbench.train.init import initial_scene, scene_extent
from gdbench.train.state import Context, Mode, TrainState
from gdbench.train.streams import make_streams
from gdbench.train.update import TrainingDiverged, apply_update
from gdbench.train.views import Views, sample_views

__all__ = [
    "Context",
    "TrainState",
    "TrainingDiverged",
    "Views",
    "apply_update",
    "distill",
    "init_state",
    "make_context",
    "render_for_prior",
    "sample_views",
    "train_step",
]


def make_context(cfg: TrainConfig, prior=None) -> Context:
    from gdbench.core.devices import resolve_device
    from gdbench.priors.factory import make_prior

    device = resolve_device(cfg.device, "device (--device)")
    prior = make_prior(cfg) if prior is None else prior
    cond = prior.encode(cfg.prompt)
    encoder = prior.encode_images  # Prior protocol: None for pixel priors
    # sd-rgb: the render encoded into the prior's input (SD's VAE, the learned prior's box filter)
    space = cfg.prior.input_space  # what the prior reads: rgb or latent, with +depth when it conditions on it
    latent = space.startswith("latent")
    mode: Mode = "rgb" if encoder is None else ("sd-latent" if latent else "sd-rgb")
    factor = int(prior.factor)
    streams = make_streams(cfg.seed)
    noise = None
    from gdbench.mechanisms.methods import is_builtin, resolve

    if cfg.noise.enabled and is_builtin("noise", cfg.noise.source):  # a user's source replaces the cloud
        cloud = make_noise_cloud(cfg.noise, prior.channels, generator=streams["noise_cloud"])
        if cfg.noise.source == "pose":  # the control: fields locked to the pose, seeded from the cloud's stream
            from gdbench.mechanisms.pose_noise import PoseLockedNoise

            seed = int(torch.randint(2**62, (1,), generator=streams["noise_cloud"]))
            noise = PoseLockedNoise(cloud, seed=seed, v_min=cfg.noise.v_min)
        else:
            noise = NoiseRenderer(cloud, v_min=cfg.noise.v_min, cache_size=0)
    depth_points, latent_bg = None, None
    if mode != "rgb" and space.endswith("+depth"):  # 3DFuse: depth of the initial cloud
        depth_points = initial_scene(cfg, generator=streams["init"]).means.detach().to(device)
    if mode == "sd-latent":
        with torch.no_grad():
            bg = torch.tensor(cfg.background, dtype=torch.float32).expand(1, 8 * factor, 8 * factor, 3)
            latent_bg = encoder(bg * 2 - 1).mean((0, 1, 2)).to(device)
    bank = prior.bank(cond)
    _check_bank_camera(cfg, bank)
    extent = scene_extent(cfg, generator=make_streams(cfg.seed)["init"], bank=bank)
    length = extent
    if cfg.vgs.unit == "pixel":
        mid = math.radians(sum(cfg.fovy_range) / 2)
        length = 2 * cfg.camera_radius * math.tan(mid / 2) / cfg.resolution
    return Context(
        cfg,
        prior,
        cond,
        DensifyStrategy(cfg.densify, cfg.steps, extent),
        noise,
        torch.tensor(cfg.background, dtype=torch.float32, device=device),
        prior.sigmas.float(),
        mode,
        factor,
        depth_points,
        latent_bg,
        length,
        extent,
        device,
        None if is_builtin("guidance", cfg.guidance) else resolve("guidance", cfg.guidance),
        None if is_builtin("noise", cfg.noise.source) or not cfg.noise.enabled else resolve("noise", cfg.noise.source),
    )


def _check_bank_camera(cfg: TrainConfig, bank) -> None:
    """The prior must see the object from the trainer's camera distance: a bank rendered at another
    radius shows it at another size, and the trainer would fit that size (a duck 1.5 times too
    large at --camera-radius 1.5 against a bank at radius 1)."""
    radius = getattr(getattr(bank, "config", None), "radius", None)
    if radius is not None and not math.isclose(float(radius), cfg.camera_radius, rel_tol=1e-6):
        raise ValueError(
            f"camera_radius: the prior's bank is rendered from distance {radius}, the training cameras are at "
            f"{cfg.camera_radius}; build the prior from this config (priors.factory.make_prior) or render its bank "
            "at the trainer's radius"
        )


def _optimizer(params: dict[str, Tensor], cfg: TrainConfig) -> Adam:
    lr = {
        "means": cfg.optim.means,
        "quats": cfg.optim.quats,
        "log_scales": cfg.optim.scales,
        "opacity_logits": cfg.optim.opacities,
        "sh": cfg.optim.colors,
        "sh_rest": cfg.optim.sh_rest,
    }
    # torch.optim.Adam(fused=True)'s kernel and bits without torch.optim (adam.py)
    groups = [{"params": [params[k]], "lr": lr[k], "name": k} for k in PARAM_NAMES]
    return Adam(groups, eps=1e-15)


def init_state(ctx: Context) -> TrainState:
    cfg = ctx.cfg
    streams = make_streams(cfg.seed)
    bank = ctx.prior.bank(ctx.cond)
    scene = initial_scene(cfg, generator=streams["init"], bank=bank)
    params = {k: getattr(scene, k).detach().clone() for k in SCENE_NAMES}
    params["sh"] = scene.sh[:, :1].detach().clone()
    params["sh_rest"] = scene.sh[:, 1:].detach().clone()
    if ctx.mode == "sd-latent":  # 4 latent features per Gaussian, the latent of the initial colour
        with torch.no_grad():
            grey = torch.full((1, 8 * ctx.factor, 8 * ctx.factor, 3), 2 * cfg.init_color - 1)
            z = ctx.prior.encode_images(grey).mean((0, 1, 2)).cpu()
        params["sh"] = z.expand(params["means"].shape[0], 1, 4).clone()
        params["sh_rest"] = torch.zeros(params["means"].shape[0], 0, 4)
    # drawn on the CPU (the same scene on every device), then moved
    params = {k: v.to(ctx.device).requires_grad_(True) for k, v in params.items()}
    colors = None
    if ctx.noise is not None:
        colors = init_colors(ctx.noise.cloud, generator=streams["noise_colors"]).colors.to(ctx.device)
    return TrainState(0, params, _optimizer(params, cfg), ctx.strategy.init_state(len(scene)), colors, streams)


def train_step(state: TrainState, ctx: Context, *, update: bool = True) -> dict:
    """One optimisation step; returns its metrics. Non-finite gradients skip the step.

    ``update=False`` evaluates the step without changing the parameters, the optimizer or the
    step count: the same random draws (restore ``state.rng_state()`` first) give the residual
    the current parameters have, so a caller can compare before and after an update."""
    t0 = time.perf_counter()
    views = sample_views(ctx, state)
    t1 = time.perf_counter()
    out, x = render_for_prior(ctx, state, views)
    depth = out.depth[..., 0].detach() if out.depth is not None else None
    if ctx.depth_points is not None:
        depth = _point_depth(ctx.depth_points, views.cams if ctx.mode != "sd-latent" else views.prior_cams)
    t2 = time.perf_counter()
    score, resid, t_noise, t_prior = distill(ctx, state, views, x.detach(), depth, update)
    t3 = time.perf_counter()
    metrics = {
        "step": state.step + 1,
        "sigma": views.sigma,
        "residual": resid,
        "n": int(state.params["means"].shape[0]),
        "alpha": float(out.alpha.detach().mean()),
    }
    if not update:
        return metrics
    metrics |= apply_update(state, ctx, views, out, x, score)
    state.step += 1
    t4 = time.perf_counter()
    # where the step's time went: views, the render (forward), noise, prior, update (backward,
    # Adam, densification)
    metrics |= {"t_views": t1 - t0, "t_render": t2 - t1, "t_noise": t_noise, "t_prior": t_prior, "t_update": t4 - t3}
    metrics["seconds"] = t4 - t0
    state.history.append(metrics)
    return metrics


def _point_depth(points: Tensor, cams) -> Tensor:
    """Depth [C, H, W] (0 where empty) of a point cloud drawn as small opaque Gaussians."""
    from renderers.splat import rasterize

    n, dev = points.shape[0], points.device
    with torch.no_grad():
        out = rasterize(
            points,
            torch.tensor([1.0, 0.0, 0.0, 0.0], device=dev).expand(n, 4),
            torch.full((n, 3), 0.01, device=dev),
            torch.full((n,), 0.99, device=dev),
            torch.zeros(n, 1, device=dev),
            cams.viewmats,
            cams.Ks,
            cams.width,
            cams.height,
            outputs=("alpha", "depth"),
        )
    return torch.where(out.alpha[..., 0] > 0.5, out.depth[..., 0], torch.zeros_like(out.depth[..., 0]))
