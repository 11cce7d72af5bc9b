"""Declared constraints on config and command-line fields, checked in one pass before any work.

A field states its range in its type, ``steps: Annotated[int, AtLeast(1)] = 2000``; tyro ignores
the annotation and ``check_fields`` reads it. Besides the declared ranges, every float must be
finite (``--camera-radius inf`` is refused, not trained), tuples are checked element by element,
and each config checks its own fields when it is made (a group, ``noise`` or ``densify``, before
the config that holds it: so once). An error names the field
and the command-line flag a user typed: ``camera_radius (--camera-radius): expected a finite
number > 0, got inf``. Rules that tie two fields together (``sigma_min < sigma_max``) stay in the
dataclasses' ``__post_init__``, after their fields' own checks.

A field that acts only under another setting says so in its type too, ``sigma_min:
Annotated[float, Positive(), When("guidance", "sjc")]``; a group switched by an ``enabled`` field
(``vgs.enabled``) makes every other field of the group act only when it is on. ``inactive`` walks
those rules for the options a user set and writes each message through ``flag``: "--vgs-gamma acts
only with --vgs (this run: --no-vgs)". A field's command-line name is derived from its key
(``flag``) unless the field declares its own (``Flag``), as the structured noise's switch does.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import types
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


@dataclass(frozen=True)
class Flag:
    """The command-line name of a field, where the one ``flag`` derives would mislead: the
    structured noise's switch ``noise.enabled`` is --structured-noise (--no-noise would read as no
    noise at all, while the ablation keeps its iid noise)."""

    name: str


class When:
    """A field acts only when another setting of its config holds: ``When("guidance", "sjc")`` (one
    of these values), ``When("log_dir", not_=(None,))`` (anything but these), ``When("per_step",
    above=1)``; ``When.any(a, b)`` holds when one of ``a``, ``b`` does. ``key`` names a field of the
    same config, dotted to reach into its groups ('prior.sd_mode'); a setting the config lacks (another
    prior's) reads None. Several markers on one field must all hold."""

    def __init__(self, key: str = "", *values, not_: tuple = (), above: float | None = None, any_of: tuple = ()):
        self.key, self.values, self.not_, self.above, self.any_of = key, values, tuple(not_), above, tuple(any_of)

    @classmethod
    def any(cls, *alternatives: When) -> When:
        return cls(any_of=alternatives)

    def __repr__(self) -> str:
        return f"When({self.key!r}, {self.values}, not_={self.not_}, above={self.above}, any_of={self.any_of})"

    def holds(self, config) -> bool:
        if self.any_of:
            return any(w.holds(config) for w in self.any_of)
        v = _lookup(config, self.key)
        if self.values and v not in self.values:
            return False
        if self.not_ and v in self.not_:
            return False
        return self.above is None or (v is not None and v > self.above)

    def needs(self, config, root: type, prefix: str) -> str:
        """What the field needs, in command-line words: '--guidance sjc', '--vgs', '--views-per-step
        2 or more', '--log-dir'; of alternatives, those ``config`` has (not another prior's)."""
        if self.any_of:
            missing = object()
            here = [w for w in self.any_of if w.any_of or _lookup(config, w.key, missing) is not missing]
            return " or ".join(w.needs(config, root, prefix) for w in here or self.any_of)
        f = flag(prefix + self.key, root)
        if self.values:
            return " or ".join(_setting(f, v) for v in self.values)
        if self.not_ == (None,):
            return f
        if self.not_:
            return f"{f} other than {' and '.join(str(v) for v in self.not_)}"
        return f"{f} {self.above + 1} or more" if is_int(self.above) else f"{f} above {_number(self.above)}"

    def now(self, config, root: type, prefix: str) -> list[str]:
        """The settings this rule reads, as this run has them ('--guidance sds')."""
        if self.any_of:
            return [s for w in self.any_of for s in w.now(config, root, prefix)]
        missing = object()
        v = _lookup(config, self.key, missing)
        if v is missing:
            return []  # another prior's setting: nothing to say
        return [_setting(flag(prefix + self.key, root), v)]


def _setting(option: str, v) -> str:
    """An option as a user types it: '--vgs', '--no-vgs', '--guidance sjc', 'no --log-dir'."""
    if v is True:
        return option
    if v is False:
        return "--no-" + option[2:]
    if v is None:
        return "no " + option
    return f"{option} {v}"


def _lookup(config, key: str, default=None):
    for part in key.split("."):
        config = getattr(config, part, default)
        if config is default:
            return default
    return config


def _group_switch(group) -> When | None:
    """A group with an ``enabled`` field: its other fields act only when it is on."""
    return When("enabled", True) if "enabled" in {f.name for f in dataclasses.fields(group)} else None


def inactive(config, keys) -> list[str]:
    """One line per dotted key in ``keys`` (settings a user gave) that does nothing in ``config``:
    "--vgs-gamma acts only with --vgs (this run: --no-vgs)"; empty when every one acts. The rules are
    the ``When`` markers on the fields and the groups' ``enabled`` switches: a switch that is off is
    named alone, else every unmet rule of the field."""
    root = type(config)
    lines = []
    for key in keys:
        parts = key.split(".")
        holder, prefix, switches = config, "", []
        for part in parts[:-1]:  # the groups on the way: their switches first
            holder, prefix = getattr(holder, part, None), prefix + part + "."
            if not dataclasses.is_dataclass(holder):
                break
            switch = _group_switch(holder) if parts[-1] != "enabled" else None
            switches += [(switch, holder, prefix)] if switch is not None else []
        else:
            unmet = [(w, h, p) for w, h, p in switches if not w.holds(h)][:1]  # a switch off says it all
            if not unmet:  # else every rule of the field's own that is not met
                unmet = [(w, holder, prefix) for w in _markers(type(holder), parts[-1], When) if not w.holds(holder)]
            if unmet:
                needs = " and ".join(w.needs(h, root, p) for w, h, p in unmet)
                now = ", ".join(s for w, h, p in unmet for s in w.now(h, root, p))
                lines.append(f"{flag(key, root)} acts only with {needs}" + (f" (this run: {now})" if now else ""))
    return lines


def _markers(cls, name: str, kind: type) -> list:
    """The ``kind`` markers (``When``, ``Flag``) in the annotation of field ``name`` of ``cls``."""
    ann = _hints(cls).get(name)
    if typing.get_origin(ann) is not typing.Annotated:
        return []
    return [m for m in typing.get_args(ann)[1:] if isinstance(m, kind)]


@functools.cache
def _hints(cls) -> dict:
    return typing.get_type_hints(cls, include_extras=True) if dataclasses.is_dataclass(cls) else {}


def _field_class(root: type, key: str) -> tuple[list[type], str]:
    """The classes that may hold the last field of ``key`` under ``root`` (a union's members each),
    and the field's name."""
    holders, parts = [root], key.split(".")
    for part in parts[:-1]:
        nxt = []
        for cls in holders:
            ann = _hints(cls).get(part)
            ann = typing.get_args(ann)[0] if typing.get_origin(ann) is typing.Annotated else ann
            members = typing.get_args(ann) if typing.get_origin(ann) in (typing.Union, types.UnionType) else (ann,)
            nxt += [m for m in members if dataclasses.is_dataclass(m)]
        holders = nxt
    return holders, parts[-1]


def flag(key: str, root: type | None = None) -> str:
    """The command-line option of a field key ('noise.ou_beta' -> '--noise-ou-beta', 'vgs.enabled'
    -> '--vgs'): derived from the key, unless the field declares its own (``Flag``), or its group is
    one whose settings are options of their own (``root.OWN_OPTIONS``: TrainConfig's prior, so
    'prior.sd_model' -> '--sd-model'); both looked up from ``root``, the config class the key
    starts at."""
    if root is not None:
        holders, name = _field_class(root, key)
        named = next((m for cls in holders for m in _markers(cls, name, Flag)), None)
        if named is not None:
            return "--" + named.name
        group, dot, rest = key.partition(".")
        if dot and group in getattr(root, "OWN_OPTIONS", ()):
            key = rest
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


def check_fields(obj, prefix: str = "", *, nested: bool = True, options: str | None = None) -> None:
    """Check every field of dataclass ``obj`` against its type and declared ``Range``; the first
    violation raises ValueError naming the field and its flag. A config's groups (``noise``,
    ``densify``: dataclasses it holds) check themselves when they are made, so they are not walked
    again. ``nested=False``: the dataclasses it holds are option groups
    whose fields are flags of their own (a command's ``train`` and ``method`` options), walked here.
    ``options``: the prefix of the fields' options where it is not ``prefix`` (a prior's settings
    are named 'prior.sd_model' and typed --sd-model: ``options=""``)."""
    for name, (base, rng) in _declared(type(obj)).items():
        value = getattr(obj, name)
        key = prefix + name
        if dataclasses.is_dataclass(value) and not isinstance(value, type):
            if not nested:
                check_fields(value, prefix, nested=nested)
            continue
        option = next((f"--{m.name}" for m in _markers(type(obj), name, Flag)), None)
        option = option or flag((prefix if options is None else options) + name)
        choices = _choices(type(obj)).get(name)
        bad = [v for v in (value if isinstance(value, tuple) else (value,)) if choices is not None and v not in choices]
        if bad:
            value = bad[0]
            raise ValueError(
                f"{key} ({option}): expected one of {[c for c in choices if c is not None]}, got {value!r}"
            )
        if value is None or base is None:
            continue
        for v in value if isinstance(value, (tuple, list)) else (value,):
            _check_value(key, option, v, base, rng)


INT64 = Range(lo=-(2**63), hi=2**63 - 1)
"""Every int must fit the int64 torch and numpy hold it in."""


def _check_value(key: str, option: str, v, base: type, rng: Range | None) -> None:
    integer = base is int
    want = (rng or (INT64 if integer else Range())).describe(integer)
    bad = isinstance(v, bool) or not isinstance(v, (int, float))
    bad = bad or (integer and not (isinstance(v, int) and INT64.holds(v))) or not _finite(v)
    if bad or (rng is not None and not rng.holds(v)):
        raise ValueError(f"{key} ({option}): expected {want}, got {v!r}")


def _finite(v) -> bool:
    try:
        return math.isfinite(v)
    except OverflowError:  # an int too large for a float
        return False
