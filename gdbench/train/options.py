"""Command-line options derived from the configs, shared by ``gdbench generate`` and ``gdbench
sweep``: every option left unset keeps the preset's value.

``train_options(exclude)`` builds a dataclass with one optional field per ``TrainConfig`` field
(its type, and its docstring as the help text), so a new config field is an option without
touching the CLI. ``MethodOptions`` adds the fields of the nested groups a user tunes: the
structured noise's schedule and the densification schedule.
"""

from __future__ import annotations

import ast
import functools
import inspect
import itertools
import typing
from dataclasses import dataclass, field, fields, make_dataclass
from typing import Annotated, Literal, Optional

from .config import PRESETS, TrainConfig

NESTED = ("noise", "optim", "densify")


@functools.cache
def _field_docs(cls) -> dict[str, str]:
    """Docstrings written under the fields of a dataclass, by field name."""
    body = ast.parse(inspect.getsource(cls)).body[0].body
    docs = {}
    for a, b in itertools.pairwise(body):
        if (
            isinstance(a, ast.AnnAssign)
            and isinstance(b, ast.Expr)
            and isinstance(getattr(b, "value", None), ast.Constant)
        ):
            if isinstance(b.value.value, str):
                docs[a.target.id] = " ".join(b.value.value.split())
    return docs


@functools.cache
def train_options(exclude: tuple[str, ...] = ()):
    """A dataclass ``TrainOptions`` of optional overrides, one per field of ``TrainConfig`` (minus
    ``exclude`` and the nested groups), with ``.overrides()`` giving the set ones as a dict."""
    import tyro

    hints = typing.get_type_hints(TrainConfig)
    docs = _field_docs(TrainConfig)
    base = TrainConfig()
    specs = []
    for f in fields(TrainConfig):
        if f.name in exclude or f.name in NESTED:
            continue
        default = getattr(base, f.name)
        differs = sorted(p for p, c in PRESETS.items() if getattr(c, f.name) != default)
        note = f" (default {default!r}" + (f"; the presets {differs} differ" if differs else "") + ")"
        helptext = docs.get(f.name, f.name.replace("_", " ")) + note
        typ = Annotated[Optional[hints[f.name]], tyro.conf.arg(help=helptext)]  # noqa: UP045
        specs.append((f.name, typ, field(default=None)))

    def overrides(self) -> dict[str, object]:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    return make_dataclass("TrainOptions", specs, namespace={"overrides": overrides})


@dataclass
class MethodOptions:
    """Overrides of the preset's nested settings (unset: the preset's own)."""

    noise_redraw: Literal["run", "ou", "step"] | None = None
    """When the noise cloud's colours are redrawn: 'run' keeps one draw for the whole run (the
    paper: every view sees one fixed 3D source; the default), 'ou' drifts them slowly
    (Ornstein-Uhlenbeck, --noise-ou-beta), 'step' redraws every step (an ablation: no two steps
    share a source)."""
    noise_ou_beta: float | None = None
    """b of the Ornstein-Uhlenbeck drift c_t = sqrt(1 - b) c_{t-1} + sqrt(b) eps."""
    noise_ratio: Literal["amplitude", "variance"] | None = None
    """How the paper's 'proportion of structured noise' (0.3 -> 0.05) mixes: 'variance' (the
    default: n = sqrt(r) n_s + sqrt(1 - r) n_iid) or 'amplitude' (n = r n_s + sqrt(1 - r^2) n_iid)."""
    densify_start: int | None = None
    """First step that densifies (default 300: the paper's)."""
    densify_stop: int | None = None
    """Last step that densifies (default 1500)."""
    densify_every: int | None = None
    """Densify every this many steps (default 50: the paper's)."""
    densify_reset_every: int | None = None
    """Opacity reset interval (default 400: the paper's); scale the schedule with --steps."""

    def overrides(self) -> dict[str, object]:
        """The set options as TrainConfig overrides (dotted keys for the nested groups)."""
        key = {"noise_redraw": "noise.redraw", "noise_ou_beta": "noise.ou_beta", "noise_ratio": "noise.ratio_mode"}
        key |= {f"densify_{k}": f"densify.{k}" for k in ("start", "stop", "every", "reset_every")}
        return {key[f.name]: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}
