"""Tolerances of the conformance cases: per case and class, what a renderer may differ from the
float64 twin (conformance.py says how each is measured; docs/references.md, "Bring your own
renderer")."""

from __future__ import annotations

import math
from dataclasses import dataclass

CLASSES = ("exact", "approximate")
"""An exact float32 rasterizer of gdbench's image model; another image model of the same scene."""


@dataclass(frozen=True)
class Tolerance:
    """What a case allows a renderer of one class: image errors (absolute, rgb and alpha in [0, 1])
    and the gradient's directional derivatives (relative, with a floor; see the module's text)."""

    mean_abs: float
    max_abs: float
    grad_rel: float = math.nan
    grad_floor: float = math.nan
    grad_atol: float = math.nan
    gradients: str = ""
    """Why gradients are not judged in this class on this case ("" where they are)."""

    @classmethod
    def parse(cls, value, where: str) -> Tolerance | str:
        """A tolerance from its JSON form, or a reason string (the class does not apply); anything
        else, or a missing or non-positive field, is a ValueError naming ``where``."""
        if isinstance(value, str) and value:
            return value
        grads = ("grad_rel", "grad_floor", "grad_atol")
        fields = ("mean_abs", "max_abs", *grads)
        if not isinstance(value, dict) or set(value) - {*fields, "gradients", "note"}:
            raise ValueError(f"{where}: expected {{{', '.join(fields)}}} or a reason string, got {value!r}")
        skip = value.get("gradients", "")
        need = fields[:2] if skip else fields  # gradients: "reason" stands for the three grad fields
        missing = [f for f in need if f not in value]
        bad = [f for f in need if f in value and not (isinstance(value[f], (int, float)) and value[f] > 0)]
        if missing or bad or not isinstance(skip, str):
            raise ValueError(
                f"{where}: missing {missing} / not a positive number {bad} (every field is required, or "
                f"'gradients': a reason in place of {list(grads)})"
            )
        return cls(**{f: float(value[f]) for f in need}, gradients=skip)


def parse_tolerances(value, where: str) -> dict[str, Tolerance | str]:
    """A case's ``tolerances`` block: every class present (a tolerance or a reason); a missing
    block or class is an error at load, not a silent pass."""
    if not isinstance(value, dict):
        raise ValueError(f"{where}: no 'tolerances' block (one entry per class: {list(CLASSES)})")
    missing = [c for c in CLASSES if c not in value]
    unknown = [c for c in value if c not in CLASSES]
    if missing or unknown:
        raise ValueError(f"{where}: tolerance classes missing {missing}, unknown {unknown}; expected {list(CLASSES)}")
    return {c: Tolerance.parse(value[c], f"{where}.{c}") for c in CLASSES}
