"""The ``gdbench`` command line: the table of commands (each in its group's module,
``cmd_*.py``), the one-line errors and exit codes, and the process's exit. ``main(cmd)`` does the
work and is tested; ``entrypoint`` only parses arguments with tyro (generate's and sweep's with
the chosen prior's options, ``chosen_prior``)."""

from __future__ import annotations

import signal
from pathlib import Path
from typing import Annotated

import tyro

from gdbench.app.cmd_generate import GenerateBase, generate_command, load_mapping, run_generate
from gdbench.app.cmd_refs import Bench, Compare, Conformance, run_bench, run_compare, run_conformance
from gdbench.app.cmd_scenes import (
    Export,
    JudgeRuns,
    Render,
    Score,
    View,
    run_export,
    run_judge,
    run_render,
    run_score,
    run_view,
)
from gdbench.app.cmd_sweep import SweepBase, run_sweep, sweep_command, sweep_from_mapping
from gdbench.app.cmd_tools import (
    Cache,
    Demo,
    Noise,
    Prompts,
    TrainJudge,
    TrainPrior,
    run_cache,
    run_demo,
    run_noise,
    run_prompts,
    run_train_judge,
    run_train_prior,
)
from gdbench.core.constraints import check_fields
from gdbench.priors.factory import PRIOR_CONFIGS

COMMANDS = {
    "generate": (GenerateBase, run_generate),
    "render": (Render, run_render),
    "compare": (Compare, run_compare),
    "conformance": (Conformance, run_conformance),
    "demo": (Demo, run_demo),
    "noise": (Noise, run_noise),
    "score": (Score, run_score),
    "judge": (JudgeRuns, run_judge),
    "sweep": (SweepBase, run_sweep),
    "bench": (Bench, run_bench),
    "train-prior": (TrainPrior, run_train_prior),
    "train-judge": (TrainJudge, run_train_judge),
    "view": (View, run_view),
    "export": (Export, run_export),
    "cache": (Cache, run_cache),
    "prompts": (Prompts, run_prompts),
}
"""Subcommand name -> (its options, the function that runs them); generate's and sweep's options
are those of a --prior choice (``generate_command``, ``sweep_command``)."""


def one_paragraph_help(cls) -> type:
    """Each field's docstring as one paragraph of help (tyro keeps the line breaks of an indented
    docstring) with the default said once: by the docstring where it says it, else by tyro. An
    optional field's None is its default, not a value to type (``--out PATH``, not
    ``--out {None}|PATH``). The class's own annotations are kept."""
    import types
    import typing

    from gdbench.train.options import _field_docs

    docs = _field_docs(cls)
    hints = typing.get_type_hints(cls, include_extras=True)
    new = {}
    for name, hint in hints.items():
        marks = []
        inner = typing.get_args(hint)[0] if typing.get_origin(hint) is Annotated else hint
        if typing.get_origin(inner) in (typing.Union, types.UnionType) and type(None) in typing.get_args(inner):
            marks.append(tyro.conf.DisallowNone)
        if name in docs:
            said = "(default" in docs[name] or "(required" in docs[name]
            marks.append(tyro.conf.arg(help=docs[name], **({"help_behavior_hint": ""} if said else {})))
        new[name] = Annotated[(hint, *marks)] if marks else hint
    cls.__annotations__ = new
    return cls


for _kind, _ in COMMANDS.values():
    one_paragraph_help(_kind)


def main(cmd) -> dict:
    """Validate the whole command line against its declared ranges (``gdbench.core.constraints``),
    then run it: nothing is built, rendered or trained for a command that cannot run."""
    for _, (kind, run) in COMMANDS.items():
        if isinstance(cmd, kind):
            check_fields(cmd, nested=False)  # option groups (train, method) hold plain flags
            return run(cmd)
    raise TypeError(f"cmd: unknown command {type(cmd).__name__}")


def error_line(e: BaseException) -> tuple[str, int]:
    """(one-line message, exit code) for an error a user can act on; re-raises anything else.

    Exit code 2: bad arguments, missing or broken files, a busy or unwritable folder, a full
    disk, an optional dependency not installed (its message says what to install); 128 + the
    signal's number when a stop signal ended a run after it saved its checkpoint (130 Ctrl-C,
    143 SIGTERM, 129 SIGHUP)."""
    from gdbench.core.io import FolderBusy
    from gdbench.core.signals import RunInterrupted
    from gdbench.train.update import TrainingDiverged

    if isinstance(e, RunInterrupted):
        return str(e), e.exit_code
    if isinstance(e, TrainingDiverged):  # its message says what to try
        return str(e), 2
    if isinstance(e, KeyboardInterrupt):
        signum = getattr(e, "signum", signal.SIGINT)
        return f"interrupted by {signal.Signals(signum).name}", 128 + signum
    if isinstance(e, (ValueError, FolderBusy, FileNotFoundError, FileExistsError, NotADirectoryError)):
        return str(e), 2
    if isinstance(e, ImportError) and "pip install" in str(e):  # an optional part, and what installs it
        return str(e), 2
    if isinstance(e, OSError):  # read-only file system, permission, disk full, ...
        where = f"{e.filename}: " if e.filename else ""
        return f"{where}{e.strerror or e}", 2
    raise e


