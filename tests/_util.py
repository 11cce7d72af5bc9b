"""Shared builders for the tests: random scenes and cameras with explicit generators."""

from __future__ import annotations

import sys

import pytest
import torch

from gdbench.core.camera import Cameras, intrinsics, look_at
from gdbench.train.config import preset
from gdbench.train.densify import DensifyConfig

TEST_DEVICE = torch.device("cpu")
"""Where the renderer tests render: pytest's ``--device`` (tests/conftest.py sets it)."""


def on_test_device(fn):
    """``fn`` (``rasterize``'s signature) on TEST_DEVICE copies of its tensors, its outputs back on
    the CPU (``refcheck.backends.on_device``): gradients reach the CPU inputs, and the tests compare
    with the same CPU oracles. On the CPU, ``fn`` itself."""
    from gdbench.refcheck.backends import on_device

    def wrapped(*args, **kwargs):
        if TEST_DEVICE.type == "cpu":
            return fn(*args, **kwargs)
        return on_device(fn, TEST_DEVICE)(*args, **kwargs)

    return wrapped


def random_gaussians(
    n: int,
    *,
    seed: int = 0,
    dtype: torch.dtype = torch.float32,
    batch: tuple[int, ...] = (),
    spread: float = 0.3,
    scale: tuple[float, float] = (0.01, 0.09),
    opacity: tuple[float, float] = (0.05, 1.0),
    d: int = 3,
    sh_degree: int | None = None,
) -> dict[str, torch.Tensor]:
    """Random anisotropic Gaussians: means ~ N(0, spread^2), random rotations and scales."""
    g = torch.Generator().manual_seed(seed)
    shape = batch + (n,)
    out = {
        "means": torch.randn(shape + (3,), generator=g, dtype=torch.float64) * spread,
        "quats": torch.randn(shape + (4,), generator=g, dtype=torch.float64),
        "scales": scale[0] + (scale[1] - scale[0]) * torch.rand(shape + (3,), generator=g, dtype=torch.float64),
        "opacities": opacity[0] + (opacity[1] - opacity[0]) * torch.rand(shape, generator=g, dtype=torch.float64),
    }
    if sh_degree is None:
        out["colors"] = torch.rand(shape + (d,), generator=g, dtype=torch.float64)
    else:
        k = (sh_degree + 1) ** 2
        out["colors"] = torch.randn(shape + (k, d), generator=g, dtype=torch.float64) * 0.4
    return {k: v.to(dtype) for k, v in out.items()}


def ring_cameras(
    c: int, width: int, height: int, *, radius: float = 1.6, fovy: float = 50.0, dtype=torch.float32, seed: int = 0
) -> Cameras:
    """C cameras looking at the origin from jittered directions around it."""
    g = torch.Generator().manual_seed(seed + 1000)
    az = torch.linspace(0, 2 * torch.pi, c + 1, dtype=torch.float64)[:-1] + 0.3 * torch.rand(
        c, generator=g, dtype=torch.float64
    )
    el = (torch.rand(c, generator=g, dtype=torch.float64) - 0.5) * 1.2
    eyes = radius * torch.stack([el.cos() * az.cos(), el.cos() * az.sin(), el.sin()], -1)
    return Cameras(look_at(eyes).to(dtype), intrinsics(torch.full((c,), fovy), width, height, dtype), width, height)


def axis_camera(z: float, f: float, width: int, height: int, dtype=torch.float64) -> tuple[torch.Tensor, torch.Tensor]:
    """A camera at the origin looking down +z (identity viewmat) with focal length f: (viewmats [1,4,4], Ks [1,3,3])."""
    del z
    vm = torch.eye(4, dtype=dtype)[None]
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=dtype)[None]
    return vm, K


