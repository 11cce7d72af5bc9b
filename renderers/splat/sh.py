"""Real spherical harmonics in the convention of the original 3DGS code.

Colour of a Gaussian seen along unit direction ``d`` (from the camera centre to the
Gaussian mean) is ``max(0, sum_k Y_k(d) f_k + 0.5)`` with the basis ``Y_k`` below,
``K = (degree + 1)^2`` coefficients per channel. Degree 0 is a plain colour:
``c = C0 * f_dc + 0.5``. The basis is orthonormal on the unit sphere (tested).
"""

from __future__ import annotations

import torch
from jaxtyping import Float
from torch import Tensor

C0 = 0.28209479177387814
C1 = 0.4886025119029199
C2 = (1.0925484305920792, -1.0925484305920792, 0.31539156525252005, -1.0925484305920792, 0.5462742152960396)
C3 = (
    -0.5900435899266435,
    2.890611442640554,
    -0.4570457994644658,
    0.3731763325901154,
    -0.4570457994644658,
    1.445305721320277,
    -0.5900435899266435,
)


def num_sh_bases(degree: int) -> int:
    """K = (degree + 1)^2."""
    return (degree + 1) ** 2


def sh_basis(degree: int, dirs: Float[Tensor, "*B 3"]) -> Float[Tensor, "*B K"]:
    """Evaluate the K = (degree+1)^2 real SH basis functions at unit directions."""
    if degree not in (0, 1, 2, 3):
        raise ValueError(f"degree: expected 0, 1, 2 or 3, got {degree}")
    x, y, z = dirs.unbind(-1)
    out = [x.new_full(x.shape, C0)]
    if degree >= 1:
        out += [-C1 * y, C1 * z, -C1 * x]
    if degree >= 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [
            C2[0] * x * y,
            C2[1] * y * z,
            C2[2] * (2.0 * zz - xx - yy),
            C2[3] * x * z,
            C2[4] * (xx - yy),
        ]
    if degree >= 3:
        out += [
            C3[0] * y * (3.0 * xx - yy),
            C3[1] * x * y * z,
            C3[2] * y * (4.0 * zz - xx - yy),
            C3[3] * z * (2.0 * zz - 3.0 * xx - 3.0 * yy),
            C3[4] * x * (4.0 * zz - xx - yy),
            C3[5] * z * (xx - yy),
            C3[6] * x * (xx - 3.0 * yy),
        ]
    return torch.stack(out, dim=-1)


def eval_sh(degree: int, coeffs: Float[Tensor, "*B K D"], dirs: Float[Tensor, "*B 3"]) -> Float[Tensor, "*B D"]:
    """Colour from SH coefficients: ``max(0, sum_k Y_k(d) f_k + 0.5)`` for unit ``dirs``.

    Only the first (degree+1)^2 of the K coefficients are used.
    """
    k = num_sh_bases(degree)
    basis = sh_basis(degree, dirs)
    return ((basis[..., None] * coeffs[..., :k, :]).sum(-2) + 0.5).clamp_min(0.0)


def rgb_to_sh0(rgb: Tensor) -> Tensor:
    """Degree-0 coefficient that evaluates to ``rgb`` (inverse of ``sh0_to_rgb``)."""
    return (rgb - 0.5) / C0


def sh0_to_rgb(sh0: Tensor) -> Tensor:
    return sh0 * C0 + 0.5
