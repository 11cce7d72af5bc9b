"""Your own method in a run: a noise source or a guidance of the user's, by name or by reference
(docs/training.md, "Your own method"), as renderers enter the comparisons.

- A **noise source** (``--noise-source REF``) replaces the structured noise field of each view:
  ``fn(request: NoiseRequest) -> Tensor [B, h, w, C]`` with unit variance per pixel. gdbench mixes
  it with iid noise by the run's ratio schedule (``--noise-ratio``, r_t from 0.3 to 0.05), as it
  mixes the noise cloud's field; the request carries the run's noise stream, so the run stays
  reproducible from its seed.
- A **guidance** (``--guidance REF``) turns the prior's denoised image into the gradient on the
  rendered image: ``fn(denoised, x, sigma, step, steps) -> Tensor`` shaped like ``x`` (SJC's is
  ``(denoised - x) / sigma``); sigma is drawn by SJC's schedule (``--sigma-min``, ``--sigma-max``,
  ``--anneal``), and ``--weight`` and the optimiser act on the result as on SJC's.

``REF`` is ``pkg.module:function``, ``path/to/file.py:function``, or a name given to
``register_method`` in the process that trains (a sweep's workers run in other processes: give
them references). The built-in names (noise: cloud, pose; guidance: sjc, sds) are not replaced.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

BUILTIN = {"noise": ("cloud", "pose"), "guidance": ("sjc", "sds")}
"""The methods gdbench has itself, by kind."""
REGISTERED: dict[str, dict[str, Callable]] = {"noise": {}, "guidance": {}}
"""Methods registered in this process, by kind and name."""
OPTION = {"noise": "noise.source (--noise-source)", "guidance": "guidance (--guidance)"}


@dataclass(frozen=True)
class NoiseRequest:
    """What a noise source is asked for at one step: the field's shape [B, h, w, C] (B views of the
    step, the prior's resolution and channels), the views' poses ([B] tensors, degrees), their
    cameras at the prior's resolution (``core.camera.Cameras``), the step, and the run's noise
    stream (draw from it: the run stays reproducible from its seed)."""

    shape: tuple[int, ...]
    step: int
    steps: int
    azimuth: torch.Tensor
    elevation: torch.Tensor
    fovy: torch.Tensor
    cameras: object
    generator: torch.Generator
    device: torch.device


def register_method(kind: str, name: str, fn: Callable) -> None:
    """Register ``fn`` as a ``kind`` ('noise' or 'guidance') method under ``name`` (not a built-in
    name, no ':'); registering a name again replaces it."""
    if kind not in BUILTIN:
        raise ValueError(f"kind: expected one of {list(BUILTIN)}, got {kind!r}")
    if not isinstance(name, str) or not name or ":" in name or name in BUILTIN[kind]:
        raise ValueError(f"name: expected a new name without ':', not a built-in {kind}'s, got {name!r}")
    if not callable(fn):
        raise ValueError(f"fn: expected a callable, got {type(fn).__name__}")
    REGISTERED[kind][name] = fn


def is_builtin(kind: str, value: str) -> bool:
    return value in BUILTIN[kind]


def resolve(kind: str, value: str) -> Callable:
    """The user's method ``value`` of ``kind`` (a registered name or a reference); one that cannot
    load, or is not callable, is a one-line ValueError naming the option."""
    if value in REGISTERED[kind]:
        return REGISTERED[kind][value]
    from gdbench.core.imports import import_ref

    if ":" not in value:
        known = list(BUILTIN[kind]) + sorted(REGISTERED[kind])
        raise ValueError(
            f"{OPTION[kind]}: expected one of {known} or a reference (pkg.mod:function, file.py:function), "
            f"got {value!r}"
        )
    fn = import_ref(value, OPTION[kind])
    if not callable(fn):
        raise ValueError(f"{OPTION[kind]} {value!r}: a {type(fn).__name__}, not a function")
    return fn


def check(kind: str, value: object) -> None:
    """A method setting's value is a built-in name or loads (``resolve``)."""
    if not isinstance(value, str):
        raise ValueError(f"{OPTION[kind]}: expected a name or a reference, got {value!r}")
    if not is_builtin(kind, value):
        resolve(kind, value)
