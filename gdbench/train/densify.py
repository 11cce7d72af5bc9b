"""Adaptive density control (3DGS), as a strategy object with explicit state.

``DensifyStrategy.init_state`` gives the state; after each backward, ``accumulate`` adds the
screen-space gradient of the means; ``step`` clones, splits, prunes and resets opacities on
the schedule, editing the parameters and the Adam moments together (new Gaussians start with
zero moments). Parameters are a dict of leaf tensors keyed by ``PARAM_NAMES``, each in its own
Adam parameter group.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import torch
from torch import Tensor

from gdbench.train.config import DensifyConfig, DensifySchedule

PARAM_NAMES = ("means", "quats", "log_scales", "opacity_logits", "sh", "sh_rest")
"""The trainer's parameters: ``sh`` is the base colour (SH band 0, [N, 1, D]) and ``sh_rest`` the
higher bands ([N, K - 1, D], empty at degree 0), each its own Adam group (3DGS trains the higher
bands at a twentieth of the base colour's rate)."""
SCENE_NAMES = ("means", "quats", "log_scales", "opacity_logits")
"""The parameters a ``GaussianScene`` takes as they are (its ``sh`` is ``sh`` and ``sh_rest`` joined)."""


def sh_coeffs(params: dict[str, Tensor]) -> Tensor:
    """All SH coefficients [N, K, D] of the trainer's parameters (``sh`` alone at degree 0)."""
    rest = params["sh_rest"]
    return params["sh"] if rest.shape[1] == 0 else torch.cat([params["sh"], rest], 1)


@dataclass
class DensifyState:
    grad2d: Tensor
    """[N] accumulated norm of the screen-space mean gradient (units of half the image size)."""
    count: Tensor
    """[N] number of views in which each Gaussian was visible."""

    def state_dict(self) -> dict:
        return {"grad2d": self.grad2d, "count": self.count}


def _edit(params: dict[str, Tensor], optimizer, keep: Tensor, extra: dict[str, Tensor]) -> None:
    """params[name] <- cat(params[name][keep], extra[name]) for every name, with Adam moments
    selected by ``keep`` and zeros for the new rows. ``keep`` is a boolean mask [N]."""
    for group in optimizer.param_groups:
        old = group["params"][0]
        name = group["name"]
        new = torch.cat([old.detach()[keep], extra[name].to(old)]).requires_grad_(True)
        st = optimizer.state.pop(old, None)
        if st is not None:
            n_new = extra[name].shape[0]
            for k in ("exp_avg", "exp_avg_sq"):
                if k in st:
                    st[k] = torch.cat([st[k][keep], st[k].new_zeros((n_new, *st[k].shape[1:]))])
            optimizer.state[new] = st
        group["params"][0] = new
        params[name] = new


class DensifyStrategy:
    """Densification of a ``steps``-step run: its schedule is ``config.resolve(steps)``; the
    clone/split and world-size prune thresholds are fractions of ``extent`` (the scene's radius)."""

    def __init__(self, config: DensifyConfig, steps: int, extent: float = 0.5):
        if not extent > 0:
            raise ValueError(f"extent: expected a positive scene radius, got {extent!r}")
        self.cfg = config
        self.schedule: DensifySchedule = config.resolve(steps)
        self.extent = extent

    def init_state(self, n: int) -> DensifyState:
        return DensifyState(torch.zeros(n), torch.zeros(n))

    def accumulate(
        self, state: DensifyState, means2d: Tensor, visible: Tensor, width: int, height: int
    ) -> DensifyState:
        """Add, per view, |d loss / d means2d| (per unit of half the image size) of each visible
        Gaussian, and count the views it was visible in.

        The loss is averaged over the pixels of all C views of the step, so each view's gradient
        is 1/C of what the same view alone would give: it is multiplied by C (gsplat's
        DefaultStrategy does the same), which makes the statistic per view whatever the number of
        views per step, and ``grad_threshold`` mean what it means in 3DGS (one view, a loss
        averaged over its pixels). ``means2d`` [C, N, 2] must have its ``.grad``; ``visible`` [C, N]."""
        if means2d.grad is None:
            return state
        C = means2d.shape[0]
        g = means2d.grad.detach().clone()
        g[..., 0] *= width / 2 * C
        g[..., 1] *= height / 2 * C
        norm = g.norm(dim=-1) * visible
        return DensifyState(state.grad2d + norm.sum(0).cpu(), state.count + visible.sum(0).float().cpu())

    def threshold(self, avg: Tensor, count: Tensor) -> float:
        """The statistic above which a Gaussian grows: ``grad_threshold``, or with ``grad_quantile``
        q that quantile of the statistic over the Gaussians seen since the last densification (the
        top 1 - q of them grow, whatever the scale of the score)."""
        q = self.cfg.grad_quantile
        if q is None:
            return self.cfg.grad_threshold
        seen = avg[count > 0]
        return float(torch.quantile(seen.double(), q)) if seen.numel() else math.inf

    def collects(self, step: int) -> bool:
        """Whether the screen-space gradients of 1-based ``step`` can still be used (a densification
        is due at this step or later); after the last one, the trainer skips gathering them."""
        return step <= self._last_collect

    @functools.cached_property
    def _last_collect(self) -> int:
        return self.schedule.last_collect()

    def is_due(self, step: int) -> tuple[bool, bool]:
        """(densify now, reset opacities now) at 1-based ``step``."""
        return self.schedule.grows(step), self.schedule.resets(step)

    @torch.no_grad()
    def step(
        self,
        params: dict[str, Tensor],
        optimizer,
        state: DensifyState,
        step: int,
        *,
        generator: torch.Generator,
    ) -> tuple[DensifyState, dict[str, int]]:
        """Clone / split / prune / reset as due at ``step``; returns the new state and counts."""
        grow, reset = self.is_due(step)
        info = {"cloned": 0, "split": 0, "pruned": 0, "reset": int(reset)}
        if grow:
            resets = self.schedule.reset_steps()
            huge = self.cfg.prune_scale_from == "start" or bool(resets and step > resets[0])
            info |= self._grow_and_prune(params, optimizer, state, generator, prune_huge=huge)
            state = self.init_state(params["means"].shape[0])
        if reset:
            c = self.cfg
            cap = math.log(c.reset_value / (1 - c.reset_value))
            op = params["opacity_logits"]
            op.data.clamp_(max=cap)
            st = optimizer.state.get(op)
            if st:
                st["exp_avg"].zero_()
                st["exp_avg_sq"].zero_()
        return state, info

    def _grow_and_prune(
        self, params, optimizer, state: DensifyState, generator: torch.Generator, *, prune_huge: bool = True
    ) -> dict[str, int]:
        c = self.cfg
        n = params["means"].shape[0]
        dev = params["means"].device  # the statistics are gathered on the CPU (accumulate)
        avg = (state.grad2d / state.count.clamp_min(1)).to(dev)
        scale = params["log_scales"].detach().exp().amax(-1)
        big = scale > c.percent_dense * self.extent
        hot = avg > self.threshold(avg, state.count.to(dev))
        room = max(0, c.max_gaussians - n)
        clone = hot & ~big
        split = hot & big
        # respect the cap: keep the hottest candidates
        for mask in (clone, split):
            if int(mask.sum()) > room:
                idx = torch.nonzero(mask).squeeze(1)
                order = torch.argsort(avg[idx], descending=True, stable=True)
                mask[:] = False
                mask[idx[order[:room]]] = True
            room -= int(mask.sum())
        p = {k: v.detach() for k, v in params.items()}
        # clone: duplicate as is; split: two samples from the Gaussian, scales / 1.6
        si = torch.nonzero(split).squeeze(1)
        s = p["log_scales"][si].exp()
        R = _rotmat(p["quats"][si])
        offsets = [torch.randn(si.numel(), 3, generator=generator).to(s) * s for _ in range(2)]
        split_means = [p["means"][si] + (R @ o[..., None])[..., 0] for o in offsets]
        new = {k: torch.cat([p[k][clone], p[k][si], p[k][si]]) for k in PARAM_NAMES if k not in ("means", "log_scales")}
        new["means"] = torch.cat([p["means"][clone], *split_means])
        new["log_scales"] = torch.cat([p["log_scales"][clone], *(2 * [p["log_scales"][si] - math.log(1.6)])])
        # prune over the densified set, as 3DGS does: transparent or huge Gaussians go, new ones included
        opac = torch.sigmoid(p["opacity_logits"])
        limit = c.prune_scale * self.extent if prune_huge else math.inf
        prune = (opac < c.prune_opacity) | (scale > limit)
        new_keep = (torch.sigmoid(new["opacity_logits"]) >= c.prune_opacity) & (
            new["log_scales"].exp().amax(-1) <= limit
        )
        # never prune everything: keep the most opaque Gaussian if all would go
        if bool((prune | split).all()) and not bool(new_keep.any()):
            prune[torch.argmax(torch.where(split, torch.full_like(opac, -1.0), opac))] = False
            split[torch.argmax(torch.where(split, torch.full_like(opac, -1.0), opac))] = False
        n_pruned = int((prune & ~split).sum()) + int((~new_keep).sum())
        _edit(params, optimizer, ~(prune | split), {k: v[new_keep] for k, v in new.items()})
        return {"cloned": int(clone.sum()), "split": int(split.sum()), "pruned": n_pruned}


def _rotmat(q: Tensor) -> Tensor:
    from renderers.splat.project import normalize_quats, quat_to_rotmat

    return quat_to_rotmat(normalize_quats(q))