def run_reporting(name: str, work) -> None:
    """``work()`` under ``install_stop_handlers``; an error a user can act on, or a stop signal,
    ends the process with one line (``gdbench <name>: error: ...``) and its exit code
    (``error_line``). The signal handlers it found are given back when it ends (a caller that
    catches the SystemExit, such as a test, keeps its own)."""
    import os
    import sys

    stops = [getattr(signal, s) for s in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, s)]
    saved = {s: signal.getsignal(s) for s in stops}
    try:
        try:
            from gdbench.core.signals import install_stop_handlers

            install_stop_handlers()  # inside the try: a signal from here on is reported in one line
            work()
        except (Exception, KeyboardInterrupt) as e:
            for s in stops:  # a second signal must not cut the one line short
                signal.signal(s, signal.SIG_IGN)
            if os.environ.get("GDBENCH_DEBUG"):
                raise
            message, code = error_line(e)
            print(f"gdbench {name}: error: {message}", file=sys.stderr)
            sys.exit(code)
    finally:
        for s, handler in saved.items():
            signal.signal(s, handler)


def _config_arg(argv: list[str]) -> tuple[Path, list[str]] | None:
    """(--config's path, the other arguments after the subcommand) when ``argv`` has --config;
    given twice, a ValueError."""
    rest = argv[1:]
    found = [i for i, a in enumerate(rest) if a == "--config" or a.startswith("--config=")]
    if len(found) > 1:
        raise ValueError("config: given more than once; expected one grid file")
    if not found:
        return None
    i = found[0]
    if rest[i].startswith("--config="):
        return Path(rest[i].split("=", 1)[1]), rest[:i] + rest[i + 1 :]
    if i + 1 < len(rest):
        return Path(rest[i + 1]), rest[:i] + rest[i + 2 :]
    return None  # tyro names the missing value


def entrypoint() -> None:
    """Parse the command line and run it. Bad arguments, missing or broken files and unwritable
    folders end with a one-line error naming what to fix and exit code 2. A stop signal (Ctrl-C,
    SIGTERM, SIGHUP) ends the command with one line and exit code 128 + its number; during
    training, after the step it lands in and a checkpoint. Set GDBENCH_DEBUG=1 for the traceback."""
    import sys

    argv = sys.argv[1:]
    if hasattr(sys.stdout, "reconfigure"):  # piped to a file: each line as it is printed
        sys.stdout.reconfigure(line_buffering=True)
    try:
        config = _config_arg(argv) if argv[:1] == ["sweep"] else None
    except ValueError as e:
        print(f"gdbench sweep: error: {e}", file=sys.stderr)
        sys.exit(2)
    prior = None
    if argv[:1] in (["generate"], ["sweep"]):
        try:
            prior = chosen_prior(argv)
            check_presets(argv)
        except ValueError as e:
            print(f"gdbench {argv[0]}: error: {e}", file=sys.stderr)
            sys.exit(2)
    try:
        check_up_axes(argv)
    except ValueError as e:
        print(f"gdbench {argv[0]}: error: {e}", file=sys.stderr)
        sys.exit(2)
    if config is not None:  # the file's options become the defaults the command line overrides

        def with_config() -> None:  # read under run_reporting: a bad file is one line, as any error
            path, rest = config
            default = sweep_from_mapping(load_mapping(path), what=f"config ({path})", prior=prior)
            cmd = tyro.cli(type(default), default=default, args=rest, prog="gdbench sweep")
            cmd.config = path
            main(cmd)

        run_reporting("sweep", with_config)
        return
    cmd = tyro.extras.subcommand_cli_from_dict({name: command(name, prior or "empirical") for name in COMMANDS})
    name = next(n for n, (kind, _) in COMMANDS.items() if isinstance(cmd, kind))
    run_reporting(name, lambda: main(cmd))


def command(name: str, prior: str = "empirical") -> type:
    """The options class of subcommand ``name``; generate's and sweep's with ``prior``'s options."""
    if name == "generate":
        return generate_command(prior)
    if name == "sweep":
        return sweep_command(prior)
    return COMMANDS[name][0]


