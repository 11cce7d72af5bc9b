"""The middle of a training step: the (jittered) scene rendered into the prior's space, the step's
noise fields (structured + iid, or iid) and the score the prior gives (``trainer`` holds the step)."""

from __future__ import annotations

import time
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from gdbench.core.rand import randn
from gdbench.mechanisms.noise import NoiseState, advance_colors, mix, ratio_schedule
from gdbench.mechanisms.variational import jitter
from gdbench.train.densify import sh_coeffs

if TYPE_CHECKING:
    from gdbench.train.state import Context, TrainState
    from gdbench.train.views import Views


def render_for_prior(ctx: Context, state: TrainState, views: Views):
    """(render output, x): the (jittered) scene rendered and mapped into the prior's space (in rgb
    mode x = 2 rgb - 1 is computed outside the graph; ``apply_update`` backpropagates through rgb)."""
    from renderers.splat import rasterize

    cfg, p = ctx.cfg, state.params
    means, log_scales = p["means"], p["log_scales"]
    if cfg.vgs.enabled:
        means, log_scales = jitter(
            means,
            log_scales,
            views.sigma,
            gamma=cfg.vgs.gamma,
            scene_radius=ctx.jitter_length,
            generator=state.streams["jitter"],
        )
    depth = cfg.prior.input_space == "rgb+depth" and ctx.mode == "rgb"
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
    if ctx.noise is None and ctx.noise_source is None:
        return [randn(shape, generator=iid, device=ctx.device) for _ in range(cfg.samples_per_step)]
    ratio = ratio_schedule(state.step, cfg.steps, cfg.noise.ratio_start, cfg.noise.ratio_end)
    if ctx.noise_source is not None:  # the user's noise source (mechanisms/methods.py) in place of the cloud's
        n_s = _user_noise(ctx, state, views, shape)
        return [mix(n_s, ratio, generator=iid, mode=cfg.noise.ratio) for _ in range(cfg.samples_per_step)]
    if cfg.noise.source == "pose":  # the control: one fixed field per pose (mechanisms/pose_noise.py)
        n_s = ctx.noise.render(views.poses, views.prior_cams, generator=state.streams["noise_colors"]).noise
        return [mix(n_s, ratio, generator=iid, mode=cfg.noise.ratio) for _ in range(cfg.samples_per_step)]
    colors = state.noise_colors
    if state.step > 0:  # step 0 uses the initial draw
        nc = NoiseState(colors)
        colors = advance_colors(nc, cfg.noise.redraw, beta=cfg.noise.ou_beta, generator=state.streams["noise_colors"])
        colors = colors.colors
    if update:
        state.noise_colors = colors
    # the colours are this run's own normal draws: no scan for non-finite values
    gen = state.streams["noise_colors"]
    n_s = ctx.noise.render(colors, views.prior_cams, generator=gen, check_values=False).noise
    return [mix(n_s, ratio, generator=iid, mode=cfg.noise.ratio) for _ in range(cfg.samples_per_step)]


def _user_noise(ctx: Context, state: TrainState, views: Views, shape) -> Tensor:
    """The user's noise source's field for this step, checked (shape, dtype, finite)."""
    from gdbench.mechanisms.methods import NoiseRequest

    p = views.poses
    req = NoiseRequest(tuple(shape), state.step, ctx.cfg.steps, p.azimuth.float(), p.elevation.float(),
                       p.fovy.float(), views.prior_cams, state.streams["noise_colors"], ctx.device)  # fmt: skip
    n = ctx.noise_source(req)
    if not isinstance(n, Tensor) or tuple(n.shape) != tuple(shape) or not n.is_floating_point():
        got = f"{n.dtype} {tuple(n.shape)}" if isinstance(n, Tensor) else type(n).__name__
        raise ValueError(f"noise.source {ctx.cfg.noise.source!r}: expected a float tensor {tuple(shape)}, got {got}")
    if not bool(torch.isfinite(n).all()):
        raise ValueError(f"noise.source {ctx.cfg.noise.source!r}: returned NaN or Inf at step {state.step}")
    return n.to(ctx.device, torch.float32)


def _guided(ctx: Context, D: Tensor, xd: Tensor, sigma: float, step: int) -> Tensor:
    """The user's guidance's gradient on x, checked (shape like x, finite)."""
    g = ctx.guidance(D, xd, sigma, step, ctx.cfg.steps)
    if not isinstance(g, Tensor) or g.shape != xd.shape or not g.is_floating_point():
        got = f"{g.dtype} {tuple(g.shape)}" if isinstance(g, Tensor) else type(g).__name__
        raise ValueError(
            f"guidance {ctx.cfg.guidance!r}: expected a float tensor shaped like x {tuple(xd.shape)}, got {got}"
        )
    if not bool(torch.isfinite(g).all()):
        raise ValueError(f"guidance {ctx.cfg.guidance!r}: returned NaN or Inf at step {step}")
    return g.to(xd.device, xd.dtype)


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
        if ctx.guidance is not None:  # the user's (mechanisms/methods.py), averaged over the K samples
            part = _guided(ctx, D, xd, sigma, state.step) / K
        else:
            part = diff / sigma if K == 1 else diff / sigma / K  # / 1 is exact: the same bits
        score = part if score is None else score + part
        resid += float((diff**2).mean()) / K
    return score, resid, t_noise, time.perf_counter() - t0 - t_noise
