"""Command-line options derived from the configs, shared by ``gdbench generate`` and ``gdbench
sweep``: every option left unset keeps the preset's value.

``train_options(exclude)`` builds a dataclass with one optional field per ``TrainConfig`` field
(its type, and its docstring as the help text), so a new config field is an option without
touching the CLI. ``method_options()`` adds the fields of the nested groups a user tunes: the
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

from gdbench.train.config import PRESETS, TrainConfig

NESTED = ("noise", "optim", "densify")


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
        note = f"(default: {default!r}" + (f"; the presets {differs} differ" if differs else "") + ")"
        helptext = docs.get(f.name, f.name.replace("_", " "))
        # DisallowNone: unset is the preset's value, so None is no value to type ("--steps INT", and
        # booleans as --anneal/--no-anneal like the command's own flags)
        typ = Annotated[
            Optional[hints[f.name]],  # noqa: UP045
            tyro.conf.DisallowNone,
            tyro.conf.arg(help=helptext, help_behavior_hint=note),
        ]
        specs.append((f.name, typ, field(default=None)))

    def overrides(self) -> dict[str, object]:
        return {f.name: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}

    return make_dataclass("TrainOptions", specs, namespace={"overrides": overrides})


@dataclass
class MethodSpec:
    """Overrides of the preset's nested settings (unset: the preset's own)."""

    noise_redraw: Literal["run", "ou", "step"] | None = None
    """When the noise cloud's colours are redrawn: 'run' keeps one draw for the whole run (the
    paper: every view sees one fixed 3D source; the default), 'ou' drifts them slowly
    (Ornstein-Uhlenbeck, --noise-ou-beta), 'step' redraws every step (an ablation: no two steps
    share a source)."""
    noise_ou_beta: float | None = None
    """b of the Ornstein-Uhlenbeck drift c_t = sqrt(1 - b) c_{t-1} + sqrt(b) eps (default 0.1); acts
    only with --noise-redraw ou."""
    noise_ratio: Literal["amplitude", "variance"] | None = None
    """How the paper's 'proportion of structured noise' (0.3 -> 0.05) mixes: 'variance' (the
    default: n = sqrt(r) n_s + sqrt(1 - r) n_iid) or 'amplitude' (n = r n_s + sqrt(1 - r^2) n_iid)."""
    densify_start: int | None = None
    """Densification starts after this step (default: 15% of --steps, rounded; the paper's 300 at
    2000). Set, it is an absolute step."""
    densify_stop: int | None = None
    """Last step that may densify (default: 75% of --steps; 1500 at 2000). Set, it is an absolute
    step, and must not densify on the run's last step."""
    densify_every: int | None = None
    """Densify every this many steps (default: 2.5% of --steps, at least 1; the paper's 50 at 2000).
    Set, it is an absolute step count."""
    densify_reset_every: int | None = None
    """Opacity reset interval, resets at its multiples up to --densify-stop (default: 20% of --steps; the
    paper's 400 at 2000). Set, it is an absolute step count; no reset may fall in the last 100 steps
    of the run, where opacities could not recover."""

    densify: bool | None = None
    """Densify at all (clone, split, prune, reset opacities; default: on). --no-densify trains the
    initial Gaussians as they are."""
    densify_grad_quantile: float | None = None
    """Grow the Gaussians above this quantile of the densification statistic (0.95: the top 5%)
    instead of above the fixed threshold 2e-4 (default: the threshold): growth then does not follow
    the score's scale, so paired presets keep comparable model sizes (docs/training.md)."""

    def overrides(self) -> dict[str, object]:
        """The set options as TrainConfig overrides (dotted keys for the nested groups)."""
        return _method_overrides(self)


METHOD_KEYS = {
    "noise_redraw": "noise.redraw",
    "noise_ou_beta": "noise.ou_beta",
    "noise_ratio": "noise.ratio_mode",
    **{f"densify_{k}": f"densify.{k}" for k in ("start", "stop", "every", "reset_every", "grad_quantile")},
    "densify": "densify.enabled",
}
"""``MethodSpec``'s option -> its TrainConfig override key (a nested group's dotted name)."""


def _method_overrides(self) -> dict[str, object]:
    return {METHOD_KEYS[f.name]: getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None}


