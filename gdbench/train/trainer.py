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

in four parts: ``sample_views`` (poses and sigma), ``render_for_prior`` (jitter and render, in
the prior's space), ``distill`` (noise and the score) and ``apply_update`` (backward, the
non-finite skip, Adam, densification). Every kind of draw has its own random stream
(``streams.py``), so presets with one seed are paired.
"""

from __future__ import annotations

import bisect
import functools
import math
import struct
import time
from dataclasses import dataclass, field
from typing import Literal

import torch
from torch import Tensor

from ..camera import Cameras, SphericalPoses
from ..noise import NoiseRenderer, NoiseState, advance_colors, init_colors, make_noise_cloud, mix, ratio_schedule
from ..rand import randn
from ..scene import GaussianScene
from ..variational import jitter
from .config import TrainConfig
from .densify import PARAM_NAMES, SCENE_NAMES, DensifyState, DensifyStrategy, sh_coeffs
from .init import SPHERE_RADIUS, initial_scene, scene_extent
from .streams import make_streams, set_stream_states, stream_states

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

    @functools.cached_property
    def sigma_values(self) -> list[float]:
        """``sigmas`` as Python floats (the per-step draw bisects them)."""
        return self.sigmas.tolist()


@dataclass
class TrainState:
    step: int
    params: dict[str, Tensor]
    optimizer: torch.optim.Adam
    densify: DensifyState
    noise_colors: Tensor | None
    streams: dict[str, torch.Generator]
    history: list[dict] = field(default_factory=list)
    bad_steps: int = 0

    def scene(self) -> GaussianScene:
        p = {k: self.params[k].detach() for k in PARAM_NAMES}
        sh = sh_coeffs(p)
        if sh.shape[-1] == 4:  # latent-mode features: colours by the linear latent preview
            from renderers.splat.sh import C0

            from ..priors.stable_diffusion import latent_to_rgb

            sh = ((latent_to_rgb(sh[:, 0]) - 0.5) / C0)[:, None]
        return GaussianScene(*(p[k] for k in SCENE_NAMES), sh)

    def rng_state(self) -> dict[str, Tensor]:
        return stream_states(self.streams)

    def set_rng_state(self, states: dict[str, Tensor]) -> None:
        set_stream_states(self.streams, states)


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


class TrainingDiverged(RuntimeError):
    """Raised when parameters stop being finite or gradients stay non-finite."""


def make_context(cfg: TrainConfig, prior=None) -> Context:
    from ..priors.factory import make_prior

    prior = make_prior(cfg) if prior is None else prior
    cond = prior.encode(cfg.prompt)
    encoder = prior.encode_images  # Prior protocol: None for pixel priors
    # sd-rgb: the render encoded into the prior's input (SD's VAE, the learned prior's box filter)
    latent = cfg.sd_mode == "latent" and cfg.prior == "sd"
    mode: Mode = "rgb" if encoder is None else ("sd-latent" if latent else "sd-rgb")
    factor = int(prior.factor)
    streams = make_streams(cfg.seed)
    noise = None
    if cfg.structured_noise:
        cloud = make_noise_cloud(cfg.noise, prior.channels, generator=streams["noise_cloud"])
        noise = NoiseRenderer(cloud, v_min=cfg.noise.v_min, cache_size=0)
    depth_points, latent_bg = None, None
    if mode != "rgb" and cfg.depth_conditioning:  # 3DFuse: depth of the initial cloud
        depth_points = initial_scene(cfg, generator=streams["init"]).means.detach()
    if mode == "sd-latent":
        with torch.no_grad():
            bg = torch.tensor(cfg.background, dtype=torch.float32).expand(1, 8 * factor, 8 * factor, 3)
            latent_bg = encoder(bg * 2 - 1).mean((0, 1, 2)).cpu()
    bank = prior.bank(cond)
    _check_bank_camera(cfg, bank)
    extent = scene_extent(cfg, generator=make_streams(cfg.seed)["init"], bank=bank)
    length = extent
    if cfg.vgs_unit == "pixel":
        mid = math.radians(sum(cfg.fovy_range) / 2)
        length = 2 * cfg.camera_radius * math.tan(mid / 2) / cfg.resolution
    return Context(
        cfg,
        prior,
        cond,
        DensifyStrategy(cfg.densify, cfg.steps, extent),
        noise,
        torch.tensor(cfg.background, dtype=torch.float32),
        prior.sigmas.float(),
        mode,
        factor,
        depth_points,
        latent_bg,
        length,
        extent,
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


def _optimizer(params: dict[str, Tensor], cfg: TrainConfig) -> torch.optim.Adam:
    lr = {
        "means": cfg.optim.means,
        "quats": cfg.optim.quats,
        "log_scales": cfg.optim.scales,
        "opacity_logits": cfg.optim.opacities,
        "sh": cfg.optim.colors,
        "sh_rest": cfg.optim.sh_rest,
    }
    # fused: one kernel per group instead of ~10 ops (6x faster on CPU, deterministic)
    groups = [{"params": [params[k]], "lr": lr[k], "name": k} for k in PARAM_NAMES]
    return torch.optim.Adam(groups, eps=1e-15, fused=True)


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
    params = {k: v.requires_grad_(True) for k, v in params.items()}
    colors = init_colors(ctx.noise.cloud, generator=streams["noise_colors"]).colors if ctx.noise is not None else None
    return TrainState(0, params, _optimizer(params, cfg), ctx.strategy.init_state(len(scene)), colors, streams)


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


def _means_lr(cfg: TrainConfig, step: int, extent: float = SPHERE_RADIUS) -> float:
    """The means' learning rate at 0-based ``step``: ``optim.means`` decaying exponentially to
    ``optim.means_final`` over max(run, ``optim.means_decay_steps``) steps, in units of the scene
    extent (times extent / 0.5, so 1 at the paper's ball; 3DGS scales its position rate by its
    scene extent the same way)."""
    t = min(step / max(max(cfg.steps, cfg.optim.means_decay_steps) - 1, 1), 1.0)
    lr = math.exp((1 - t) * math.log(cfg.optim.means) + t * math.log(cfg.optim.means_final))
    return lr * (extent / SPHERE_RADIUS)


# ----------------------------------------------------------------------------- the step
def sample_views(ctx: Context, state: TrainState) -> Views:
    """Poses (``views`` stream) and the noise level (``sigma`` stream) of this step."""
    cfg = ctx.cfg
    poses = SphericalPoses.sample(
        cfg.views_per_step,
        generator=state.streams["views"],
        radius=cfg.camera_radius,
        fovy_range=cfg.fovy_range,
        azimuth_range=cfg.azimuth_range,
        elevation_range=cfg.elevation_range,
        spread_deg=cfg.views_spread_deg,
    )
    R, r = cfg.resolution, cfg.resolution // ctx.factor
    prior_cams = poses.cameras(r, r)
    cams = prior_cams if ctx.mode == "sd-latent" or r == R else poses.cameras(R, R)
    sigma, w = sample_sigma(ctx, state.step, state.streams["sigma"])
    return Views(poses, cams, prior_cams, sigma, w)


def render_for_prior(ctx: Context, state: TrainState, views: Views):
    """(render output, x): the (jittered) scene rendered and mapped into the prior's space (in rgb
    mode x = 2 rgb - 1 is computed outside the graph; ``apply_update`` backpropagates through rgb)."""
    from renderers.splat import rasterize

    cfg, p = ctx.cfg, state.params
    means, log_scales = p["means"], p["log_scales"]
    if cfg.vgs:
        means, log_scales = jitter(
            means,
            log_scales,
            views.sigma,
            gamma=cfg.vgs_gamma,
            scene_radius=ctx.jitter_length,
            generator=state.streams["jitter"],
        )
    depth = cfg.depth_conditioning and ctx.mode == "rgb"
    latent = ctx.mode == "sd-latent"
    out = rasterize(
        means,
        p["quats"],
        log_scales.exp(),
        torch.sigmoid(p["opacity_logits"]),
        p["sh"][:, 0] if latent else sh_coeffs(p),
        views.cams.viewmats,
        views.cams.Ks,
        views.cams.width,
        views.cams.height,
        sh_degree=None if latent else cfg.sh_degree,
        background=ctx.latent_background if latent else ctx.background,
        outputs=("rgb", "alpha", "means2d", "visible") + (("depth",) if depth else ()),
        check_values=False,  # the parameters are checked after every update (apply_update)
    )
    if ctx.strategy.collects(state.step + 1):
        out.means2d.retain_grad()  # densification's screen-space gradients
    if latent:
        x = out.rgb  # the 4 latent channels themselves
    elif ctx.mode == "sd-rgb":
        x = ctx.prior.encode_images(out.rgb * 2 - 1)  # differentiable: the VAE encoder is in the graph
    else:  # x = 2 rgb - 1 outside the graph: apply_update hands 2 dL/dx to rgb itself
        with torch.no_grad():
            x = out.rgb * 2 - 1
    return out, x


def _noise_fields(ctx: Context, state: TrainState, views: Views, shape, update: bool) -> list[Tensor]:
    """The K unit-variance noise fields of this step (structured + iid, or iid)."""
    cfg = ctx.cfg
    iid = state.streams["noise_iid"]
    if ctx.noise is None:
        return [randn(shape, generator=iid) for _ in range(cfg.samples_per_step)]
    colors = state.noise_colors
    if state.step > 0:  # step 0 uses the initial draw
        nc = NoiseState(colors)
        colors = advance_colors(nc, cfg.noise.redraw, beta=cfg.noise.ou_beta, generator=state.streams["noise_colors"])
        colors = colors.colors
    if update:
        state.noise_colors = colors
    n_s = ctx.noise.render(colors, views.prior_cams, generator=state.streams["noise_colors"]).noise
    ratio = ratio_schedule(state.step, cfg.steps, cfg.noise.ratio_start, cfg.noise.ratio_end)
    return [mix(n_s, ratio, generator=iid, mode=cfg.noise.ratio_mode) for _ in range(cfg.samples_per_step)]


def distill(ctx: Context, state: TrainState, views: Views, xd: Tensor, depth: Tensor | None, update: bool):
    """(score g [B, h, w, C], mean squared residual |D - x|^2, seconds in the noise, seconds in
    the prior) averaged over the K noise samples."""
    sigma, K = views.sigma, ctx.cfg.samples_per_step
    t0 = time.perf_counter()
    noises = _noise_fields(ctx, state, views, xd.shape, update)
    t_noise = time.perf_counter() - t0
    p = views.poses
    az, el, fovy = p.azimuth.float(), p.elevation.float(), p.fovy.float()
    sig = torch.full((xd.shape[0],), sigma)
    score, resid = None, 0.0
    for n in noises:
        D = ctx.prior.denoise(xd + sigma * n, sig, ctx.cond, azimuth=az, elevation=el, depth=depth, fovy=fovy)
        diff = D - xd
        part = diff / sigma if K == 1 else diff / sigma / K  # / 1 is exact: the same bits
        score = part if score is None else score + part
        resid += float((diff**2).mean()) / K
    return score, resid, t_noise, time.perf_counter() - t0 - t_noise


def apply_update(state: TrainState, ctx: Context, views: Views, out, x: Tensor, score: Tensor) -> dict:
    """Backward of the score, Adam (skipping non-finite steps) and densification; returns info."""
    cfg, p = ctx.cfg, state.params
    for opt_group in state.optimizer.param_groups:
        opt_group["params"][0].grad = None
    # the loss -(w) sum(score * x) / (elements of the render): averaged over the rendered pixels and
    # channels in every mode (in sd-rgb mode x is the VAE latent, and the sum runs over latents, but
    # the average is still per rendered pixel). Adam does not care about the scale; densification
    # thresholds screen-space gradients, which then mean what they mean in 3DGS (per-pixel-averaged
    # losses), for every prior. Its gradient is handed to x directly: no loss graph to build and walk
    g = score * (-(cfg.weight * views.weight) / out.rgb.numel())
    if x.requires_grad:
        x.backward(g)
    else:  # rgb mode: x = 2 rgb - 1 (render_for_prior), dL/drgb = 2 dL/dx exactly (autograd's bits)
        out.rgb.backward(g * 2)
    if not _all_finite([p[k].grad for k in PARAM_NAMES if p[k].grad is not None]):
        state.bad_steps += 1
        if state.bad_steps > cfg.max_bad_steps:
            raise TrainingDiverged(
                f"{state.bad_steps} consecutive steps had non-finite gradients (last at step {state.step + 1}); "
                "lower the learning rates or the guidance weight. The last checkpoint is intact."
            )
        return {"skipped": 1}
    state.bad_steps = 0
    for opt_group in state.optimizer.param_groups:
        if opt_group["name"] == "means":
            opt_group["lr"] = _means_lr(cfg, state.step, ctx.extent)
    adam_step(state.optimizer)
    if not _all_finite([p[k] for k in PARAM_NAMES]):
        raise TrainingDiverged(
            f"parameters became non-finite at step {state.step + 1}; lower the learning rates "
            "or the guidance weight. The last checkpoint is intact; nothing was written."
        )
    if ctx.strategy.collects(state.step + 1):
        w, h = views.cams.width, views.cams.height
        state.densify = ctx.strategy.accumulate(state.densify, out.means2d, out.visible, w, h)
    state.densify, info = ctx.strategy.step(
        p, state.optimizer, state.densify, state.step + 1, generator=state.streams["densify"]
    )
    return {k: v for k, v in info.items() if v}


_ONE = torch.ones(())


def _all_finite(tensors: list[Tensor]) -> bool:
    """Whether every entry is finite, in one operation over all tensors: the check of torch's
    GradScaler (it also multiplies by the inverse scale, here 1, which leaves every value as it
    is) instead of a float64 sum per tensor, about 12 operations fewer twice a step."""
    if not tensors:
        return True
    found = torch.zeros((), device=tensors[0].device)
    with torch.no_grad():
        torch._amp_foreach_non_finite_check_and_unscale_([t.detach() for t in tensors], found, _ONE.to(found))
    return not bool(found)


def adam_step(opt: torch.optim.Adam) -> None:
    """``opt.step()`` for the trainer's fused Adam (one parameter per group), calling the fused
    kernel directly: torch.optim's own step is about 1 ms of Python and checks per training step
    on 2 cores for 5 kernel calls of ~10 us. The same kernel on the same tensors, so the same
    bits (tests/test_train.py checks them against ``opt.step()``). Anything else, such as a
    group's first step, whose state torch creates, or other options, goes through ``opt.step()``."""
    todo = []  # (group, param, state)
    for g in opt.param_groups:
        p = g["params"][0]
        if p.grad is None:
            continue
        st = opt.state.get(p)
        if not st or len(g["params"]) != 1 or not _plain_fused(g):
            opt.step()
            return
        todo.append((g, p, st))
    if not todo:
        return
    torch._foreach_add_([st["step"] for _, _, st in todo], 1)
    for g, p, st in todo:
        b1, b2 = g["betas"]
        torch._fused_adam_([p], [p.grad], [st["exp_avg"]], [st["exp_avg_sq"]], [], [st["step"]], amsgrad=False,
                           lr=g["lr"], beta1=b1, beta2=b2, weight_decay=g["weight_decay"], eps=g["eps"],
                           maximize=False, grad_scale=None, found_inf=None)  # fmt: skip


def _plain_fused(g: dict) -> bool:
    """The options ``adam_step`` reproduces: fused, no amsgrad, maximize, decoupled decay or
    tensor learning rate."""
    return (
        g.get("fused") is True
        and not g.get("amsgrad")
        and not g.get("maximize")
        and not g.get("decoupled_weight_decay", False)
        and not g.get("capturable")
        and not g.get("differentiable")
        and not isinstance(g["lr"], Tensor)
    )


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
