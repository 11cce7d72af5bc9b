"""Typed configuration of the reference trainer and its named presets.

Paper defaults (GaussianDiffusion, section 4): 2000 steps, 4096 initial points (grey,
opacity 0.1, in a sphere of radius 0.5), camera radius 1, fovy 40-70, azimuth [-180, 180],
elevation [-45, 45], white background, densify every 50 steps after step 300, opacity
reset every 400 steps. One departure, for the 2-core CPU: the training resolution is 64 px
(the paper renders 512 px for Stable Diffusion).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Annotated, ClassVar, Literal

from gdbench.core.constraints import AtLeast, Between, Positive, Seed, When, check_fields, flag
from gdbench.mechanisms.noise import NoiseConfig
from gdbench.mechanisms.variational import VGSConfig
from gdbench.priors import RunView
from gdbench.priors.factory import PRIOR_CONFIGS, EmpiricalPriorConfig, PriorConfig
from gdbench.train.adam import OptimConfig
from gdbench.train.densify import DensifyConfig
from gdbench.train.layout import LEGACY_PRIOR_DEFAULTS, RENAMED
from gdbench.train.views import ViewsConfig


@dataclass(frozen=True)
class TrainConfig:
    OWN_OPTIONS: ClassVar[tuple[str, ...]] = ("prior",)
    """Groups whose settings are options of their own: --sd-model, not --prior-sd-model
    (``core.constraints.flag``)."""
    prompt: str = "a yellow duck"
    """What to generate (the empirical prior matches it to one of its assets' captions)."""
    preset: str = "gd"
    """Name of the preset this config came from (recorded in run.json)."""
    steps: Annotated[int, AtLeast(1)] = 2000
    """Training steps (the paper: 2000). The densification schedule, the sigma annealing, the noise
    ratio and the means' learning-rate decay are fractions of it."""
    seed: Annotated[int, Seed()] = 0
    """Seed of every random stream of the run (train/streams.py): presets with one seed are paired."""
    resolution: Annotated[int, AtLeast(8, "px")] = 64
    """Training render size (CPU-sized; the paper uses 512 with Stable Diffusion)."""
    views: ViewsConfig = field(default_factory=ViewsConfig)
    """How many views a step renders, and how far apart (train/views.py)."""
    # initialisation
    init: Literal["sphere", "ply", "bank-depth"] = "sphere"
    """Initial Gaussians: the paper's sphere, a point cloud (--init-ply) or the prompt's bank depth."""
    init_points: Annotated[int, AtLeast(1)] = 4096
    """Initial Gaussians (the paper: 4096)."""
    init_ply: Annotated[Path | None, When("init", "ply")] = None
    """init='ply': any point cloud Open3D reads. A file that records its up axis (every scene file
    gdbench writes, an export included) is turned to +Z up; any other is taken as +Z up."""
    init_opacity: Annotated[float, Between(0, 1, open=True)] = 0.1
    """Opacity of every initial Gaussian (the paper: 0.1)."""
    init_color: Annotated[float, Between(0, 1), When.any(When("init", "sphere"), When("prior.sd_mode", "latent"))] = 0.5
    """Grey level of the initial sphere's Gaussians (init='sphere'; point clouds bring their colours)."""
    # cameras (paper)
    camera_radius: Annotated[float, Positive()] = 1.0
    """Distance of the training cameras from the origin (the paper: 1)."""
    fovy_range: Annotated[tuple[float, float], Between(1, 179, unit="degrees")] = (40.0, 70.0)
    """Vertical field of view of the training views, degrees, drawn uniformly (the paper: 40-70)."""
    azimuth_range: Annotated[tuple[float, float], Between(-360, 360, unit="degrees")] = (-180.0, 180.0)
    """Azimuth of the training views, degrees (the paper: all around)."""
    elevation_range: Annotated[tuple[float, float], Between(-90, 90, open=True, unit="degrees")] = (-45.0, 45.0)
    """Elevation of the training views, degrees (the paper: -45 to 45)."""
    background: Annotated[tuple[float, float, float], Between(0, 1)] = (1.0, 1.0, 1.0)
    """Background colour of the renders and of the prior's bank (the paper: white)."""
    # score distillation
    guidance: str = "sjc"
    """sjc: g = (D(x + sigma n) - x) / sigma with sigma uniform over the prior's ticks;
    sds: the same residual with DreamGaussian's annealed timestep and weight 1 - abar; or your own,
    pkg.mod:function or file.py:function, with SJC's sigma (mechanisms/methods.py, docs/training.md
    "Your own method")."""
    sigma_min: Annotated[float, Positive(), When("guidance", not_=("sds",))] = 0.03
    """Smallest noise level drawn (VE sigma; not with guidance 'sds', which anneals its timestep)."""
    sigma_max: Annotated[float, Positive(), When("guidance", not_=("sds",))] = 10.0
    """Largest noise level drawn at the start of the run (VE sigma; not with guidance 'sds')."""
    anneal: Annotated[bool, When("guidance", not_=("sds",))] = True
    """Anneal sigma (not with guidance 'sds'): the upper end of its range decays linearly to ``sigma_min``
    over the run; off, sigma stays uniform over [sigma_min, sigma_max] (measured: docs/training.md,
    "Options measured")."""
    samples_per_step: Annotated[int, AtLeast(1)] = 1
    """K, perturb-and-average: noise samples averaged per step."""
    weight: Annotated[float, Positive()] = 1.0
    """Global scale of the score (the 'guidance' multiplier)."""
    prior: PriorConfig = field(default_factory=EmpiricalPriorConfig)
    """The prior score distillation queries, with its own settings (--prior empirical, learned or
    sd): the embedded CPU prior (the exact posterior over image banks of procedural assets), a
    small diffusion model trained on the same assets (docs/learned_prior.md), or Stable Diffusion."""
    # the paper's additions
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    """The paper's structured noise (section 3.2; mechanisms/noise.py): --structured-noise and its
    settings."""
    vgs: VGSConfig = field(default_factory=VGSConfig)
    """The paper's variational Gaussians (section 3.3; mechanisms/variational.py)."""
    # optimisation
    optim: OptimConfig = field(default_factory=OptimConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    sh_degree: Annotated[int, Between(0, 3), When("prior.sd_mode", not_=("latent",))] = 0
    """Spherical-harmonics degree of the Gaussians' colours (0: plain colour)."""
    # run management
    out: Path = Path("runs/duck")
    """The run folder."""
    checkpoint_every: Annotated[int, AtLeast(1)] = 200
    """Steps between checkpoints (a run also checkpoints on Ctrl-C)."""
    log_every: Annotated[int, AtLeast(1), When.any(When("progress", True), When("log_dir", not_=(None,)))] = 10
    """Steps between updates of the progress report's figures and between --log-dir's scalars."""
    turntable_frames: Annotated[int, AtLeast(1)] = 36
    """Frames of the output turntable (GIF, MP4 and contact sheet), evenly spaced around the object."""
    progress: bool = True
    """Report progress: a bar on a terminal, a plain line every few seconds in a log."""
    log_dir: Path | None = None
    """Write TensorBoard scalars (residual, sigma, Gaussians, step times; PSNR against the asset
    where the prompt matched one) under this folder, one sub-folder per run (needs tensorboard:
    pip install -e '.[log]')."""
    max_bad_steps: Annotated[int, AtLeast(0)] = 20
    """Stop with an error after this many consecutive steps with non-finite gradients."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Where the scene, its renders and the noise live: cpu (the reference: the C++ compositor,
    results reproduce bit for bit), cuda (gsplat's CUDA kernels with
    gdbench's conventions; the same random draws, results that follow the CPU's in distribution;
    the empirical prior stays on the CPU) or auto (cuda when torch
    sees one)."""

    def __post_init__(self) -> None:
        check_fields(self)  # every field against its declared type, range and choices (core.constraints)
        from gdbench.mechanisms.methods import check

        check("guidance", self.guidance)  # a built-in name, or the user's method loads
        if not self.sigma_min < self.sigma_max:
            raise ValueError(f"sigma_min (--sigma-min): expected < sigma_max ({self.sigma_max}), got {self.sigma_min}")
        for name in ("fovy_range", "azimuth_range", "elevation_range"):
            lo, hi = getattr(self, name)
            if lo > hi:
                raise ValueError(f"{name} (--{name.replace('_', '-')}): expected low <= high, got {(lo, hi)}")
        if self.init == "bank-depth" and self.prior.kind != "empirical":
            raise ValueError(
                f"init: 'bank-depth' needs the empirical prior's image bank; --prior {self.prior.kind} has none"
            )
        if self.init == "ply" and self.init_ply is None:
            raise ValueError("init_ply: init='ply' needs a PLY path (--init-ply FILE)")
        if self.prior.kind == "sd" and self.resolution % 8:
            raise ValueError(f"resolution: the sd prior needs a multiple of 8 (latents are 1/8), got {self.resolution}")
        self.densify.resolve(self.steps)  # an explicit schedule that breaks the rules fails here

    def run_view(self) -> RunView:
        """What the prior reads of this run (``priors.RunView``)."""
        return RunView(
            self.prompt, self.seed, self.resolution, self.camera_radius, self.fovy_range, self.elevation_range,
            self.background, self.device, self.out,
        )  # fmt: skip


PRESETS: dict[str, TrainConfig] = {
    "gd": TrainConfig(preset="gd"),
    "gd-no-sn": TrainConfig(preset="gd-no-sn", noise=NoiseConfig(enabled=False)),
    "gd-no-vgs": TrainConfig(preset="gd-no-vgs", vgs=VGSConfig(enabled=False)),
    "sjc-gs": TrainConfig(preset="sjc-gs", noise=NoiseConfig(enabled=False), vgs=VGSConfig(enabled=False)),
    "sds-gs": TrainConfig(
        preset="sds-gs", noise=NoiseConfig(enabled=False), vgs=VGSConfig(enabled=False), guidance="sds", anneal=True
    ),
    "gd-redraw-step": TrainConfig(preset="gd-redraw-step", noise=NoiseConfig(redraw="step")),
    "gd-pose-locked": TrainConfig(preset="gd-pose-locked", noise=NoiseConfig(source="pose")),
}
"""The paper's method, its two ablations and two baselines, written out by hand; and two controls
of the mechanism (docs/decisive.md, "The controls"): gd-redraw-step, gd with the noise cloud's
colours redrawn every step (the noise's spatial statistics without persistence: no two steps see
the same noise; at --views-per-step 4 the views of one step still share it in 3D), and
gd-pose-locked, a fixed 2D field per camera pose (persistence and the same statistics without 3D
correspondence between views, mechanisms/pose_noise.py)."""

BASE_PRESETS = ("gd", "gd-no-sn", "gd-no-vgs", "sjc-gs", "sds-gs")
"""The paper's method, ablations and baselines (a sweep's default presets)."""


NESTED = {"views": ViewsConfig, "noise": NoiseConfig, "vgs": VGSConfig, "optim": OptimConfig, "densify": DensifyConfig}
"""Nested config groups an override may reach with a dotted key ('noise.redraw')."""


@functools.cache
def setting_names() -> dict[str, str]:
    """Every name a setting goes by -> its dotted key: the one converter of the command line's
    names, sweep files' keys, ``preset()``'s keywords and run.json's layouts. Each dotted key
    ('noise.redraw', 'prior.sd_model', 'steps') under itself and under its option name (its flag
    without dashes: 'noise_redraw', 'sd_model', 'vgs', 'structured_noise'), and the keys of
    ``layout.RENAMED``."""
    keys = [f.name for f in fields(TrainConfig) if f.name not in NESTED and f.name != "prior"]
    keys += [f"{g}.{f.name}" for g, cls in NESTED.items() for f in fields(cls)]
    keys += [f"prior.{f.name}" for cls in PRIOR_CONFIGS.values() for f in fields(cls)]
    names = {k: k for k in keys}
    names |= {flag(k, TrainConfig)[2:].replace("-", "_"): k for k in keys if "." in k}
    return names | RENAMED


def key_of(name: str) -> str:
    """The dotted key of a setting named any way ``setting_names`` knows; 'prior' (the kind) as it
    is. An unknown name is a ValueError naming it."""
    if name == "prior":
        return name
    plain = name.replace("-", "_")  # an option as typed: views-per-step
    key = setting_names().get(plain)
    if key is None and plain.startswith("prior."):  # a prior's setting by its dotted key
        key = setting_names().get(plain.removeprefix("prior."))
        key = key if key is not None and key.startswith("prior.") else None
    if key is None:
        raise ValueError(f"overrides: unknown setting {name!r}")
    return key


def prior_option_error(key: str, kind: str, typed: str = "") -> str | None:
    """The one message for a prior's setting given with a prior that lacks it ('--front-bias acts
    only with --prior empirical or learned (this run: --prior sd)', the option named as ``typed``
    where given: --no-depth-conditioning); None when ``kind`` has it."""
    name = key.removeprefix("prior.")
    kinds = [k for k, c in PRIOR_CONFIGS.items() if name in {f.name for f in fields(c)}]
    if kind in kinds or not kinds:
        return None
    return f"{typed or flag(key, TrainConfig)} acts only with --prior {' or '.join(kinds)} (this run: --prior {kind})"


def apply_overrides(cfg: TrainConfig, overrides: Mapping[str, object]) -> TrainConfig:
    """``cfg`` with ``overrides`` applied: each key a setting's name as ``key_of`` reads it (a
    field, 'group.field', an option name such as 'vgs_gamma', a prior's setting with or without
    'prior.'); a group's name with a config replaces the group (keeping the run's structured noise
    switch, or the prior's view prompting, where the config leaves them at their defaults: they
    moved into those configs, ``_keep_moved``); 'prior' names its kind (its settings
    that the new kind shares are kept). Unknown keys, and a prior's setting the chosen prior lacks,
    raise ValueError naming them."""
    top: dict[str, object] = {}
    nested: dict[str, dict[str, object]] = {}
    prior_kw: dict[str, object] = {}
    prior = cfg.prior
    named = {key_of(n) for n in overrides if not (n in NESTED and is_dataclass(overrides[n]))}
    for name, value in overrides.items():
        if name in NESTED and is_dataclass(value):  # the group itself ('vgs': a VGSConfig)
            top[name] = _keep_moved(value, getattr(cfg, name), name, named)
            continue
        key = key_of(name)
        group, _, field_name = key.rpartition(".")
        if key == "prior":
            prior = _prior_of_kind(prior, value)
            prior = _keep_moved(prior, cfg.prior, "prior", named) if not isinstance(value, str) else prior
        elif group == "prior":
            prior_kw[field_name] = value
        elif group:
            nested.setdefault(group, {})[field_name] = value
        else:
            top[key] = value
    for name in prior_kw:
        message = prior_option_error(f"prior.{name}", prior.kind)
        if message is not None:
            raise ValueError(message)
    for group, values in nested.items():
        top[group] = replace(top.get(group, getattr(cfg, group)), **values)
    return replace(cfg, **top, prior=replace(prior, **prior_kw))


def _keep_moved(new, old, group: str, named: set[str]):
    """A group (or prior) config passed whole, with the settings that moved into it from the top of
    the config (``layout.RENAMED``: structured noise's switch, view prompting) kept from ``old``
    where ``new`` leaves them at their default and no override names them: before the move such a
    group did not hold them, so it did not change them."""
    keep = {}
    for moved in RENAMED.values():
        g, _, name = moved.rpartition(".")
        if g == group and moved not in named and hasattr(new, name) and hasattr(old, name):
            if getattr(new, name) == getattr(type(new)(), name):
                keep[name] = getattr(old, name)
    return replace(new, **keep) if keep else new


def _prior_of_kind(prior, kind):
    """``prior`` as a config of ``kind`` (a --prior name, or a prior's config as it is): the
    settings the two kinds share (front_bias, variants, depth_conditioning) carried over."""
    if not isinstance(kind, str):
        if type(kind) not in PRIOR_CONFIGS.values():
            raise ValueError(f"prior (--prior): expected one of {list(PRIOR_CONFIGS)} or a config, got {kind!r}")
        return kind
    if kind not in PRIOR_CONFIGS:
        raise ValueError(f"prior (--prior): expected one of {list(PRIOR_CONFIGS)}, got {kind!r}")
    if kind == prior.kind:
        return prior
    cls = PRIOR_CONFIGS[kind]
    shared = {f.name: getattr(prior, f.name) for f in fields(cls) if f.name in {g.name for g in fields(prior)}}
    return cls(**shared)


def preset(name: str, **overrides) -> TrainConfig:
    """The named preset with ``overrides`` (``apply_overrides``; pass dotted keys as a dict:
    ``preset("gd", **{"noise.redraw": "ou"})``)."""
    if name not in PRESETS:
        raise ValueError(f"preset: unknown {name!r}; expected one of {sorted(PRESETS)}")
    return apply_overrides(PRESETS[name], overrides)


def from_json(typ, value, key: str, what: str = "config"):
    """``value`` as a JSON or YAML file holds it, checked and converted to a field of type ``typ``:
    lists as tuples (each element by its type), strings as paths, ints and numeric strings ('1e-3',
    which YAML leaves a string) as floats where a float is wanted. A value of the wrong kind is a
    ValueError naming ``key`` (so "false" is not taken for a true bool, nor 5 for a path)."""
    import types
    import typing

    origin, args = typing.get_origin(typ), typing.get_args(typ)
    if origin is Annotated:
        return from_json(args[0], value, key, what)
    bad = ValueError(f"{what}: {key}: expected {getattr(typ, '__name__', typ)}, got {value!r}")
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in args:
            return None
        inner = [a for a in args if a is not type(None)]
        return from_json(inner[0], value, key, what) if len(inner) == 1 else value
    if value is None:
        raise ValueError(f"{what}: {key}: expected a value, got null")
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            raise ValueError(f"{what}: {key}: expected a list, got {value!r}")
        each = [args[0]] * len(value) if len(args) == 2 and args[1] is Ellipsis else list(args)
        if len(each) != len(value):
            raise ValueError(f"{what}: {key}: expected {len(each)} values, got {len(value)}")
        return tuple(from_json(t, v, f"{key}[{i}]", what) for i, (t, v) in enumerate(zip(each, value)))
    if origin is Literal:
        return value  # the declared check names the choices
    if typ is Path:
        if not isinstance(value, (str, Path)):
            raise bad
        return Path(value)
    if typ is bool:
        if not isinstance(value, bool):
            raise bad
        return value
    if typ is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise bad
        return value
    if typ is float:
        if isinstance(value, str):
            try:
                return float(value)
            except ValueError:
                raise bad from None
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise bad
        return float(value)
    if typ is str and not isinstance(value, str):
        raise bad
    return value


def _hint(key: str, kind: str):
    """The declared type of a dotted key ('noise.redraw', 'prior.sd_model', 'steps') with the prior
    ``kind``, or None where it has none."""
    import typing

    group, _, name = key.rpartition(".")
    cls = PRIOR_CONFIGS.get(kind) if group == "prior" else NESTED.get(group) if group else TrainConfig
    return typing.get_type_hints(cls, include_extras=True).get(name) if cls is not None else None


def config_from_dict(d: Mapping[str, object], *, base: TrainConfig | None = None, what: str = "config") -> TrainConfig:
    """The ``TrainConfig`` a JSON dict describes (the inverse of ``outputs.config_dict``, as run.json
    stores it): nested groups as dicts, tuples as lists, paths as strings, the prior as a mapping
    with its 'kind'. Every earlier layout of run.json reads here too (``train.layout``): the flat
    one up to commit 95ebebe (the prior's kind as 'prior', its settings beside the other fields,
    where the settings of the other priors must hold their defaults, ``LEGACY_PRIOR_DEFAULTS``) and
    the renamed settings (``layout.RENAMED``). Keys it lacks keep ``base``'s values (default: the
    dict's own preset); unknown keys raise a ValueError naming them."""
    if not isinstance(d, Mapping):
        raise ValueError(f"{what}: expected a mapping of settings, got {type(d).__name__}")
    name = d.get("preset", base.preset if base is not None else "gd")
    if base is None:
        complete = {f.name for f in fields(TrainConfig)} - {"device"} <= set(d)  # a run.json (its device aside)
        if name not in PRESETS and not complete:
            raise ValueError(
                f"{what}: preset: unknown {name!r}; expected one of {sorted(PRESETS)} (a preset a sweep file "
                "defines is known to its sweep; its cells' run.json files hold every setting)"
            )
        base = PRESETS.get(name, PRESETS["gd"])  # a sweep's own preset: every field comes from the dict
    given: list[tuple[str, object]] = []  # (name as written, value), groups and the prior opened
    prior = d.get("prior")
    kind = prior.get("kind", base.prior.kind) if isinstance(prior, Mapping) else prior if prior is not None else None
    if kind is not None:
        given.append(("prior", kind))
    kind = kind if isinstance(kind, str) else base.prior.kind
    mine = {f.name for f in fields(PRIOR_CONFIGS[kind])} if kind in PRIOR_CONFIGS else set()
    for key, value in d.items():
        if key == "prior":
            given += [(f"prior.{k}", v) for k, v in prior.items() if k != "kind"] if isinstance(prior, Mapping) else []
        elif key in NESTED and (isinstance(value, Mapping) or key not in setting_names()):  # ('vgs': the flat switch)
            if not isinstance(value, Mapping):
                raise ValueError(f"{what}: {key}: expected a mapping, got {value!r}")
            given += [(f"{key}.{k}", v) for k, v in value.items()]
        elif key in LEGACY_PRIOR_DEFAULTS and key not in mine and value == LEGACY_PRIOR_DEFAULTS[key]:
            continue  # the flat layout: another prior's setting at its default (that layout wrote every one)
        else:
            given.append((key, value))
    flat: dict[str, object] = {}
    for written, value in given:
        try:
            key = key_of(written)
        except ValueError:
            raise ValueError(f"{what}: unknown setting {written!r}") from None
        hint = _hint(key, kind)
        flat[key] = from_json(hint, value, written, what) if hint is not None and key != "prior" else value
    try:
        return apply_overrides(base, flat)
    except ValueError as e:
        raise ValueError(f"{what}: {e}") from None