def cotangent_loss(out, names, seed: int = 0) -> torch.Tensor:
    """sum_k <out_k, r_k> with fixed random cotangents r_k (STYLE rule 5)."""
    total = 0.0
    for i, name in enumerate(names):
        x = getattr(out, name)
        g = torch.Generator().manual_seed(seed + i)
        total = total + (x * torch.randn(x.shape, generator=g, dtype=torch.float64).to(x)).sum()
    return total


def tiny_bank(caption: str = "a test blob", res: int = 16, azimuths: int = 8, elevations=(0.0, 20.0)):
    """A small image bank rendered with the splat renderer from the built-in demo scene."""
    from gdbench.assets.bank import Bank, BankConfig
    from gdbench.core.builtin import demo_scene
    from renderers.splat import rasterize

    cfg = BankConfig(resolution=res, azimuths=azimuths, elevations=tuple(elevations))
    cams = cfg.poses().cameras(res, res)
    scene = demo_scene(300, seed=1)
    with torch.no_grad():
        out = rasterize(
            **scene.render_args(),
            viewmats=cams.viewmats,
            Ks=cams.Ks,
            width=res,
            height=res,
            background=torch.ones(3),
            outputs=("rgb", "alpha", "depth"),
        )
    poses = cfg.poses()
    return Bank(
        caption,
        cfg,
        out.rgb.clamp(0, 1),
        out.depth[..., 0],
        out.alpha[..., 0],
        poses.azimuth.float(),
        poses.elevation.float(),
    )


def write_failure_images(name, actual, ref, out):
    """actual | reference | |error| (normalised) of the first camera, as one PNG; returns its path."""
    import imageio.v3 as iio

    out.mkdir(parents=True, exist_ok=True)
    err = (actual - ref).abs()
    tiles = torch.cat([actual[0], ref[0], err[0] / max(float(err.max()), 1e-9)], 1)
    path = out / f"{name}_actual_reference_error.png"
    iio.imwrite(path, (tiles.clamp(0, 1) * 255).round().byte().numpy())
    return path


def require_cpp():
    """The C++ extension of renderers.splat, or a skip that says why it did not build."""
    from renderers.splat._ext import extension_status, load_extension

    ext = load_extension()
    if ext is None:
        pytest.skip(f"C++ extension unavailable: {extension_status()}")
    return ext


PACED_RUN = """
import sys, time
from tests._util import CAPTION, tiny, tiny_bank
from gdbench.priors.empirical import EmpiricalPrior
import gdbench.train.run as run
save = run.save_checkpoint
def slow_save(*a, **k):  # paced, so that a signal or a kill lands mid-run on a machine of any speed
    out = save(*a, **k)
    time.sleep(0.25)
    return out
run.save_checkpoint = slow_save
prior = EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})
"""
"""The start of a script for a separate process: the test prior, and checkpoints paced so that a
signal sent from the test lands mid-run; the script then trains (``run.train``)."""


def import_edges(*packages: str) -> dict[str, set[str]]:
    """Every module of the repository's ``packages`` and the modules of those packages it imports,
    at the top or inside a function (a lazy import counts: it runs sooner or later)."""
    import ast
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    mods = {".".join(p.relative_to(root).with_suffix("").parts).removesuffix(".__init__"): p
            for package in packages for p in (root / package).rglob("*.py")}  # fmt: skip
    edges = {}
    for name, path in mods.items():
        pkg = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = ".".join(pkg.split(".")[: len(pkg.split(".")) - node.level + 1]) if node.level else ""
                mod = ".".join(x for x in (base, node.module) if x)
                found |= {m for m in [mod, *(f"{mod}.{a.name}" for a in node.names)] if m in mods}
            elif isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name in mods}
        edges[name] = found - {name}
    return edges


CAPTION = "a test blob"
"""The caption of the tests' tiny bank (``tiny_bank``), the prompt of ``tiny`` configs."""

TINY_DENSIFY = DensifyConfig(
    start_frac=0.1, every_frac=0.2, reset_frac=1 / 3, grad_threshold=1e-6, recover_steps=0, min_every=1
)
"""A schedule that scales down to a few steps: at 9 steps, densify at 2, 4 and 6, reset at 3 and 6."""


