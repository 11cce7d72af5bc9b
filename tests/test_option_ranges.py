"""The command line's declared option ranges (gdbench/core/constraints.py, docs/reliability.md): by
property, any value of any numeric option of a command either works or ends in one line naming
the flag, and every numeric field declares its range."""

import sys

import pytest
import torch
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from gdbench.priors.empirical import EmpiricalPrior
from tests._util import CAPTION, one_line, tiny_bank


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})


_VALUES = st.one_of(
    st.sampled_from(
        [0, -1, 1, 2, 3, 0.5, -0.5, 1e-30, 1e30, 179.9, 180, 360, float("nan"), float("inf"), -float("inf")]
    ),
    st.integers(-5, 48),
    st.floats(-1e3, 1e3, allow_nan=False),
)
"""Option values of the right kind (the parser's own errors are tyro's): small ints, so what is
valid stays cheap to run, and floats of every edge."""


def _value(v, integer: bool):
    return (
        None
        if integer and not (isinstance(v, int) or (isinstance(v, float) and v.is_integer()))
        else (int(v) if integer else v)
    )


def _numeric_flags(cls, exclude=()) -> dict[str, bool]:
    """flag -> whether it takes an int, for every numeric field of ``cls`` (from its declarations)."""
    from gdbench.core.constraints import _declared, flag

    return {flag(k): base is int for k, (base, _) in _declared(cls).items() if base is not None and k not in exclude}


@pytest.mark.parametrize("command", ["render", "demo", "noise"])
@settings(max_examples=20, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_command_options_work_or_end_in_one_line_naming_the_flag(tmp_path_factory, data, command):
    """Any value of any numeric option of `render`, `demo` and `noise` (the others small, so what
    is valid runs in a second): the command writes its output (exit 0) or ends with one line
    naming the flag (exit 2), before writing anything."""
    from gdbench.app import cli
    from gdbench.core.scene import sphere_init

    tmp = tmp_path_factory.mktemp(command)
    sphere_init(200, opacity=0.5, generator=torch.Generator().manual_seed(0)).save_ply(tmp / "s.ply")
    cls, base, output = {
        "render": (cli.Render, ["render", tmp / "s.ply", "--frames", "2", "--size", "24"], tmp / "s_turntable.gif"),
        "demo": (cli.Demo, ["demo", "--out", tmp / "d", "--frames", "2", "--size", "24", "--gaussians", "50"],
                 tmp / "d" / "turntable.gif"),
        "noise": (cli.Noise, ["noise", "--preview", "--out", tmp / "n.png", "--res", "16", "--n-gaussians", "64"],
                  tmp / "n.png"),
    }[command]  # fmt: skip
    flags = _numeric_flags(cls)
    opt = data.draw(st.sampled_from(sorted(flags)))
    v = _value(data.draw(_VALUES), flags[opt])
    assume(v is not None)
    code, err = _run_cli(cli.entrypoint, [*base, opt, v])
    if code == 0:
        assert output.is_file(), (opt, v, err)
    else:
        line = one_line(err)
        assert code == 2 and line.startswith(f"gdbench {command}: error: ") and opt in line, (opt, v, err)
        assert not output.exists()


@settings(max_examples=25, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_training_options_work_or_end_in_one_line_naming_the_flag(prior, tmp_path_factory, data, request):
    """Any value of any numeric training option of `generate` (on the test prior, 2 steps): the
    run finishes (exit 0) or ends with one line naming the flag or the file (exit 2)."""
    from gdbench.app.cli import entrypoint
    from gdbench.priors import factory
    from gdbench.priors.empirical import EmpiricalPriorConfig
    from gdbench.train.config import TrainConfig

    # the empirical prior's own options too (the default --prior; the others need a network)
    flags = _numeric_flags(TrainConfig, exclude=("steps", "resolution", "seed")) | _numeric_flags(EmpiricalPriorConfig)
    opt = data.draw(st.sampled_from(sorted(flags)))
    v = _value(data.draw(_VALUES), flags[opt])
    assume(v is not None)
    out = tmp_path_factory.mktemp("gen") / "run"
    base = ["generate", CAPTION, "--out", out, "--steps", "2", "--resolution", "16", "--init-points", "150",
            "--turntable-frames", "2", "--no-score", "--no-progress"]  # fmt: skip
    if opt in ("--fovy-range", "--azimuth-range", "--elevation-range"):
        args = [opt, v, v]
    elif opt == "--background":
        args = [opt, v, v, v]
    else:
        args = [opt, v]
    mp = pytest.MonkeyPatch()
    mp.setattr(factory, "make_prior", lambda cfg: prior)
    try:
        code, err = _run_cli(entrypoint, [*base, *args])
    finally:
        mp.undo()
    if code == 0:
        assert (out / "scene.ply").is_file(), err
    else:
        line = one_line(err)
        assert code == 2 and line.startswith("gdbench generate: error: "), (opt, v, err)
        assert opt in line or "camera" in line or "/" in line, (opt, v, line)  # the flag, or a file


def _run_cli(entrypoint, argv) -> tuple[int, str]:
    """``gdbench *argv`` in-process: (exit code, stderr)."""
    import contextlib
    import io

    err = io.StringIO()
    old = sys.argv
    sys.argv = ["gdbench", *map(str, argv)]
    code = 0
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            entrypoint()
    except SystemExit as e:
        code = e.code
    finally:
        sys.argv = old
    return code, err.getvalue()


def test_every_numeric_option_declares_its_range():
    """A numeric field of a config or a command without a declared range must be listed here as
    free (any finite value is meaningful): a new field fails until someone decides."""
    from gdbench.app import cli
    from gdbench.core.constraints import _declared
    from gdbench.mechanisms.noise import NoiseConfig
    from gdbench.train.config import TrainConfig
    from gdbench.train.densify import DensifyConfig

    free: set[tuple[str, str]] = set()  # none today: seeds too have a range (what manual_seed takes)
    missing = []
    from gdbench.priors.factory import PRIOR_CONFIGS

    for cls in (TrainConfig, DensifyConfig, NoiseConfig, *PRIOR_CONFIGS.values(), cli.Demo, cli.Noise, cli.Render,
                cli.Score, cli.SweepBase, cli.TrainPrior):  # fmt: skip
        for name, (base, rng) in _declared(cls).items():
            if base is not None and rng is None and (cls.__name__, name) not in free:
                missing.append(f"{cls.__name__}.{name}")
    assert missing == [], missing