def _option_value(rest: list[str], flag: str) -> str | None:
    """The last value ``flag`` is given on a command line (``--flag V`` or ``--flag=V``), before
    any ``--``; None when it is not given."""
    value = None
    for i, a in enumerate(rest):
        if a == "--":
            break
        if a.startswith(flag + "="):
            value = a.split("=", 1)[1]
        elif a == flag and i + 1 < len(rest):
            value = rest[i + 1]
    return value


def check_presets(argv: list[str]) -> None:
    """A ValueError naming --preset and the known presets when a generate command line's --preset
    is not one (the parser's own message lists 'None' among them, the value that means "not
    given"; a sweep's --presets are checked by ``SweepConfig``)."""
    from gdbench.train.config import PRESETS

    if argv[:1] != ["generate"]:
        return
    given = _option_value(argv[1:], "--preset")
    if given is not None and given not in PRESETS:
        raise ValueError(f"--preset: unknown preset {given!r}; expected one of {', '.join(PRESETS)}")


def check_up_axes(argv: list[str]) -> None:
    """A ValueError naming the flag and the six axes when render's, view's or export's --up (or
    export's --src-up) is not one (the parser's message lists 'None' among them, in no fixed order)."""
    from gdbench.core.filetags import UP_AXES

    if argv[:1] not in (["render"], ["view"], ["export"]):
        return
    for flag in ("--up", "--src-up"):
        given = _option_value(argv[1:], flag)
        if given is not None and given not in UP_AXES:
            raise ValueError(f"{flag}: unknown axis {given!r}; expected one of {', '.join(UP_AXES)}")


def chosen_prior(argv: list[str]) -> str:
    """The --prior of a generate or sweep command line (``argv`` from the subcommand on): given,
    else the one its --config file names, else 'empirical'; a bad name is left to the parser. A
    prior's option typed for another prior is a ValueError naming the prior it needs."""
    from gdbench.train.config import prior_option_error

    rest = argv[1:]
    kind = _option_value(rest, "--prior")
    if kind is None:
        kind = _file_prior(argv)
    kind = kind if kind in PRIOR_CONFIGS else "empirical"
    for a in rest:
        if a == "--":
            break
        name = a.split("=", 1)[0].removeprefix("--").removeprefix("no-").replace("-", "_")
        message = prior_option_error(f"prior.{name}", kind, a.split("=", 1)[0]) if a.startswith("--") else None
        if message is not None:
            raise ValueError(message)
    return kind


def _file_prior(argv: list[str]) -> str | None:
    """The prior a generate or sweep --config file names (a run.json's config, a settings file,
    a sweep's overrides), or None; a file that cannot be read is left to the command to report."""
    try:
        found = _config_arg(argv)
        if found is None:
            return None
        d = load_mapping(found[0])
    except Exception:  # (the command reads the file again and names what is wrong)
        return None
    d = d.get("config", d) if "run_id" in d else d
    d = d.get("overrides", d) if argv[0] == "sweep" else d
    prior = d.get("prior") if isinstance(d, dict) else None
    prior = prior.get("kind") if isinstance(prior, dict) else prior
    return prior if isinstance(prior, str) else None


def program() -> None:
    """The ``gdbench`` command and ``python -m gdbench.app.cli``: ``entrypoint``, then the process
    ends without Python's teardown of its modules, most of the exit's time once torch is imported
    (docs/log/2026-11-26_cell_cost.md, "The command's exit"). What an exit owes still happens,
    in the order Python does it: ``threading._shutdown``
    (executors' exit hooks, then the threads that are not daemons joined), the exit handlers
    (logging's flush, the finalizers of temporary folders, multiprocessing), both streams flushed
    (a failed flush exits 120, as Python does), and the exit code is the one ``sys.exit`` gives.
    An error that escapes (``GDBENCH_DEBUG=1``) takes Python's own way out, traceback and all."""
    import os
    import sys

    from gdbench.core.private import run_exit_functions, shutdown_threads

    try:
        entrypoint()
        code = 0
    except SystemExit as e:
        code = exit_code(e.code)
    shutdown_threads()  # Python's own first step: wakes executors' workers, joins non-daemon threads
    run_exit_functions()
    for stream in (sys.stdout, sys.stderr, sys.__stdout__, sys.__stderr__):
        try:
            if stream is not None:
                stream.flush()
        except Exception:
            code = code or 120  # as Python does when its streams cannot be flushed at exit
    os._exit(code)


def exit_code(code) -> int:
    """The exit status ``SystemExit(code)`` gives a Python process: None is 0, an integer itself,
    anything else is written to standard error and gives 1."""
    import sys

    if code is None:
        return 0
    if isinstance(code, int):
        return code
    print(code, file=sys.stderr)
    return 1


if __name__ == "__main__":
    program()
