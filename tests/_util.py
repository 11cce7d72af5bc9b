"""Shared builders for the tests: random scenes and cameras with explicit generators."""

from __future__ import annotations

import pytest
import torch

from gdbench.camera import Cameras, intrinsics, look_at

TEST_DEVICE = torch.device("cpu")
"""Where the renderer tests render: pytest's ``--device`` (tests/conftest.py sets it)."""


def on_test_device(fn):
    """``fn`` (``rasterize``'s signature) on TEST_DEVICE copies of its tensors, its outputs back on
    the CPU; the copies are in the graph, so gradients reach the CPU inputs and the tests compare
    with the same CPU oracles. On the CPU, ``fn`` itself."""

    def wrapped(*args, **kwargs):
        if TEST_DEVICE.type == "cpu":
            return fn(*args, **kwargs)
        move = lambda x: x.to(TEST_DEVICE) if isinstance(x, torch.Tensor) and x.device.type == "cpu" else x  # noqa: E731
        out = fn(*map(move, args), **{k: move(v) for k, v in kwargs.items()})
        return type(out)(*(x.cpu() if isinstance(x, torch.Tensor) else x for x in out))

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
    from gdbench.builtin import demo_scene
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
from tests.test_train import tiny, CAPTION
from tests._util import tiny_bank
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