@functools.cache
def method_options():
    """``MethodSpec`` for the command line: each option's help is its docstring as one paragraph
    (tyro keeps a docstring's line breaks), which already states the default."""
    import tyro

    hints = typing.get_type_hints(MethodSpec)
    docs = _field_docs(MethodSpec)
    specs = [
        (
            f.name,
            Annotated[hints[f.name], tyro.conf.DisallowNone, tyro.conf.arg(help=docs[f.name], help_behavior_hint="")],
            field(default=None),
        )
        for f in fields(MethodSpec)
    ]
    return make_dataclass(
        "MethodOptions", specs, namespace={"overrides": _method_overrides, "__doc__": MethodSpec.__doc__}
    )


def flag(key: str) -> str:
    """The command-line option of an override key ('noise.ou_beta' -> '--noise-ou-beta')."""
    from gdbench.core.constraints import flag as _flag

    return _flag(key)


def _acts(cfg) -> dict[str, tuple[bool, str]]:
    """For each option that acts only under another setting: (whether it acts in ``cfg``, what it
    needs, named by its option)."""
    sn = (cfg.structured_noise, "structured noise (--structured-noise; this run has it off)")
    sd = (cfg.prior == "sd", f"--prior sd (this run: --prior {cfg.prior})")
    sjc = (cfg.guidance == "sjc", f"--guidance sjc (this run: --guidance {cfg.guidance}, which anneals its timestep)")
    lp = (cfg.prior == "learned", f"--prior learned (this run: --prior {cfg.prior})")
    emp_lp = (cfg.prior in ("empirical", "learned"), f"--prior empirical or learned (this run: --prior {cfg.prior})")
    return {
        "noise.ou_beta": (
            cfg.structured_noise and cfg.noise.redraw == "ou",
            f"--noise-redraw ou (this run: --noise-redraw {cfg.noise.redraw})" if cfg.structured_noise else sn[1],
        ),
        "noise.redraw": sn,
        "noise.ratio_mode": sn,
        "log_every": (
            cfg.progress or cfg.log_dir is not None,
            "the progress report or --log-dir (this run: --no-progress, no --log-dir)",
        ),
        "view_window_deg": (
            cfg.view_prompting == "window" and cfg.prior == "empirical",
            f"--view-prompting window and --prior empirical (this run: --view-prompting {cfg.view_prompting}, "
            f"--prior {cfg.prior}; Stable Diffusion's view prompts are words, with no window)",
        ),
        "views_spread_deg": (
            cfg.views_per_step > 1,
            f"--views-per-step 2 or more (this run: --views-per-step {cfg.views_per_step})",
        ),
        "vgs_gamma": (cfg.vgs, "--vgs (this run has VGS off)"),
        "vgs_unit": (cfg.vgs, "--vgs (this run has VGS off)"),
        "sigma_min": sjc,
        "sigma_max": sjc,
        "anneal": sjc,
        "front_bias": (
            cfg.prior == "empirical" or (cfg.prior == "learned" and cfg.learned_model == "auto"),
            f"--prior empirical, or --prior learned with --learned-model auto (this run: --prior {cfg.prior}"
            + (f", --learned-model {cfg.learned_model})" if cfg.prior == "learned" else ")"),
        ),
        "variants": emp_lp,
        "learned_model": lp,
        "learned_guidance": lp,
        "sd_model": sd,
        "sd_mode": sd,
        "sd_guidance": sd,
        "sd_dtype": sd,
        "semantic_code": sd,
        "semantic_steps": (cfg.prior == "sd" and cfg.semantic_code, "--prior sd with --semantic-code"),
        "sd_controlnet": (
            cfg.prior == "sd" and cfg.depth_conditioning and cfg.sd_model != "tiny",
            "--prior sd with --depth-conditioning and a real --sd-model (the tiny model builds its own)",
        ),
        **{
            f"densify.{k}": (cfg.densify.enabled, "densification (this run: --no-densify)")
            for k in ("start", "stop", "every", "reset_every", "grad_quantile")
        },
        "init_ply": (cfg.init == "ply", f"--init ply (this run: --init {cfg.init})"),
        "init_color": (
            cfg.init == "sphere" or (cfg.prior == "sd" and cfg.sd_mode == "latent"),
            f"--init sphere (this run: --init {cfg.init}, whose points bring their colours)",
        ),
        "sh_degree": (
            not (cfg.prior == "sd" and cfg.sd_mode == "latent"),
            "an RGB render (this run: --sd-mode latent renders 4 latent features without SH)",
        ),
    }


def inert_options(cfg, given) -> list[str]:
    """One line per option in ``given`` (override keys the user set) that does nothing in ``cfg``,
    naming the option it needs; empty when every given option acts."""
    acts = _acts(cfg)
    return [f"{flag(k)} acts only with {acts[k][1]}" for k in given if k in acts and not acts[k][0]]
