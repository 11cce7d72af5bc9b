"""Built-in procedural scenes made of Gaussians (no data files needed).

``demo_scene``: a hue-striped torus around a checkered ball, about 0.45 in radius,
built of flat Gaussians lying in the surfaces (anisotropic, rotated, opaque), so that
the turntable exercises rotations, anisotropy, sorting and occlusion.
"""

from __future__ import annotations

import math

import torch

from gdbench.core.scene import GaussianScene


def _hsv(h: torch.Tensor, s: float = 0.75, v: float = 0.95) -> torch.Tensor:
    k = torch.stack([(5 + h * 6) % 6, (3 + h * 6) % 6, (1 + h * 6) % 6], -1)
    return v - v * s * torch.clamp(torch.minimum(k, 4 - k), 0, 1)


def _frame_quats(normal: torch.Tensor, tangent: torch.Tensor) -> torch.Tensor:
    """wxyz quaternions of rotations whose columns are (tangent, bitangent, normal)."""
    from gdbench.core.camera import rotmat_to_quat

    b = torch.linalg.cross(normal, tangent)
    R = torch.stack([tangent, b, normal], dim=-1).double()
    return torch.stack([rotmat_to_quat(r) for r in R]).float()


def demo_scene(n: int = 3000, *, seed: int = 0) -> GaussianScene:
    """The demo torus-and-ball scene with about ``n`` Gaussians (deterministic for a seed)."""
    if n < 10:
        raise ValueError(f"n: expected at least 10 Gaussians, got {n}")
    g = torch.Generator().manual_seed(seed)
    n_torus = int(0.65 * n)
    n_ball = n - n_torus
    R0, r0 = 0.32, 0.09
    u = 2 * math.pi * torch.rand(n_torus, generator=g)
    v = 2 * math.pi * torch.rand(n_torus, generator=g)
    ring = torch.stack([torch.cos(u), torch.sin(u), torch.zeros_like(u)], -1)
    normal_t = torch.cos(v)[:, None] * ring + torch.sin(v)[:, None] * torch.tensor([0.0, 0.0, 1.0])
    pos_t = R0 * ring + r0 * normal_t
    tangent_t = torch.stack([-torch.sin(u), torch.cos(u), torch.zeros_like(u)], -1)
    col_t = _hsv((u / (2 * math.pi) * 3) % 1.0)
    col_t = col_t * (0.75 + 0.25 * (torch.sin(6 * v) > 0).float())[:, None]

    normal_b = torch.nn.functional.normalize(torch.randn(n_ball, 3, generator=g), dim=-1)
    pos_b = 0.16 * normal_b
    helper = torch.where(normal_b[:, 2:3].abs() < 0.9, torch.tensor([0.0, 0.0, 1.0]), torch.tensor([1.0, 0.0, 0.0]))
    tangent_b = torch.nn.functional.normalize(torch.linalg.cross(helper, normal_b), dim=-1)
    theta = torch.atan2(normal_b[:, 1], normal_b[:, 0])
    phi = torch.asin(normal_b[:, 2].clamp(-1, 1))
    checker = ((torch.floor(theta / (math.pi / 4)) + torch.floor(phi / (math.pi / 6))) % 2)[:, None]
    col_b = checker * torch.tensor([0.95, 0.95, 0.9]) + (1 - checker) * torch.tensor([0.15, 0.2, 0.6])

    means = torch.cat([pos_t, pos_b])
    normals = torch.cat([normal_t, normal_b])
    tangents = torch.cat([tangent_t, tangent_b])
    spacing_t = math.sqrt(4 * math.pi**2 * R0 * r0 / n_torus)
    spacing_b = math.sqrt(4 * math.pi * 0.16**2 / n_ball)
    s_in = torch.cat([torch.full((n_torus,), spacing_t), torch.full((n_ball,), spacing_b)])
    scales = torch.stack([0.9 * s_in, 0.9 * s_in, 0.08 * s_in], -1)
    return GaussianScene.from_activated(
        means,
        scales,
        torch.full((n,), 0.9),
        torch.cat([col_t, col_b]).clamp(0, 1),
        quats=_frame_quats(normals, tangents),
    )