def tiny(name="gd", tmp=None, **kw):
    base = dict(
        prompt=CAPTION,
        steps=4,
        resolution=16,
        init_points=150,
        checkpoint_every=2,
        progress=False,
        turntable_frames=2,
        densify=TINY_DENSIFY,
    )
    base |= {"noise.n_gaussians": 200, "noise.scale": 0.05}  # the preset's noise switch kept
    base.update(kw)
    if tmp is not None:
        base["out"] = tmp
    return preset(name, **base)


def cli(monkeypatch, capsys, *argv):
    """Run ``gdbench *argv`` in-process; returns (exit code, stdout, stderr)."""
    from gdbench.app.cli import entrypoint

    monkeypatch.setattr(sys, "argv", ["gdbench", *map(str, argv)])
    monkeypatch.delenv("GDBENCH_DEBUG", raising=False)
    code = 0
    try:
        entrypoint()
    except SystemExit as e:
        code = e.code
    out = capsys.readouterr()
    return code, out.out, out.err


def one_line(err: str) -> str:
    lines = [line for line in err.strip().splitlines() if line.strip()]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def help_text(name: str, prior: str = "empirical") -> str:
    """``gdbench NAME --help`` as tyro prints it, in this process (one column: tyro lays out
    two at ~200), with the commands' help as the entry point builds it (generate's and sweep's
    for ``prior``)."""
    import contextlib
    import io
    import os

    import tyro

    from gdbench.app.cli import command

    buf, columns = io.StringIO(), os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "100"
    try:
        with contextlib.redirect_stdout(buf), contextlib.suppress(SystemExit):
            tyro.cli(command(name, prior), args=["--help"], prog=f"gdbench {name}")
    finally:
        if columns is None:
            del os.environ["COLUMNS"]
        else:
            os.environ["COLUMNS"] = columns
    return buf.getvalue()


def option_helps(command: str, prior: str = "empirical") -> dict[str, str]:
    """Each option of ``gdbench COMMAND --help`` with its help text (tyro's boxed or plain layout)."""
    import re

    text = help_text(command, prior)
    helps: dict[str, str] = {}
    name = None
    for line in text.splitlines():
        body = line.rstrip()
        if body.lstrip().startswith("│"):  # the boxed layout of a terminal
            body = body.strip().strip("│").rstrip()
        m = re.match(r"\s{0,2}(--[a-z][a-z0-9-]*)", body)  # an option starts a line; help lines are indented
        if m:  # the help starts on this line after two spaces, or on the next ones
            name = m.group(1)
            parts = re.split(r"\s{2,}", body.strip(), maxsplit=1)
            helps[name] = parts[1] if len(parts) > 1 else ""
        elif name and body.startswith("      "):
            helps[name] += " " + body.strip()
        else:
            name = None
    return helps


TINY_CELL = {"resolution": 16, "init_points": 150, "checkpoint_every": 2, "turntable_frames": 2}
"""A sweep cell's overrides that train and score in seconds."""


def script(name: str):
    """scripts/<name>.py as a module (registered in sys.modules as gdbench_script_<name>, where
    dataclasses look their module up)."""
    import importlib.util
    import sys
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "scripts" / f"{name}.py"
    spec = importlib.util.spec_from_file_location(f"gdbench_script_{name}", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules.setdefault(spec.name, module)
    spec.loader.exec_module(module)
    return module


def csv_rows(path) -> list[dict]:
    """A CSV's rows as strings, as a reader of the file sees them."""
    import csv

    with open(path) as f:
        return list(csv.DictReader(f))


def strict_json(path):
    """json.loads that refuses NaN and Infinity, as browsers and strict readers do."""
    import json

    def refuse(name):
        raise ValueError(f"{path}: non-standard JSON constant {name}")

    return json.loads(path.read_text(), parse_constant=refuse)
