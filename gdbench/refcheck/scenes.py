"""Fixture scenes for the reference comparisons: small scenes with declared needs.

Each scene is a JSON file in ``fixtures/scenes/`` naming a generator (a function below, in
the explicit ``GENERATORS`` dict), its arguments, the cameras, the outputs it needs, and per
reference renderer either tolerances or the reason it does not apply. ``load_fixture`` returns
the scene, the cameras and the spec; everything is deterministic.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path

import torch

from gdbench.core.camera import Cameras, SphericalPoses, intrinsics, look_at
from gdbench.core.scene import GaussianScene

FIXTURE_DIR = Path(__file__).resolve().parents[2] / "fixtures" / "scenes"


def _one(mean, scale, opacity, color, quat=(1.0, 0.0, 0.0, 0.0)) -> GaussianScene:
    t = lambda x: torch.tensor([x], dtype=torch.float32)  # noqa: E731
    return GaussianScene.from_activated(t(mean), t(scale), torch.tensor([opacity]), t(color), quats=t(quat))


def isotropic(scale: float = 0.1, opacity: float = 0.8, color=(0.9, 0.4, 0.1)) -> GaussianScene:
    return _one([0.0, 0.0, 0.0], [scale] * 3, opacity, color)


def anisotropic(scales=(0.25, 0.06, 0.03), opacity: float = 0.9, axis_angle=(0.4, 0.7, 0.2, 50.0)) -> GaussianScene:
    ax = torch.tensor(axis_angle[:3], dtype=torch.float64)
    ax = ax / ax.norm()
    h = math.radians(axis_angle[3]) / 2
    q = [math.cos(h), *(math.sin(h) * ax).tolist()]
    return _one([0.0, 0.0, 0.0], list(scales), opacity, [0.2, 0.5, 0.9], quat=q)


def crossing(opacity: float = 0.7, angle_deg: float = 30.0, offset: float = 0.01) -> GaussianScene:
    """Two thin discs through the Z axis, turned by +-angle about it, centres 2 x ``offset`` apart
    along X. Seen from +X, disc a's centre is nearer everywhere, but over half of the image disc b
    is physically in front: per-Gaussian depth sorting (splatting) gets that half wrong, ray
    tracing does not. The centres never tie in depth."""
    h = math.radians(angle_deg) / 2
    a = _one([offset, 0.0, 0.0], [0.01, 0.25, 0.25], opacity, [0.9, 0.1, 0.1], quat=[math.cos(h), 0, 0, math.sin(h)])
    b = _one([-offset, 0.0, 0.0], [0.01, 0.25, 0.25], opacity, [0.1, 0.2, 0.9], quat=[math.cos(h), 0, 0, -math.sin(h)])
    return GaussianScene.cat([a, b])


def near_wide(distance: float = 0.35, offset: float = 0.5) -> GaussianScene:
    """A Gaussian close to the camera and far off-axis (viewed with a wide field of view)."""
    return _one([offset, 0.0, 0.0], [0.06, 0.06, 0.06], 0.9, [0.3, 0.8, 0.3])


def random_cloud(n: int = 10000, seed: int = 0, radius: float = 0.5) -> GaussianScene:
    from gdbench.bench.common import random_cloud as rc

    c = rc(n, seed=seed, radius=radius)
    return GaussianScene.from_activated(c["means"], c["scales"], c["opacities"], c["colors"], quats=c["quats"])


def subpixel(n: int = 3000, seed: int = 1, scale: float = 0.0015) -> GaussianScene:
    """Many Gaussians far smaller than a pixel: aliasing, and the eps2d low-pass at work."""
    g = torch.Generator().manual_seed(seed)
    means = (torch.rand(n, 3, generator=g) - 0.5) * 0.8
    return GaussianScene.from_activated(
        means, torch.full((n, 3), scale), torch.full((n,), 0.9), torch.rand(n, 3, generator=g)
    )


def procedural(n: int = 2000, seed: int = 0) -> GaussianScene:
    from gdbench.core.builtin import demo_scene

    return demo_scene(n, seed=seed)


GENERATORS = {
    "isotropic": isotropic,
    "anisotropic": anisotropic,
    "crossing": crossing,
    "near_wide": near_wide,
    "random_cloud": random_cloud,
    "subpixel": subpixel,
    "procedural": procedural,
}


@dataclass(frozen=True)
class Fixture:
    name: str
    spec: dict
    scene: GaussianScene
    cameras: Cameras

    @property
    def tolerances(self) -> dict:
        """{class: tolerance.Tolerance or the reason it does not apply}, checked at load."""
        from gdbench.refcheck.tolerance import parse_tolerances

        return parse_tolerances(self.spec.get("tolerances"), f"fixture {self.name!r}")

    def tolerance(self, reference: str) -> dict | None:
        """{"mean_abs": .., "max_abs": ..} for an applicable reference, else None; a reference
        declared as ``{"class": c}`` takes the image tolerance of the scene's class c."""
        r = self.spec.get("references", {}).get(reference)
        if isinstance(r, dict) and "class" in r:
            t = self.tolerances.get(r["class"])
            if t is None or isinstance(t, str):
                raise ValueError(f"fixture {self.name!r}: reference {reference!r} names class {r['class']!r}, "
                                 f"which the scene does not state")  # fmt: skip
            return {"mean_abs": t.mean_abs, "max_abs": t.max_abs}
        return r if isinstance(r, dict) else None

    def skip_reason(self, reference: str) -> str | None:
        r = self.spec.get("references", {}).get(reference)
        if r is None:
            return f"scene '{self.name}' does not declare reference '{reference}'"
        return r if isinstance(r, str) else None

    @property
    def background(self) -> torch.Tensor:
        return torch.tensor(self.spec.get("background", [1.0, 1.0, 1.0]), dtype=torch.float32)


def _cameras(spec: dict) -> Cameras:
    size = spec["size"]
    w, h = (size, size) if isinstance(size, int) else size
    if "look_at" in spec:
        eyes = torch.tensor(spec["look_at"]["eyes"], dtype=torch.float64)
        targets = torch.tensor(spec["look_at"].get("targets", [[0.0, 0.0, 0.0]] * len(eyes)), dtype=torch.float64)
        fov = torch.full((len(eyes),), float(spec["fovy"]))
        return Cameras(look_at(eyes, targets).float(), intrinsics(fov, w, h), w, h)
    n = spec.get("orbit", 4)
    return SphericalPoses.orbit(
        n,
        radius=spec.get("radius", 1.5),
        elevation=spec.get("elevation", 20.0),
        fovy=spec.get("fovy", 50.0),
        start=spec.get("start", 10.0),
    ).cameras(w, h)


def fixture_names() -> list[str]:
    return sorted(p.stem for p in FIXTURE_DIR.glob("*.json"))


def load_fixture(name: str) -> Fixture:
    path = FIXTURE_DIR / f"{name}.json"
    if not path.is_file():
        raise ValueError(f"scene: no fixture named {name!r}; known: {fixture_names()}")
    spec = json.loads(path.read_text())
    gen = spec["generator"]
    if gen["name"] not in GENERATORS:
        raise ValueError(f"{path}: unknown generator {gen['name']!r}; known: {sorted(GENERATORS)}")
    scene = GENERATORS[gen["name"]](**gen.get("args", {}))
    fx = Fixture(name, spec, scene.with_sh_degree(spec.get("sh_degree", 0)), _cameras(spec["cameras"]))
    assert fx.tolerances  # a missing or malformed tolerance raises at load, not a silent pass
    return fx
