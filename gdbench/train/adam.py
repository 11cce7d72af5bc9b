"""The trainer's Adam: torch.optim.Adam(fused=True)'s arithmetic and checkpoint format without
torch.optim.

torch.optim's optimizers wrap ``__init__``, ``state_dict`` and ``load_state_dict`` in a guard that
imports torch._dynamo on first use (seconds of every training process, for a compiler the trainer
never calls), and torch.optim's ``step`` spends far longer in Python and checks than its few
kernel calls take (docs/log/2026-11-26_cell_cost.md). This class calls the same fused kernel on the
same tensors (``torch._fused_adam_``, through ``core.private``), so its parameters and moments are torch's bit for bit,
and its ``state_dict`` is torch's format: checkpoints written by either load into the other
(tests/test_update.py checks both against ``torch.optim.Adam(fused=True)``).

One parameter per group (the trainer's six: means, quats, ...), each group named.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, fields
from typing import ClassVar

import torch
from torch import Tensor

from gdbench.core.constraints import check_fields, is_int
from gdbench.core.private import foreach_add_, fused_adam_


@dataclass(frozen=True)
class OptimConfig:
    """Adam learning rates per parameter group (docs/training.md, "Settings against the
    references": the references' values and the reasons for ours)."""

    OPTIONS: ClassVar[tuple[str, ...]] = ()
    """None of its fields is a command-line option (a config file sets them: optim.means)."""

    means: float = 1e-3
    """Initial learning rate of the means, per unit of the scene extent over 0.5 (the rate is
    multiplied by extent / 0.5: 1 at the paper's initial ball); decays exponentially to
    ``means_final`` over ``means_decay_steps`` steps or the run, whichever is longer."""
    means_final: float = 2e-5
    """Learning rate of the means at the end of its decay (same units as ``means``)."""
    means_decay_steps: int = 2000
    """The means' rate decays over at least this many steps (3DGS: a fixed 30k): a shorter run
    stops partway down the paper's 2000-step decay instead of squeezing it, which froze the
    geometry early (400 / 800 steps: +1.7 / +2.2 dB over 16 paired seeds; docs/training.md)."""
    colors: float = 0.01
    """Base colour (SH band 0); DreamGaussian's."""
    sh_rest: float = 0.0005
    """Higher SH bands (degree >= 1): a twentieth of ``colors``, 3DGS's rule. At the base colour's
    rate the bands absorb each view's noise (--sh-degree 3: a pale duck speckled with colours)."""
    opacities: float = 0.05
    """Opacity logits (3DGS, gsplat and DreamGaussian: 0.05)."""
    scales: float = 0.005
    """Log-scales (3DGS, gsplat and DreamGaussian: 0.005)."""
    quats: float = 0.005
    """Rotations (DreamGaussian's; 3DGS and gsplat: 0.001)."""

    def __post_init__(self) -> None:
        check_fields(self, "optim.")  # every field against its declared type and range
        if not (is_int(self.means_decay_steps) and self.means_decay_steps >= 1):
            raise ValueError(f"optim.means_decay_steps: expected an int >= 1, got {self.means_decay_steps!r}")
        for f in fields(self):
            if f.name == "means_decay_steps":
                continue
            v = getattr(self, f.name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"optim.{f.name}: expected a finite learning rate >= 0, got {v!r}")
        if self.means_final <= 0 or self.means <= 0:
            raise ValueError(
                f"optim.means, optim.means_final: expected positive rates, got {self.means}, {self.means_final}"
            )


OPTIONS = {
    "betas": (0.9, 0.999),
    "eps": 1e-8,
    "weight_decay": 0.0,
    "amsgrad": False,
    "maximize": False,
    "foreach": None,
    "capturable": False,
    "differentiable": False,
    "fused": True,
    "decoupled_weight_decay": False,
}
"""torch.optim.Adam's group options and their defaults (those a torch checkpoint holds)."""


class Adam:
    """Adam over named one-parameter groups, with torch.optim.Adam(fused=True)'s bits."""

    def __init__(self, groups: list[dict], *, eps: float = 1e-8, betas: tuple[float, float] = (0.9, 0.999)):
        self.param_groups: list[dict] = []
        for g in groups:
            if len(g["params"]) != 1:
                n = len(g["params"])
                raise ValueError(f"groups: expected one parameter per group, got {n} in {g.get('name')!r}")
            self.param_groups.append(OPTIONS | {"eps": eps, "betas": betas} | g | {"params": list(g["params"])})
        self.state: collections.defaultdict[Tensor, dict] = collections.defaultdict(dict)

    def step(self) -> None:
        """One Adam step of every group whose parameter has a gradient (state made on its first)."""
        todo = []
        for g in self.param_groups:
            p = g["params"][0]
            if p.grad is None:
                continue
            st = self.state[p]
            if not st:  # torch's _init_group for fused: a float32 step on the parameter's device
                st["step"] = torch.zeros((), dtype=torch.float32, device=p.device)
                st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
            todo.append((g, p, st))
        if not todo:
            return
        foreach_add_([st["step"] for _, _, st in todo], 1)
        with torch.no_grad():
            for g, p, st in todo:
                b1, b2 = g["betas"]
                fused_adam_([p], [p.grad], [st["exp_avg"]], [st["exp_avg_sq"]], [], [st["step"]],
                            amsgrad=False, lr=g["lr"], beta1=b1, beta2=b2, weight_decay=g["weight_decay"],
                            eps=g["eps"], maximize=False, grad_scale=None, found_inf=None)  # fmt: skip

    def state_dict(self) -> dict:
        """torch.optim's format: state by parameter index, groups with indices for parameters."""
        index = {id(g["params"][0]): i for i, g in enumerate(self.param_groups)}
        groups = [{k: v for k, v in g.items() if k != "params"} | {"params": [i]}
                  for i, g in enumerate(self.param_groups)]  # fmt: skip
        state = {index[id(p)]: dict(st) for p, st in self.state.items() if id(p) in index and st}
        return {"state": state, "param_groups": groups}

    def load_state_dict(self, blob: dict) -> None:
        """A state dict of this class or of torch.optim.Adam over the same groups (as torch's
        ``load_state_dict``: moments cast to their parameter's dtype and device, steps float32).
        Options this class does not compute (amsgrad, maximize, decoupled weight decay,
        capturable, differentiable, a tensor learning rate) are refused, naming the option: the
        run would go on with other arithmetic than it started with. Checkpoints from before the
        trainer's Adam was fused (``fused`` None) go on fused: equal to about 1e-7."""
        saved = blob["param_groups"]
        if len(saved) != len(self.param_groups) or any(len(s["params"]) != 1 for s in saved):
            raise ValueError(
                f"optimizer: expected {len(self.param_groups)} groups of one parameter, got "
                f"{[len(s['params']) for s in saved]}"
            )
        state: collections.defaultdict[Tensor, dict] = collections.defaultdict(dict)
        for g, s in zip(self.param_groups, saved):
            for key in ("amsgrad", "maximize", "decoupled_weight_decay", "capturable", "differentiable"):
                if s.get(key):
                    raise ValueError(f"optimizer[{g.get('name')!r}].{key}: this trainer's Adam does not compute it")
            if isinstance(s.get("lr"), Tensor):
                raise ValueError(f"optimizer[{g.get('name')!r}].lr: expected a number, got a tensor")
            p = g["params"][0]
            st = blob["state"].get(s["params"][0])
            if st:
                unknown = sorted(set(st) - {"step", "exp_avg", "exp_avg_sq"})
                if unknown:
                    raise ValueError(f"optimizer[{g.get('name')!r}]: unexpected state {unknown}")
                state[p] = {
                    k: (torch.as_tensor(float(v)) if k == "step" and not isinstance(v, Tensor) else v).to(
                        dtype=torch.float32 if k == "step" else p.dtype, device=p.device
                    )
                    for k, v in st.items()
                }
            g.update({k: v for k, v in s.items() if k not in ("params", "fused", "foreach")})
        self.state = state
