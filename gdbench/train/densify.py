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
import warnings
from dataclasses import dataclass, fields
from typing import Annotated, ClassVar, Literal

import torch
from torch import Tensor

from gdbench.core.constraints import AtLeast, Between, Positive, Range, check_fields, is_int


@dataclass(frozen=True)
class DensifyConfig:
    """Adaptive density control (3DGS): clone small and split large Gaussians whose screen-space
    gradient is high, prune transparent or huge ones, reset opacities periodically.

    The schedule (``start``, ``stop``, ``every``, ``reset_every``) follows the run's length: left
    unset, each is a fraction of the run (``*_frac``: the paper's 300, 1500, 50 and 400 steps at
    its 2000), rounded to whole steps; set, it is an absolute step count. ``resolve`` gives the
    schedule of a run, which never densifies on the last step and never resets opacities in the
    last ``recover_steps`` steps of the run (docs/training.md, "The densification schedule")."""

    OPTIONS: ClassVar[tuple[str, ...]] = ("enabled", "start", "stop", "every", "reset_every", "grad_quantile")
    """The fields that are command-line options (``core.constraints.flag`` names them: --densify,
    --densify-start, ...)."""
    enabled: bool = True
    """Densify at all (clone, split, prune, reset opacities; default: on). --no-densify trains the
    initial Gaussians as they are."""
    start: Annotated[int | None, AtLeast(0)] = None
    """Densification starts after this step (default: ``start_frac`` = 15% of --steps, rounded; the
    paper's 300 at 2000). Set, it is an absolute step."""
    stop: Annotated[int | None, AtLeast(0)] = None
    """Last step that may densify (default: ``stop_frac`` = 75% of --steps; 1500 at 2000). Set, it is
    an absolute step, and must not densify on the run's last step."""
    every: Annotated[int | None, AtLeast(1)] = None
    """Densify every this many steps (default: ``every_frac`` = 2.5% of --steps, at least
    ``min_every`` = 25; the paper's 50 at 2000). Set, it is an absolute step count."""
    reset_every: Annotated[int | None, AtLeast(1)] = None
    """Opacity reset interval, resets at its multiples up to --densify-stop (default: ``reset_frac``
    = 20% of --steps; the paper's 400 at 2000). Set, it is an absolute step count; no reset may
    fall in the last ``recover_steps`` (100) steps of the run, where opacities could not recover."""
    start_frac: Annotated[float, Between(0, 1)] = 0.15
    """Default ``start`` as a fraction of the run (the paper: 300 of 2000 steps)."""
    stop_frac: Annotated[float, Between(0, 1)] = 0.75
    """Default ``stop`` as a fraction of the run (1500 of 2000 steps)."""
    every_frac: Annotated[float, Between(0, 1)] = 0.025
    """Default ``every`` as a fraction of the run (the paper: 50 of 2000 steps)."""
    min_every: Annotated[int, AtLeast(1)] = 25
    """The default ``every`` is at least this many steps, whatever the run's length: the
    statistic a densification reads is gathered over that many steps. Measured on the duck
    (docs/training.md, "Short runs"): over 25 steps the Gaussians that grow overlap those of a
    200-step reading 0.41 (Jaccard; 0.43 at 4 views per step), 84% of the agreement of the paper's
    50 steps (0.49); over 3 steps, 0.23. Runs of 1000 steps and more are unchanged (their 2.5% is
    25 or more); a shorter run densifies less often, a 20-step run not at all."""
    reset_frac: Annotated[float, Between(0, 1)] = 0.2
    """Default ``reset_every`` as a fraction of the run (the paper: 400 of 2000 steps)."""
    recover_steps: Annotated[int, AtLeast(0)] = 100
    """No opacity reset in the last this many steps of the run: opacities need them to recover from
    the reset value (measured on the duck: 25-50 steps; docs/training.md). Resets of the default
    interval that would fall there are dropped; an explicit ``reset_every`` that puts one there is
    refused."""
    grad_threshold: Annotated[float, AtLeast(0)] = 2e-4
    """Mean screen-space gradient norm per view (per unit of half the image size, losses averaged
    over pixels) above which a Gaussian grows; 3DGS's default. About 5% of Gaussians exceed it
    mid-run (measured)."""
    grad_quantile: Annotated[float | None, Range(0, 1, hi_open=True)] = None
    """Instead of ``grad_threshold`` (default: the threshold 2e-4): grow the Gaussians whose
    statistic is above this quantile of the statistic over the Gaussians seen since the last
    densification (0.95: the top 5%). Growth then does not depend on the score's scale, which
    differs between guidance rules (sds-gs's weight 1 - abar): a way to hold paired presets' model
    sizes comparable (docs/training.md)."""
    percent_dense: Annotated[float, Positive()] = 0.01
    """Scale (fraction of the scene extent) separating clone (below) from split (above)."""
    prune_opacity: Annotated[float, Between(0, 1)] = 0.01
    """Gaussians below this opacity are pruned."""
    prune_scale: Annotated[float, Positive()] = 0.5
    """Gaussians larger than this fraction of the scene extent are pruned."""
    prune_scale_from: Literal["start", "reset"] = "start"
    """When the world-size prune (``prune_scale``) starts: with the first densification, or after
    the first opacity reset (3DGS and gsplat; never, in a run without one)."""
    reset_value: Annotated[float, Between(0, 1, open=True)] = 0.05
    """Opacities are capped at this value by a reset."""
    max_gaussians: Annotated[int, AtLeast(1)] = 30000
    """No densification grows the scene beyond this many Gaussians (the hottest candidates go first)."""
    max_growth: Annotated[float, Positive()] = 0.3
    """One densification adds at most this share of the Gaussians it starts from (clones before
    splits, the hottest first in each, as for ``max_gaussians``). Measured on the duck
    (docs/training.md, "Short runs"): the densifications of 1000- to 5000-step runs add at most
    0.26 (seeds 0-2), so it binds on none of them; those of 100- and 300-step runs add up to 0.40."""

    def __post_init__(self) -> None:
        check_fields(self, "densify.")  # every field against its declared type and range
        if self.start_frac > self.stop_frac:
            raise ValueError(f"densify.start_frac: {self.start_frac} is after stop_frac {self.stop_frac}")

    def resolve(self, steps: int) -> DensifySchedule:
        """The schedule of a ``steps``-step run. An explicit setting that would densify on the last
        step, reset opacities in the last ``recover_steps`` steps, or leave no densification at all
        raises ValueError naming it, the run's length and the limit."""
        if not is_int(steps) or steps < 1:
            raise ValueError(f"steps: expected an int >= 1, got {steps!r}")
        n = int(steps)

        def frac(f: float, least: int = 0) -> int:
            return max(least, math.floor(f * n + 0.5))

        start = self.start if self.start is not None else frac(self.start_frac)
        every = self.every if self.every is not None else frac(self.every_frac, self.min_every)
        reset_every = self.reset_every if self.reset_every is not None else frac(self.reset_frac, 1)
        stop = self.stop if self.stop is not None else min(frac(self.stop_frac), n - 1)
        last_grow = (min(stop, n) // every) * every
        if self.enabled and self.stop is not None and last_grow == n and last_grow > start:
            raise ValueError(
                f"densify.stop (--densify-stop): {self.stop} densifies on the last step of a {n}-step run "
                f"(every {every} steps), and nothing would train what it adds; expected at most {n - 1}"
            )
        explicit = [f"--densify-{k.replace('_', '-')} {getattr(self, k)}" for k in ("start", "stop", "every")
                    if getattr(self, k) is not None]  # fmt: skip
        if self.enabled and explicit and (start // every + 1) * every > min(stop, n):
            raise ValueError(
                f"densify ({', '.join(explicit)}): no step of a {n}-step run densifies (every {every} steps after "
                f"step {start}, up to step {min(stop, n)}); to train without densification pass --no-densify"
            )
        reset_until = max(0, min(stop, n - self.recover_steps))
        last_reset = (min(stop, n) // reset_every) * reset_every
        if self.enabled and 0 < last_reset and last_reset > reset_until and self.reset_every is not None:
            limit = f"at or before step {reset_until}" if reset_until else "none: the run is too short for one"
            raise ValueError(
                f"densify.reset_every (--densify-reset-every): {self.reset_every} puts an opacity reset at step "
                f"{last_reset} of a {n}-step run, {n - last_reset} steps before its end; the last reset must be "
                f"at least {self.recover_steps} steps before the end (densify.recover_steps), so {limit}"
            )
        return DensifySchedule(n, self.enabled, start, stop, every, reset_every, reset_until)


@dataclass(frozen=True)
class DensifySchedule:
    """The densification schedule of one run, in 1-based steps: grow at the multiples of
    ``every`` in (``start``, min(``stop``, ``steps``)], reset opacities at the multiples of
    ``reset_every`` up to ``reset_until`` (at most ``stop``). No growth falls on the last step and
    ``reset_until <= steps - recover_steps`` (``DensifyConfig.resolve`` refuses settings that
    would break either); an explicit ``stop`` may lie beyond the run."""

    steps: int
    enabled: bool
    start: int
    stop: int
    every: int
    reset_every: int
    reset_until: int

    def grows(self, step: int) -> bool:
        return self.enabled and self.start < step <= min(self.stop, self.steps) and step % self.every == 0

    def resets(self, step: int) -> bool:
        return self.enabled and 0 < step <= self.reset_until and step % self.reset_every == 0

    def grow_steps(self) -> list[int]:
        if not self.enabled:
            return []
        first = (self.start // self.every + 1) * self.every
        return list(range(first, min(self.stop, self.steps) + 1, self.every))

    def reset_steps(self) -> list[int]:
        return list(range(self.reset_every, self.reset_until + 1, self.reset_every)) if self.enabled else []

    def last_collect(self) -> int:
        """The last step whose screen-space gradients a densification still uses (0: none)."""
        g = self.grow_steps()
        return g[-1] if g else 0

    def as_dict(self) -> dict:
        """What run.json and the checkpoint record: the settings and the steps they give."""
        d = {f.name: getattr(self, f.name) for f in fields(self)}
        return d | {"grow_steps": self.grow_steps(), "reset_steps": self.reset_steps()}


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
        if means2d.grad is None:  # a renderer whose means2d lies off the loss's graph (9ca308a did)
            warnings.warn(
                "densification: the render's means2d has no gradient, so no Gaussian can grow; is the "
                "renderer's means2d the tensor its images were rasterised from?",
                RuntimeWarning,
                stacklevel=2,
            )
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
        room = max(0, min(c.max_gaussians - n, math.floor(c.max_growth * n)))
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
