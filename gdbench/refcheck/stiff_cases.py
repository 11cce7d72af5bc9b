"""The stiff and extreme cases of the stability benchmark and of conformance: each a small scene and
one camera, built in float64 (their tolerances: fixtures/stability_tolerances.json)."""

from __future__ import annotations

import math
from collections.abc import Callable

import torch

F64 = torch.float64
C0 = 0.28209479177387814
"""The SH degree-0 basis constant (rgb = 0.5 + C0 * c): a case's RGB colours as coefficients."""


def _gaussians(means, scales, quats=None, opacity=0.8, colors=None) -> dict[str, torch.Tensor]:
    means = torch.as_tensor(means, dtype=F64).reshape(-1, 3)
    n = means.shape[0]
    sc = torch.as_tensor(scales, dtype=F64)
    q = torch.as_tensor((1.0, 0.0, 0.0, 0.0) if quats is None else quats, dtype=F64)
    op = torch.as_tensor(opacity, dtype=F64)
    col = torch.tensor([0.9, 0.5, 0.1], dtype=F64) if colors is None else torch.as_tensor(colors, dtype=F64)
    return {
        "means": means.clone(),
        "quats": q.expand(n, 4).clone() if q.dim() == 1 else q.clone(),
        "scales": sc.expand(n, 3).clone() if sc.dim() <= 1 else sc.clone(),
        "opacities": op.expand(n).clone() if op.dim() == 0 else op.clone(),
        "colors": col.expand(n, 3).clone() if col.dim() == 1 else col.clone(),
    }


def _camera(width: int, height: int, fovy_deg: float = 60.0, viewmat=None) -> dict:
    """Pinhole camera (OpenCV axes) with the given vertical field of view; identity pose by default."""
    f = height / 2 / math.tan(math.radians(fovy_deg) / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=F64)[None]
    vm = torch.eye(4, dtype=F64)[None] if viewmat is None else torch.as_tensor(viewmat, dtype=F64)[None]
    return {"viewmats": vm, "Ks": K, "width": width, "height": height}


def _cloud(n: int, seed: int = 0, spread: float = 0.3, z: float = 2.0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * spread
    means[:, 2] += z
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=F64),
        "scales": 0.01 + 0.08 * torch.rand(n, 3, generator=g, dtype=F64),
        "opacities": 0.05 + 0.95 * torch.rand(n, generator=g, dtype=F64),
        "colors": torch.rand(n, 3, generator=g, dtype=F64),
    }


def _edge_on_view(tilt_deg: float) -> torch.Tensor:
    """A camera at (0, -2, 0) looking at the origin along +y, tilted by ``tilt_deg`` about x: a disc
    in the z = 0 plane at the origin is seen edge-on (0) or nearly so."""
    t = math.radians(tilt_deg)
    # camera axes in world coordinates (OpenCV: x right, y down, z forward)
    fwd = torch.tensor([0.0, math.cos(t), math.sin(t)], dtype=F64)
    right = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])  # world -> camera rotation
    c = -2.0 * fwd
    vm = torch.eye(4, dtype=F64)
    vm[:3, :3], vm[:3, 3] = R, -R @ c
    return vm


def cases() -> dict[str, Callable[[], tuple[dict, dict]]]:
    """name -> () -> (gaussians, camera). The foundation issue's list and more."""
    rot = (0.8, 0.4, 0.3, 0.2)

    def huge_n_one_pixel():
        g = torch.Generator().manual_seed(0)
        gs = _gaussians([[0.0, 0.0, 2.0]] * 10_000, 0.2, opacity=0.5)
        gs["means"][:, 2] = 1.0 + torch.rand(10_000, generator=g, dtype=F64) * 3
        return gs, _camera(1, 1)

    return {
        "behind the camera": lambda: (_gaussians([0, 0, -1.0], 0.2), _camera(32, 32)),
        "on the near plane (z=0.0102)": lambda: (_gaussians([0, 0, 0.0102], 1e-4), _camera(32, 32)),
        "camera inside a Gaussian": lambda: (_gaussians([0, 0, 0.3], [1.0, 0.6, 0.8]), _camera(32, 32)),
        "tiny scale 1e-8": lambda: (_gaussians([0, 0, 2.0], 1e-8), _camera(32, 32)),
        "huge scale 1e4": lambda: (_gaussians([0, 0, 2.0], 1e4), _camera(32, 32)),
        "condition number 1e8": lambda: (_gaussians([0, 0, 2.0], [0.3, 3e-5, 0.2], rot), _camera(48, 48)),
        "anisotropy 1e6": lambda: (_gaussians([0, 0, 2.0], [0.3, 3e-7, 0.3], rot), _camera(48, 48)),
        "zero quaternion": lambda: (_gaussians([0, 0, 2.0], [0.3, 0.1, 0.05], (0.0, 0.0, 0.0, 0.0)), _camera(32, 32)),
        "opacity 1 - 1e-7": lambda: (_gaussians([0, 0, 2.0], 0.2, opacity=1 - 1e-7), _camera(33, 33)),
        "opacity 1e-7": lambda: (_gaussians([0, 0, 2.0], 0.2, opacity=1e-7), _camera(33, 33)),
        "empty scene": lambda: ({k: v[:0] for k, v in _gaussians([0, 0, 2.0], 0.1).items()}, _camera(16, 16)),
        "10k Gaussians on one pixel": huge_n_one_pixel,
        "grazing view: disc edge-on": lambda: (
            _gaussians([0, 0, 0], [0.3, 0.3, 1e-4]),
            _camera(48, 48, 40.0, _edge_on_view(0.0)),
        ),
        "grazing view: disc at 0.5 deg": lambda: (
            _gaussians([0, 0, 0], [0.3, 0.3, 1e-4]),
            _camera(48, 48, 40.0, _edge_on_view(0.5)),
        ),
        "fovy 1 deg": lambda: (_cloud(200, spread=0.01), _camera(48, 48, 1.0)),
        "fovy 170 deg": lambda: (_cloud(500, spread=1.0), _camera(64, 64, 170.0)),
        "image 4096 x 1": lambda: (_cloud(60, spread=0.05), _camera(4096, 1, 0.05)),
    }
