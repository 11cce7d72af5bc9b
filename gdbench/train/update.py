"""The end of a training step: the score's backward, the non-finite skip, Adam (``adam.Adam``) and
densification (``trainer`` holds the step)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from gdbench.core.private import non_finite_check_
from gdbench.train.config import TrainConfig
from gdbench.train.densify import PARAM_NAMES
from gdbench.train.init import SPHERE_RADIUS

if TYPE_CHECKING:
    from gdbench.train.state import Context, TrainState
    from gdbench.train.views import Views


class TrainingDiverged(RuntimeError):
    """Raised when parameters stop being finite or gradients stay non-finite."""


def _means_lr(cfg: TrainConfig, step: int, extent: float = SPHERE_RADIUS) -> float:
    """The means' learning rate at 0-based ``step``: ``optim.means`` decaying exponentially to
    ``optim.means_final`` over max(run, ``optim.means_decay_steps``) steps, in units of the scene
    extent (times extent / 0.5, so 1 at the paper's ball; 3DGS scales its position rate by its
    scene extent the same way)."""
    t = min(step / max(max(cfg.steps, cfg.optim.means_decay_steps) - 1, 1), 1.0)
    lr = math.exp((1 - t) * math.log(cfg.optim.means) + t * math.log(cfg.optim.means_final))
    return lr * (extent / SPHERE_RADIUS)


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
        _backward(x, g)
    else:  # rgb mode: x = 2 rgb - 1 (render_for_prior), dL/drgb = 2 dL/dx exactly (autograd's bits)
        _backward(out.rgb, g * 2)
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
    state.optimizer.step()
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


class _Seed(torch.autograd.Function):
    """A scalar whose backward hands ``grad`` to ``x`` as it is: ``_Seed.apply(x, grad).backward()``
    is ``x.backward(grad)`` (the same bits reach x's graph), without torch's check of a given
    gradient's shape, whose first call imports sympy (a slow import in every training process)."""

    @staticmethod
    def forward(ctx, x: Tensor, grad: Tensor) -> Tensor:  # type: ignore[override]
        ctx.grad = grad
        return x.new_zeros(())

    @staticmethod
    def backward(ctx, _one: Tensor):  # type: ignore[override]
        return ctx.grad, None


def _backward(x: Tensor, grad: Tensor) -> None:
    """``x.backward(grad)`` (``_Seed``); the shapes must match, as ``backward`` demands."""
    if grad.shape != x.shape:
        raise ValueError(f"grad: expected the shape of x, {list(x.shape)}, got {list(grad.shape)}")
    with torch.enable_grad():  # x.backward(grad) works under no_grad too: its graph exists already
        _Seed.apply(x, grad).backward()


_ONE = torch.ones(())


def _all_finite(tensors: list[Tensor]) -> bool:
    """Whether every entry is finite, in one operation over all tensors: the check of torch's
    GradScaler (it also multiplies by the inverse scale, here 1, which leaves every value as it
    is) instead of a float64 sum per tensor, about 12 operations fewer twice a step."""
    if not tensors:
        return True
    found = torch.zeros((), device=tensors[0].device)
    with torch.no_grad():
        non_finite_check_([t.detach() for t in tensors], found, _ONE.to(found))
    return not bool(found)
