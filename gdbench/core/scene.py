"""``GaussianScene``: the typed container of a 3D Gaussian splatting scene.

Stored (optimisable) parameters, in the 3DGS conventions (docs/conventions.md):
means [N, 3], quats [N, 4] (wxyz, any norm), log_scales [N, 3], opacity_logits [N],
sh [N, K, 3] SH coefficients with K = (degree + 1)^2, degree 0..3 (sh[:, 0] is the DC
term: colour = C0 * sh[:, 0] + 0.5). ``scales``, ``opacities`` and ``render_args`` give the
activated values that ``renderers.splat.rasterize`` takes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, fields
from pathlib import Path

import torch
from torch import Tensor

from gdbench.core.ply import FIELDS, read_ply, write_ply
from renderers.splat.sh import rgb_to_sh0, sh0_to_rgb

_SH_K = {1: 0, 4: 1, 9: 2, 16: 3}


@dataclass(frozen=True)
class GaussianScene:
    means: Tensor
    """[N, 3] world positions."""
    quats: Tensor
    """[N, 4] rotations, wxyz, any norm (zero means identity)."""
    log_scales: Tensor
    """[N, 3] log of the standard deviations along the rotated axes."""
    opacity_logits: Tensor
    """[N] logits of the opacity."""
    sh: Tensor
    """[N, K, 3] SH coefficients, K in {1, 4, 9, 16}."""

    def __post_init__(self) -> None:
        for f in fields(self):
            x = getattr(self, f.name)
            if not isinstance(x, Tensor):
                raise TypeError(f"GaussianScene.{f.name}: expected a torch.Tensor, got {type(x).__name__}")
            if x.dtype not in (torch.float32, torch.float64):
                raise TypeError(f"GaussianScene.{f.name}: expected dtype float32 or float64, got {x.dtype}")
        if self.means.dim() != 2 or self.means.shape[1] != 3:
            raise ValueError(f"GaussianScene.means: expected shape [N, 3], got {list(self.means.shape)}")
        n = self.means.shape[0]
        expected = {"quats": (n, 4), "log_scales": (n, 3), "opacity_logits": (n,)}
        for name, shape in expected.items():
            x = getattr(self, name)
            if tuple(x.shape) != shape:
                raise ValueError(f"GaussianScene.{name}: expected shape {list(shape)}, got {list(x.shape)}")
        if self.sh.dim() != 3 or self.sh.shape[0] != n or self.sh.shape[2] != 3 or self.sh.shape[1] not in _SH_K:
            raise ValueError(
                f"GaussianScene.sh: expected shape [{n}, K, 3] with K in (1, 4, 9, 16), got {list(self.sh.shape)}"
            )
        for f in fields(self):
            x = getattr(self, f.name)
            if x.device != self.means.device or x.dtype != self.means.dtype:
                raise ValueError(
                    f"GaussianScene.{f.name}: expected {self.means.dtype} on {self.means.device} like means, "
                    f"got {x.dtype} on {x.device}"
                )
            if x.numel() and not bool(torch.isfinite(x).all()):
                raise ValueError(f"GaussianScene.{f.name}: expected finite values, found NaN/Inf")

    # ----------------------------------------------------------------- construction
    @classmethod
    def from_activated(
        cls,
        means: Tensor,
        scales: Tensor,
        opacities: Tensor,
        colors: Tensor,
        quats: Tensor | None = None,
        sh_degree: int = 0,
    ) -> GaussianScene:
        """Build from linear scales, opacities in (0, 1) and plain RGB colours [N, 3]."""
        n = means.shape[0]
        if quats is None:
            quats = torch.zeros(n, 4, dtype=means.dtype, device=means.device)
            quats[:, 0] = 1.0
        k = (sh_degree + 1) ** 2
        sh = torch.zeros(n, k, 3, dtype=means.dtype, device=means.device)
        sh[:, 0] = rgb_to_sh0(colors)
        eps = torch.finfo(means.dtype).eps
        return cls(means, quats, torch.log(scales), torch.logit(opacities.clamp(eps, 1 - eps)), sh)

    @classmethod
    def cat(cls, scenes: Sequence[GaussianScene]) -> GaussianScene:
        """Concatenate scenes; SH bands are zero-padded to the highest degree."""
        if not scenes:
            raise ValueError("scenes: expected at least one GaussianScene")
        k = max(s.sh.shape[1] for s in scenes)
        padded = [torch.nn.functional.pad(s.sh, (0, 0, 0, k - s.sh.shape[1])) for s in scenes]
        return cls(
            *(
                torch.cat([getattr(s, name) for s in scenes])
                for name in ("means", "quats", "log_scales", "opacity_logits")
            ),
            torch.cat(padded),
        )

    @classmethod
    def load_ply(cls, path: str | Path) -> GaussianScene:
        """A 3DGS PLY (ours, the Inria code's, Open3D's, or a SuperSplat compressed PLY;
        ``ply.read_ply``) as a scene. Errors name the file and the problem. ``export.load_scene``
        also reads ``.splat`` files."""
        fields = read_ply(path)
        try:
            return cls(**fields)
        except ValueError as e:
            raise ValueError(f"{path}: {e}") from e

    def save_ply(self, path: str | Path, *, comments: list[str] | None = None) -> Path:
        """Write the scene as a binary 3DGS PLY, atomically (``ply.write_ply``)."""
        return write_ply({k: getattr(self, k) for k in FIELDS}, path, comments=comments)

    # -------------------------------------------------------------------- accessors
    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def sh_degree(self) -> int:
        return _SH_K[self.sh.shape[1]]

    @property
    def scales(self) -> Tensor:
        return torch.exp(self.log_scales)

    @property
    def opacities(self) -> Tensor:
        return torch.sigmoid(self.opacity_logits)

    @property
    def colors(self) -> Tensor:
        """View-independent (DC) colour [N, 3]."""
        return sh0_to_rgb(self.sh[:, 0])

    def render_args(self) -> dict[str, Tensor | int]:
        """Keyword arguments of ``renderers.splat.rasterize`` for this scene."""
        return {
            "means": self.means,
            "quats": self.quats,
            "scales": self.scales,
            "opacities": self.opacities,
            "colors": self.sh,
            "sh_degree": self.sh_degree,
        }

    def radius(self) -> float:
        """Radius of the smallest origin-centred ball holding every mean (0 if empty)."""
        return float(self.means.norm(dim=-1).max()) if len(self) else 0.0

    # -------------------------------------------------------------------- transforms
    def _map(self, fn) -> GaussianScene:
        return GaussianScene(*(fn(getattr(self, f.name)) for f in fields(self)))

    def to(self, *args, **kwargs) -> GaussianScene:
        return self._map(lambda x: x.to(*args, **kwargs))

    def detach(self) -> GaussianScene:
        return self._map(lambda x: x.detach())

    def clone(self) -> GaussianScene:
        return self._map(lambda x: x.clone())

    def subset(self, index: Tensor) -> GaussianScene:
        """Gaussians selected by a boolean mask [N] or an integer index."""
        if index.dtype == torch.bool and index.shape != (len(self),):
            raise ValueError(f"index: expected a boolean mask of shape [{len(self)}], got {list(index.shape)}")
        return self._map(lambda x: x[index])

    def with_sh_degree(self, degree: int) -> GaussianScene:
        """Same scene with SH truncated or zero-padded to ``degree``."""
        k = (degree + 1) ** 2
        sh = (
            self.sh[:, :k]
            if k <= self.sh.shape[1]
            else torch.nn.functional.pad(self.sh, (0, 0, 0, k - self.sh.shape[1]))
        )
        return GaussianScene(self.means, self.quats, self.log_scales, self.opacity_logits, sh)


def sphere_init(
    n: int = 4096,
    radius: float = 0.5,
    color: float = 0.5,
    opacity: float = 0.1,
    scale: float | None = None,
    *,
    generator: torch.Generator,
    dtype: torch.dtype = torch.float32,
) -> GaussianScene:
    """The paper's initialisation: n grey Gaussians uniform in a ball, isotropic scales.

    The default scale is the mean nearest-neighbour spacing of n points in the ball,
    ``radius * (4/3 pi / n)^(1/3)`` divided by 2.
    """
    if n < 0:
        raise ValueError(f"n: expected a non-negative count, got {n}")
    dirs = torch.nn.functional.normalize(torch.randn(n, 3, generator=generator, dtype=dtype), dim=-1)
    r = radius * torch.rand(n, 1, generator=generator, dtype=dtype) ** (1.0 / 3.0)
    s = scale if scale is not None else 0.5 * radius * (4.0 / 3.0 * math.pi / max(n, 1)) ** (1.0 / 3.0)
    return GaussianScene.from_activated(
        dirs * r,
        torch.full((n, 3), s, dtype=dtype),
        torch.full((n,), opacity, dtype=dtype),
        torch.full((n, 3), color, dtype=dtype),
    )
