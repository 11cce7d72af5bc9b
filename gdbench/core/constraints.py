"""Declared constraints on config and command-line fields, checked in one pass before any work.

A field states its range in its type, ``steps: Annotated[int, AtLeast(1)] = 2000``; tyro ignores
the annotation and ``check_fields`` reads it. Besides the declared ranges, every float must be
finite (``--camera-radius inf`` is refused, not trained), tuples are checked element by element,
and nested dataclasses (``noise``, ``optim``, ``densify``) are walked. An error names the field
and the command-line flag a user typed: ``camera_radius (--camera-radius): expected a finite
number > 0, got inf``. Rules that tie two fields together (``sigma_min < sigma_max``) stay in the
dataclasses' ``__post_init__``, after their fields' own checks.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import typing
from dataclasses import dataclass


@dataclass(frozen=True)
class Range:
    """``lo <= v <= hi`` (an end left None is open-ended; ``lo_open``/``hi_open`` exclude it)."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    unit: str = ""

    def holds(self, v: float) -> bool:
        if self.lo is not None and (v <= self.lo if self.lo_open else v < self.lo):
            return False
        return not (self.hi is not None and (v >= self.hi if self.hi_open else v > self.hi))

    def describe(self, integer: bool) -> str:
        what = "an int" if integer else "a finite number"
        unit = f" {self.unit}" if self.unit else ""
        lo, hi = _number(self.lo), _number(self.hi)
        if self.lo is not None and self.hi is not None:
            left, right = "(" if self.lo_open else "[", ")" if self.hi_open else "]"
            return f"{what} in {left}{lo}, {hi}{right}{unit}"
        if self.lo is not None:
            return f"{what} {'>' if self.lo_open else '>='} {lo}{unit}"
        if self.hi is not None:
            return f"{what} {'<' if self.hi_open else '<='} {hi}{unit}"
        return what + unit


def is_int(v) -> bool:
    """An int that is not a bool (``True`` is an int to Python, not a step count)."""
    return isinstance(v, int) and not isinstance(v, bool)


def _number(x) -> str:
    return str(x) if isinstance(x, int) else f"{x:g}" if x is not None else ""


def AtLeast(lo: float, unit: str = "") -> Range:
    return Range(lo=lo, unit=unit)


def Positive(unit: str = "") -> Range:
    return Range(lo=0, lo_open=True, unit=unit)


def Between(lo: float, hi: float, *, open: bool = False, unit: str = "") -> Range:
    """``[lo, hi]``, or ``(lo, hi)`` with ``open``."""
    return Range(lo=lo, hi=hi, lo_open=open, hi_open=open, unit=unit)


def Seed() -> Range:
    """A random seed: what torch.Generator.manual_seed takes on every platform, [0, 2^63 - 1]."""
    return Range(lo=0, hi=2**63 - 1)


def flag(key: str) -> str:
    """The command-line option of a field key ('noise.ou_beta' -> '--noise-ou-beta', 'vgs.enabled'
    -> '--vgs', 'prior.sd_model' -> '--sd-model')."""
    key = key.removeprefix("prior.")  # the prior's settings are flags of their own (--sd-model)
    if key == "noise.ratio_mode":
        return "--noise-ratio"
    key = key.removesuffix(".enabled")  # a group switched on and off by its name (--vgs, --densify)
    return "--" + key.replace(".", "-").replace("_", "-")


@functools.cache
def _choices(cls) -> dict[str, tuple]:
    """field name -> the values of its ``Literal`` type (``X | None`` allows None too)."""
    hints = typing.get_type_hints(cls)
    out = {}
    for name, ann in hints.items():
        if typing.get_origin(ann) is tuple:  # tuple[Literal[...], ...]: each element
            ann = typing.get_args(ann)[0]
        args = typing.get_args(ann) if typing.get_origin(ann) is not typing.Literal else (ann,)
        lits = [a for a in (args or (ann,)) if typing.get_origin(a) is typing.Literal]
        if lits:
            out[name] = tuple(v for lit in lits for v in typing.get_args(lit)) + ((None,) if type(None) in args else ())
    return out


@functools.cache
def _declared(cls) -> dict[str, tuple[type | None, Range | None]]:
    """field name -> (its plain numeric type or None, its declared Range or None)."""
    hints = typing.get_type_hints(cls, include_extras=True)
    out = {}
    for f in dataclasses.fields(cls):
        ann, rng = hints[f.name], None
        if typing.get_origin(ann) is typing.Annotated:
            rng = next((m for m in typing.get_args(ann)[1:] if isinstance(m, Range)), None)
            ann = typing.get_args(ann)[0]
        if typing.get_origin(ann) is not tuple:  # X | None -> X
            args = [a for a in typing.get_args(ann) if a is not type(None)] or [ann]
            ann = args[0] if len(args) == 1 else None
        if typing.get_origin(ann) is tuple:  # tuple[float, float]: checked element by element
            ann = typing.get_args(ann)[0]
        base = ann
        out[f.name] = (base if base in (int, float) else None, rng)
    return out


def check_fields(obj, prefix: str = "", *, nested: bool = True) -> None:
    """Check every field of dataclass ``obj`` (and of the dataclasses it holds) against its type
    and declared ``Range``; the first violation raises ValueError naming the field and its flag.
    ``nested=False``: the dataclasses it holds are option groups whose fields are flags of their
    own (a command's ``train`` and ``method`` options), not ``group.field``."""
    for name, (base, rng) in _declared(type(obj)).items():
        value = getattr(obj, name)
        key = prefix + name
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            check_fields(value, key + "." if nested else prefix, nested=nested)
            continue
        choices = _choices(type(obj)).get(name)
        bad = [v for v in (value if isinstance(value, tuple) else (value,)) if choices is not None and v not in choices]
        if bad:
            value = bad[0]
            raise ValueError(
                f"{key} ({flag(key)}): expected one of {[c for c in choices if c is not None]}, got {value!r}"
            )
        if value is None or base is None:
            continue
        for v in value if isinstance(value, (tuple, list)) else (value,):
            _check_value(key, v, base, rng)


INT64 = Range(lo=-(2**63), hi=2**63 - 1)
"""Every int must fit the int64 torch and numpy hold it in."""


def _check_value(key: str, v, base: type, rng: Range | None) -> None:
    integer = base is int
    want = (rng or (INT64 if integer else Range())).describe(integer)
    bad = isinstance(v, bool) or not isinstance(v, (int, float))
    bad = bad or (integer and not (isinstance(v, int) and INT64.holds(v))) or not _finite(v)
    if bad or (rng is not None and not rng.holds(v)):
        raise ValueError(f"{key} ({flag(key)}): expected {want}, got {v!r}")


def _finite(v) -> bool:
    try:
        return math.isfinite(v)
    except OverflowError:  # an int too large for a float
        return False
