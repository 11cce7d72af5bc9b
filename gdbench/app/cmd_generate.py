"""``gdbench generate``: text to a 3D Gaussian scene (the trainer, with a run folder that resumes).
Its options are the preset's overrides of the chosen prior (``generate_command``); a --config file
(a run.json or a file of settings) gives the base the command line overrides."""

from __future__ import annotations

import functools
from dataclasses import dataclass, field, make_dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from gdbench.core.constraints import AtLeast, Between
from gdbench.core.io import prompt_slug
from gdbench.train.config import PRESETS
from gdbench.train.options import train_options

PresetName = Literal[tuple(PRESETS)]  # type: ignore[valid-type]
"""The presets' names, from the one place they are defined (train/config.py)."""

GENERATE_EXCLUDES = ("prompt", "preset", "out", "progress")
"""TrainConfig fields that are not training options of generate (its own options, or none)."""

GenerateTrain = train_options(GENERATE_EXCLUDES)
"""Every other TrainConfig field as an optional override of the preset (the empirical prior's
options; ``generate_command`` makes the others')."""


@dataclass
class GenerateBase:
    """Text to a 3D Gaussian scene: score distillation on the embedded CPU prior (or the learned
    prior with --prior learned, Stable Diffusion with --prior sd).

    Writes scene.ply, turntable.{gif,mp4}, turntable_sheet.png, curves.png, run.json and a
    checkpoint to --out; an interrupted run resumes from its checkpoint. Every training setting
    is an option; unset ones keep the preset's value (docs/training.md)."""

    prompt: Annotated[tyro.conf.Positional[str | None], tyro.conf.DisallowNone, tyro.conf.arg(metavar="PROMPT")] = None
    """What to generate: one of the built-in assets' captions or a paraphrase of one (required
    unless --config gives it)."""
    preset: Annotated[PresetName | None, tyro.conf.DisallowNone, tyro.conf.arg(help_behavior_hint="(default: gd)")] = (
        None
    )
    """gd: structured noise + VGS (the paper); the others are its ablations and baselines."""
    config: Path | None = None
    """A run.json (reproduces that run: same settings, same result on CPU; its device is not taken
    from it) or a JSON/YAML file of settings (TrainConfig's field names; nested groups as
    mappings). Options given on the command line override it; the file's run folder is used when
    --out is not given (default: none)."""
    out: Path | None = None
    """The run folder (default: runs/<the prompt, lower-case, '_' for other characters>, such as
    runs/a_yellow_duck)."""
    resume: bool = True
    """Continue from --out's checkpoint if there is one."""
    overwrite: bool = False
    """Replace a finished run in --out (its outputs are deleted first)."""
    score: bool = True
    """Score the result against the asset (PSNR/SSIM and view metrics) into scores.json."""
    progress: bool = True
    """Report progress: a bar on a terminal, a plain line every few seconds in a log."""
    view: bool = False
    """Watch the run train in the browser viewer (viser; `pip install -e '.[view]'`): the scene is
    sent every --view-every steps; the server stops when the run ends (docs/viewer.md)."""
    view_every: Annotated[int, AtLeast(1)] = 100
    """--view: send the scene to the viewer every this many steps."""
    view_port: Annotated[int, Between(1, 65535)] = 8080
    """--view: the viewer's port on 127.0.0.1 (the next free one when it is busy)."""


def _with_options(base: type, train: type, name: str) -> type:
    """``base`` with the option group ``train`` (a ``train_options`` class)."""
    cls = make_dataclass(
        name,
        [("train", tyro.conf.OmitArgPrefixes[train], field(default_factory=train))],
        bases=(base,),
        namespace={"__doc__": base.__doc__, "__module__": __name__},
    )
    return cls


@functools.cache
def generate_command(prior: str = "empirical") -> type:
    """The generate command with the options of ``prior`` (a --prior choice)."""
    return _with_options(GenerateBase, train_options(GENERATE_EXCLUDES, prior), "Generate")


Generate = generate_command()
"""The generate command with the empirical prior's options (the default --prior)."""


