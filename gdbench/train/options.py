"""Command-line options derived from the configs, shared by ``gdbench generate`` and ``gdbench
sweep``: every option left unset keeps the preset's value.

``train_options(exclude, prior)`` builds a dataclass with one optional field per ``TrainConfig``
field (its type, and its docstring as the help text), per field a nested group offers
(``OPTIONS`` of its config: --noise-redraw, --vgs-gamma, --views-per-step) and per setting of
the chosen prior's config, so a new config field is an option without touching the CLI.
"""

from __future__ import annotations

import ast
import functools
import inspect
import itertools
import typing
from dataclasses import field, fields, make_dataclass
from typing import Annotated, Literal, Optional

from gdbench.core.constraints import flag, inactive
from gdbench.train.config import NESTED, PRESETS, TrainConfig, key_of


@functools.cache
def _module_tree(path: str) -> ast.Module:
    """A source file parsed once (``inspect.getsource`` parses a class's whole file on every call,
    once for each class whose field docs are the command line's help)."""
    with open(path, encoding="utf-8") as f:
        return ast.parse(f.read(), path)


def _class_node(cls) -> ast.ClassDef:
    """The definition of ``cls`` in its source file, found by its qualified name."""
    path = inspect.getsourcefile(cls)
    if path is None:
        raise OSError(f"no source file for {cls!r}")
    node: ast.AST = _module_tree(path)
    for name in cls.__qualname__.split("."):
        node = next(n for n in getattr(node, "body", []) if isinstance(n, ast.ClassDef) and n.name == name)
    return node


@functools.cache
def _field_docs(cls) -> dict[str, str]:
    """Docstrings written under the fields of a dataclass, by field name."""
    body = _class_node(cls).body
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


PRIOR_HELP = (
    "The prior score distillation queries: empirical (the embedded CPU prior, the exact posterior "
    "over image banks of procedural assets), learned (a small diffusion model trained on the same "
    "assets) or sd (Stable Diffusion). Each has options of its own: `--prior learned --help` lists them."
)


@functools.cache
def train_options(exclude: tuple[str, ...] = (), prior: str = "empirical"):
    """A dataclass ``TrainOptions`` of optional overrides: one per field of ``TrainConfig`` (minus
    ``exclude``), per field a nested group offers (its config's ``OPTIONS``, named by ``flag``),
    --prior, and one per setting of the ``prior`` kind's config (the options of the other priors
    are not there to type). ``.overrides()`` gives the set ones as ``apply_overrides`` takes them
    (a group's by their dotted key, a prior's by their names); ``.options()`` by option name."""
    import tyro

    from gdbench.priors.factory import PRIOR_CONFIGS

    base = TrainConfig()
    specs = []
    keys: dict[str, str] = {}

    def option(name: str, hint, helptext: str, note: str, key: str | None = None) -> None:
        # DisallowNone: unset is the preset's value, so None is no value to type ("--steps INT", and
        # booleans as --anneal/--no-anneal like the command's own flags)
        typ = Annotated[
            Optional[hint],  # noqa: UP045
            tyro.conf.DisallowNone,
            tyro.conf.arg(help=helptext, help_behavior_hint=note),
        ]
        specs.append((name, typ, field(default=None)))
        keys[name] = key or name

    def group(cls, values, prefix: str = "") -> None:
        hints, docs = typing.get_type_hints(cls), _field_docs(cls)
        names = [f.name for f in fields(cls)] if not prefix else list(cls.OPTIONS)
        for name in names:
            key = prefix + name
            default = getattr(values, name)
            differs = sorted(p for p, c in PRESETS.items() if prefix and _get(c, key) != _get(base, key))
            doc = docs.get(name, name.replace("_", " "))
            said = "(default" in doc or "unset" in doc
            note = (
                "" if said else f"(default: {default!r}" + (f"; the presets {differs} differ" if differs else "") + ")"
            )
            option(flag(key, TrainConfig)[2:].replace("-", "_") if prefix else name, hints[name], doc, note, key)

    hints, docs = typing.get_type_hints(TrainConfig), _field_docs(TrainConfig)
    for f in fields(TrainConfig):
        if f.name in exclude:
            continue
        if f.name == "prior":
            option("prior", Literal[tuple(PRIOR_CONFIGS)], PRIOR_HELP, "(default: empirical)")
            group(PRIOR_CONFIGS[prior], PRIOR_CONFIGS[prior]())
        elif f.name in NESTED:
            group(NESTED[f.name], getattr(base, f.name), prefix=f.name + ".")
        else:
            default = getattr(base, f.name)
            differs = sorted(p for p, c in PRESETS.items() if getattr(c, f.name) != default)
            note = f"(default: {default!r}" + (f"; the presets {differs} differ" if differs else "") + ")"
            option(f.name, hints[f.name], docs.get(f.name, f.name.replace("_", " ")), note)

    def overrides(self) -> dict[str, object]:
        return {keys[f.name]: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    def options(self) -> dict[str, object]:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    namespace = {"overrides": overrides, "options": options, "prior_kind": prior}
    return make_dataclass("TrainOptions", specs, namespace=namespace)


def _get(cfg, key: str):
    """The value of a dotted key ('vgs.gamma') of a config."""
    for part in key.split("."):
        cfg = getattr(cfg, part)
    return cfg


def inert_options(cfg, given) -> list[str]:
    """One line per option in ``given`` (setting names as ``config.key_of`` reads them) that does
    nothing in ``cfg``, naming what it needs (the ``When`` markers beside the fields and the groups'
    switches, read by ``core.constraints.inactive``); empty when every given option acts."""
    return inactive(cfg, [key_of(k) for k in given if k not in NESTED])  # a group, or its switch: always acts
