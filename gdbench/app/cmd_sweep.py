"""``gdbench sweep``: train and score a grid of cells, then the paper's claims as verdicts. Its
options are a grid file's (``--config``, read by ``sweep_from_mapping``; each sweep writes its own
as sweep.yaml) overridden by the command line; every cell takes the chosen prior's overrides."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Annotated, Literal

import tyro

from gdbench.app.cmd_generate import _with_options
from gdbench.core.constraints import AtLeast, Seed
from gdbench.priors.factory import PRIOR_CONFIGS
from gdbench.train.config import BASE_PRESETS
from gdbench.train.options import train_options

SWEEP_EXCLUDES = ("prompt", "preset", "out", "progress", "seed", "steps", "log_every", "log_dir")
"""TrainConfig fields that are not overrides of a sweep's cells (cells run without a progress bar,
so --log-every has no place here)."""

SweepTrain = train_options(SWEEP_EXCLUDES)
"""Every other TrainConfig field as an override of every cell (the empirical prior's options;
``sweep_command`` makes the others')."""


@dataclass
class SweepBase:
    """Train and score every (setting, prompt, preset, seed) cell; write cells.csv, summary.csv,
    summary.md and verdict.csv (the paper's claims over (prompt, seed) pairs: BCa intervals,
    signed-rank p-values Holm-adjusted, equivalence tests, power, per-prompt effects); with
    --figures also ablation.png and each cell's turntable. Resumable: finished cells (scored by
    the same code) are skipped, an interrupted cell resumes from its checkpoint. The grid is
    validated before the first cell."""

    config: Path | None = None
    """A YAML or JSON file of this command's options (their names with '_' or '-', lists for
    the tuples) and 'overrides', a mapping of training options applied to every cell; options on
    the command line override it. Each sweep writes the options it ran with to <out>/sweep.yaml,
    which this reads back (default: none)."""
    prompts: tuple[str, ...] = ("a yellow duck", "a corgi", "a penguin")
    """Prompts (free text; matched to the embedded prior's assets)."""
    presets: tuple[str, ...] = BASE_PRESETS
    """Training presets to compare (see docs/training.md; the mechanism's controls gd-redraw-step
    and gd-pose-locked on request)."""
    seeds: Annotated[tuple[int, ...], Seed()] = (0, 1)
    """Seeds per (setting, prompt, preset); cells with one seed and prompt are paired."""
    settings: tuple[Literal["easy", "janus", "instance"], ...] = ("easy",)
    """Ambiguity settings: easy (the presets' view window, one variant), janus (no view prompting,
    front-heavy bank), instance (three procedural variants per caption)."""
    janus_presets: tuple[str, ...] = ()
    """Presets of the janus setting (default: all of --presets)."""
    instance_presets: tuple[str, ...] = ()
    """Presets of the instance setting (default: all of --presets)."""
    colmap_presets: tuple[str, ...] = ()
    """Score only these presets with COLMAP (default: all, when --colmap)."""
    colmap_settings: tuple[str, ...] = ()
    """Score with COLMAP only in these settings (default: all, when --colmap)."""
    steps: Annotated[int, AtLeast(1)] = 2000
    """Training steps per cell."""
    out: Path = Path("runs/sweep")
    """Folder for the cells (one run folder each) and the tables."""
    executor: Literal["local", "ray"] = "local"
    """Where cells run: a local process pool or a Ray cluster."""
    address: str = ""
    """Ray cluster address (ray executor); empty starts a local Ray instance."""
    workers: Annotated[int, AtLeast(1)] = 1
    """Cells run at once (one training already uses both cores of a small machine)."""
    colmap: bool = True
    """Score cells with COLMAP consistency (seconds per cell on 2 cores, a share of a cell's time;
    measured: docs/performance.md)."""
    colmap_views: Annotated[int, AtLeast(2)] = 100
    """Views on the circle rendered for COLMAP."""
    figures: bool = False
    """Also draw each cell's turntable (GIF, MP4, contact sheet) and training curves, as generate
    does (about 2 s a cell), and the sweep's ablation.png (every cell's metrics). Off, a cell
    writes scene.ply, run.json, scores.json and cell.json, what the tables need; run a finished
    sweep again with --figures to draw them (nothing is trained again)."""
    labels: tuple[Path, ...] = ()
    """Rater label files (run_id,label per line; two passes, as docs/results/v3/labelling): the
    claims on the Janus outcome read them. summary.md says which it read. Run a finished sweep
    again with --labels: nothing is trained again (default: none, the shipped judge)."""
    define_presets: tyro.conf.Suppress[dict] = field(default_factory=dict)
    """(The grid file only.) Presets of this sweep's own, named overlays on a built-in one:
    {name: {base: gd, overrides: {guidance: pkg.mod:fn, ...}}}; list them in presets."""
    claims: tyro.conf.Suppress[tuple] = ()
    """(The grid file only.) Claims of this sweep's own between any two of its presets:
    [{text, a, b, metric, fails_at}], verdicts in their own family (docs/training.md)."""


@functools.cache
def sweep_command(prior: str = "empirical") -> type:
    """The sweep command with the options of ``prior`` (a --prior choice) as overrides of every
    cell (after its setting's)."""
    return _with_options(SweepBase, train_options(SWEEP_EXCLUDES, prior), "Sweep")


Sweep = sweep_command()
"""The sweep command with the empirical prior's options (the default --prior)."""


def sweep_from_mapping(d: dict, what: str = "config", prior: str | None = None):
    """The ``Sweep`` a grid file describes (see ``Sweep.config``): each value checked against its
    option's type (``train.config.from_json``); ``overrides`` takes the training options by their
    option names (views-per-step, noise-redraw) or run.json's (noise.redraw, or nested mappings).
    Its command has the options of ``prior`` (the command line's --prior), else of the file's
    'prior' override, else of the empirical prior."""
    import typing

    from gdbench.core.constraints import flag
    from gdbench.train.config import NESTED, TrainConfig, from_json, key_of

    if d is None:
        d = {}  # an empty file: every default
    if not isinstance(d, dict):
        raise ValueError(f"{what}: expected a mapping of sweep options, got {type(d).__name__}")
    over = d.get("overrides")
    kind = prior or (over.get("prior") if isinstance(over, dict) else None) or "empirical"
    command = sweep_command(kind if kind in PRIOR_CONFIGS else "empirical")  # (a bad name: the check names it)
    train_cls = typing.get_type_hints(command)["train"]
    train_cls = typing.get_args(train_cls)[0] if typing.get_origin(train_cls) is Annotated else train_cls
    hints = typing.get_type_hints(SweepBase, include_extras=True)
    names = {f.name for f in fields(SweepBase)} - {"config"}
    train_hints = typing.get_type_hints(train_cls, include_extras=True)
    top, train = {}, {}
    for key, value in d.items():
        k = str(key).replace("-", "_")
        if k in ("define_presets", "claims"):  # the grid file's own: checked by the sweep before any cell
            if not isinstance(value, dict if k == "define_presets" else list):
                raise ValueError(f"{what}: {k}: expected a {'mapping' if k == 'define_presets' else 'list'}")
            top[k] = value if k == "define_presets" else tuple(value)
        elif k == "overrides":
            if not isinstance(value, dict):
                raise ValueError(f"{what}: overrides: expected a mapping of training options, got {value!r}")
            flat = {}
            for ok, ov in value.items():
                if ok in NESTED and isinstance(ov, dict):  # run.json's nested form
                    flat |= {f"{ok}.{k2}": v2 for k2, v2 in ov.items()}
                else:
                    flat[str(ok)] = ov
            for ok, ov in flat.items():
                try:  # any name of the setting (noise.redraw, noise_ratio, an old one) -> its option's
                    key = key_of(str(ok))
                except ValueError:
                    key = str(ok).replace("-", "_")
                o = flag(key, TrainConfig)[2:].replace("-", "_") if "." in key else key
                if o in train_hints:
                    train[o] = from_json(train_hints[o], ov, f"overrides: {ok}", what)
                else:
                    raise ValueError(f"{what}: overrides: unknown training option {ok!r}")
        elif k in names:
            typ = typing.get_args(hints[k])[0] if typing.get_origin(hints[k]) is Annotated else hints[k]
            if isinstance(value, (str, int, float)) and typing.get_origin(typ) is tuple:
                value = [value]  # one prompt or seed written without a list
            top[k] = from_json(hints[k], value, k, what)
        else:
            raise ValueError(f"{what}: unknown sweep option {key!r}; expected some of {sorted(names | {'overrides'})}")
    return command(**top, train=train_cls(**train))


def sweep_mapping(cmd) -> dict:
    """``cmd`` as the mapping ``sweep_from_mapping`` reads (what <out>/sweep.yaml holds)."""
    d = {}
    for f in fields(cmd):
        if f.name in ("config", "train"):
            continue
        v = getattr(cmd, f.name)
        if f.name in ("define_presets", "claims"):
            if v:
                d[f.name] = dict(v) if f.name == "define_presets" else [dict(c) for c in v]
            continue
        d[f.name] = (
            [str(x) if isinstance(x, Path) else x for x in v]
            if isinstance(v, tuple)
            else (str(v) if isinstance(v, Path) else v)
        )

    def plain(v):
        return list(v) if isinstance(v, tuple) else (str(v) if isinstance(v, Path) else v)

    over = {k: plain(v) for k, v in cmd.train.options().items()}  # by option name, as a user writes them
    if over:
        d["overrides"] = over
    return d


def run_sweep(cmd) -> dict:
    import yaml

    from gdbench.core.io import atomic_write, check_folder
    from gdbench.experiments.sweep import SweepConfig, sweep

    check_folder(cmd.out)
    text = yaml.safe_dump(sweep_mapping(cmd), sort_keys=False).encode()

    def record() -> None:  # once the grid is valid: a refused grid leaves nothing behind
        Path(cmd.out).mkdir(parents=True, exist_ok=True)
        atomic_write(Path(cmd.out) / "sweep.yaml", lambda f: f.write(text))

    per = {"janus": cmd.janus_presets, "instance": cmd.instance_presets}
    grid = SweepConfig(
        list(cmd.prompts),
        list(cmd.presets),
        list(cmd.seeds),
        steps=cmd.steps,
        out=cmd.out,
        executor=cmd.executor,
        address=cmd.address,
        workers=cmd.workers,
        colmap=cmd.colmap,
        colmap_views=cmd.colmap_views,
        overrides=cmd.train.overrides(),
        settings=list(cmd.settings),
        setting_presets={k: list(v) for k, v in per.items() if v},
        colmap_presets=list(cmd.colmap_presets) or None,
        colmap_settings=list(cmd.colmap_settings) or None,
        figures=cmd.figures,
        defined_presets=cmd.define_presets or None,
        claims=list(cmd.claims) or None,
        labels=[str(p) for p in cmd.labels] or None,
    )
    rows = sweep(grid, on_valid=record)
    print((Path(cmd.out) / "summary.md").read_text())
    return {"cells": len(rows), "out": str(cmd.out)}