def run_generate(cmd) -> dict:
    from gdbench.app.resources import check_generate_memory
    from gdbench.train.config import apply_overrides, preset
    from gdbench.train.options import inert_options
    from gdbench.train.run import train

    overrides = cmd.train.overrides()
    base, file_out = _config_file(cmd.config, cmd.preset) if cmd.config is not None else (None, None)
    prompt = cmd.prompt if cmd.prompt is not None else (base.prompt if base is not None else None)
    if not prompt:
        raise ValueError("prompt: expected a prompt (such as 'a yellow duck'), or --config with one")
    if cmd.out is not None:
        out = Path(cmd.out)
    elif file_out is not None:
        out = file_out
    else:
        try:
            out = Path("runs") / prompt_slug(prompt)
        except ValueError as e:
            raise ValueError(f"{e}; pass --out") from None
    given = {"prompt": prompt, "out": out, "progress": cmd.progress, **overrides}
    cfg = apply_overrides(base, given) if base is not None else preset(cmd.preset or "gd", **given)
    inert = inert_options(cfg, overrides)
    if inert:
        raise ValueError("; ".join(inert) + ": drop the option, or set the one it needs")
    check_generate_memory(cfg)
    if cfg.log_dir is not None:  # before the bank is built, not after
        from gdbench.train.tblog import require_tensorboard

        require_tensorboard()

    def started(ctx) -> None:  # the matched asset before the steps, not after them
        from gdbench.train.checkpoint import checkpoint_path

        caption, sim = getattr(ctx.cond, "caption", None), getattr(ctx.cond, "similarity", None)
        match = f" -> asset {caption!r} (cosine {sim:.2f})" if caption is not None else ""
        replaced = cmd.overwrite and (out / "run.json").is_file()  # --overwrite deletes a finished run's checkpoint
        if cmd.resume and checkpoint_path(cfg).is_file() and not replaced:  # said first, not only in the last line
            what = f"resuming the run in {out} from its checkpoint ({cfg.steps} steps in all)"
        else:
            what = f"{cfg.steps} steps into {out}"
        print(f"gdbench generate: prompt {cfg.prompt!r}{match}; {what}", flush=True)
        from gdbench.app.prebuild import running

        pid = running()
        if pid is not None:
            from gdbench.core.cache import root

            print(
                f"gdbench generate: note: the assets' banks are being built in the background (gdbench cache build, "
                f"pid {pid}; log {root() / 'prebuild.log'}); this run shares the machine with it and is slower "
                "until it ends",
                flush=True,
            )

    live = None
    if cmd.view:
        from gdbench.app.live_view import LiveView
        from gdbench.app.viewer import import_viser

        import_viser()  # its install hint now, not after the bank is built
        live = LiveView(every=cmd.view_every, port=cmd.view_port)
    try:
        r = train(cfg, resume=cmd.resume, overwrite=cmd.overwrite, on_start=started, on_step=live)
    finally:
        if live is not None:
            live.close()
    summary = r.summary()
    if cmd.score and r.caption is not None and r.state.step >= cfg.steps:
        from gdbench.metrics.run_scores import score_run

        scores = score_run(out, gt=True, colmap=False, progress=cmd.progress, device=cfg.device)
        summary |= {k: scores[k] for k in ("gt", "views", "judge") if k in scores}
    print(r.report(summary, matched=False))
    return summary


def _config_file(path: Path, preset_name: str | None):
    """(the TrainConfig, the run folder the file names or None) of a run.json (its "config") or a
    JSON/YAML file of settings. ``preset_name`` (given on the command line) is the base of a file
    that names no preset; a file that names one keeps it (a preset is a set of settings, not a
    label to put on another's)."""
    from gdbench.train.config import PRESETS, config_from_dict

    d = load_mapping(path)
    settings = d["config"] if "run_id" in d and isinstance(d.get("config"), dict) else d  # a run.json
    if settings is not d:  # a run.json reproduces its run on any device: --device chooses (default cpu)
        settings = {k: v for k, v in settings.items() if k != "device"}
    if preset_name and "preset" in settings and settings["preset"] != preset_name:
        raise ValueError(
            f"preset: {path} holds the settings of preset {settings['preset']!r}; drop --preset {preset_name}, "
            "or drop 'preset' from the file to apply its settings to another preset"
        )
    base = PRESETS[preset_name] if preset_name and "preset" not in settings else None
    cfg = config_from_dict(settings, base=base, what=f"config ({path})")
    return cfg, (cfg.out if "out" in settings else None)


def load_mapping(path: Path, what: str = "config") -> dict:
    """A YAML (.yaml, .yml) or JSON file's top-level mapping; errors name ``what`` and the file."""
    from gdbench.core.io import read_json

    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"{what}: no file at {path}")
    if path.suffix.lower() in (".yaml", ".yml"):
        import yaml

        try:
            d = yaml.safe_load(path.read_text())
        except yaml.YAMLError as e:
            raise ValueError(f"{what}: {path} is not valid YAML ({str(e).splitlines()[0]})") from None
    else:
        d = read_json(path, what=what)
    if not isinstance(d, dict):
        raise ValueError(f"{what}: {path}: expected a mapping, got {type(d).__name__}")
    return d
