"""Cameras and the one place where camera conventions are converted.

Ours (docs/conventions.md): OpenCV camera frame (x right, y down, z forward), world-to-
camera ``viewmats`` [C, 4, 4], pinhole intrinsics ``Ks`` [C, 3, 3] in pixels with pixel
centres at +0.5, so ``cx = W/2`` is the image centre. World is right-handed with +Z up;
spherical poses put the eye at ``r (cos el cos az, cos el sin az, sin el)`` looking at the
origin, so azimuth 0 looks at an object's front when its front faces +X.

Converters: OpenGL/pyrender (camera-to-world with y up and z backward), Mitsuba (camera-
to-world with x left, y up, z forward, horizontal fov) and COLMAP (world-to-camera,
OpenCV axes, quaternion wxyz, PINHOLE parameters).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

_CV_TO_GL = torch.diag(torch.tensor([1.0, -1.0, -1.0, 1.0], dtype=torch.float64))


def _numpy(x) -> np.ndarray:
    return x.detach().cpu().double().numpy() if isinstance(x, Tensor) else np.asarray(x, dtype=np.float64)


def intrinsics(fovy_deg: Tensor | float, width: int, height: int, dtype=torch.float32) -> Tensor:
    """Square-pixel pinhole K [..., 3, 3] with vertical field of view ``fovy_deg`` and centred principal point."""
    # numpy float64: a handful of tiny arrays per training step, where torch's per-op dispatch
    # cost more than the maths (the same for look_at and spherical_to_eye)
    fovy = _numpy(fovy_deg)
    if bool(((fovy <= 0) | (fovy >= 180)).any()):
        raise ValueError(f"fovy_deg: expected degrees in (0, 180), got {fovy.tolist()}")
    f = 0.5 * height / np.tan(np.deg2rad(fovy) / 2)
    K = np.zeros(fovy.shape + (3, 3))
    K[..., 0, 0] = f
    K[..., 1, 1] = f
    K[..., 0, 2] = width / 2
    K[..., 1, 2] = height / 2
    K[..., 2, 2] = 1.0
    return torch.from_numpy(K).to(dtype)


def _norm(v: np.ndarray) -> np.ndarray:
    return np.sqrt((v * v).sum(-1, keepdims=True))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:  # np.cross's generality costs 60 us a call
    ax, ay, az, bx, by, bz = a[..., 0], a[..., 1], a[..., 2], b[..., 0], b[..., 1], b[..., 2]
    return np.stack([ay * bz - az * by, az * bx - ax * bz, ax * by - ay * bx], -1)


def look_at(eye: Tensor, target: Tensor | None = None, up: Tensor | None = None) -> Tensor:
    """World-to-camera OpenCV viewmats [..., 4, 4] looking from ``eye`` [..., 3] at ``target`` (default origin).

    ``up`` defaults to +Z. When the view direction is parallel to ``up`` (looking straight
    down or up) the world +Y axis is used as the up hint instead, so the result is always
    a proper rotation. Computed in float64 (no gradients); returned in ``eye``'s float dtype.
    """
    eye = torch.as_tensor(eye)
    dtype = eye.dtype if eye.is_floating_point() else torch.float32
    e = _numpy(eye)
    t = np.zeros_like(e) if target is None else np.broadcast_to(_numpy(target), e.shape)
    u = np.broadcast_to(np.array([0.0, 0.0, 1.0]) if up is None else _numpy(up), e.shape)
    fwd = t - e
    norm = _norm(fwd)
    if bool((norm < 1e-12).any()):
        raise ValueError("eye: coincides with target, the view direction is undefined")
    fwd = fwd / norm
    right = _cross(fwd, u)
    degenerate = _norm(right) < 1e-6
    right = np.where(degenerate, _cross(fwd, np.broadcast_to(np.array([0.0, 1.0, 0.0]), fwd.shape)), right)
    right = right / _norm(right)
    down = _cross(fwd, right)
    R = np.stack([right, down, fwd], axis=-2)  # rows: camera axes in world (world-to-camera)
    view = np.zeros(e.shape[:-1] + (4, 4))
    view[..., :3, :3] = R
    view[..., :3, 3] = -(R @ e[..., None])[..., 0]
    view[..., 3, 3] = 1.0
    return torch.from_numpy(view).to(dtype)


def spherical_to_eye(azimuth_deg: Tensor, elevation_deg: Tensor, radius: Tensor) -> Tensor:
    """Eye positions [..., 3] (float64) at ``radius`` in the directions of the angles (degrees)."""
    az, el = np.deg2rad(_numpy(azimuth_deg)), np.deg2rad(_numpy(elevation_deg))
    d = np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], -1)
    return torch.from_numpy(d * _numpy(radius)[..., None])


@dataclass(frozen=True)
class Cameras:
    """A batch of C pinhole cameras sharing one image size."""

    viewmats: Tensor
    """[C, 4, 4] world-to-camera, OpenCV axes."""
    Ks: Tensor
    """[C, 3, 3] intrinsics in pixels."""
    width: int
    height: int

    def __post_init__(self) -> None:
        if not isinstance(self.viewmats, Tensor) or self.viewmats.dim() != 3 or self.viewmats.shape[1:] != (4, 4):
            raise ValueError(
                f"viewmats: expected a tensor of shape [C, 4, 4], got {getattr(self.viewmats, 'shape', None)}"
            )
        c = self.viewmats.shape[0]
        if not isinstance(self.Ks, Tensor) or tuple(self.Ks.shape) != (c, 3, 3):
            raise ValueError(f"Ks: expected shape [{c}, 3, 3], got {getattr(self.Ks, 'shape', None)}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ValueError(f"{name}: expected a positive int, got {v!r}")

    def __len__(self) -> int:
        return self.viewmats.shape[0]

    def __getitem__(self, index) -> Cameras:
        v, k = self.viewmats[index], self.Ks[index]
        if v.dim() == 2:
            v, k = v[None], k[None]
        return Cameras(v, k, self.width, self.height)

    def to(self, *args, **kwargs) -> Cameras:
        return Cameras(self.viewmats.to(*args, **kwargs), self.Ks.to(*args, **kwargs), self.width, self.height)

    @classmethod
    def cat(cls, cams: list[Cameras]) -> Cameras:
        sizes = {(c.width, c.height) for c in cams}
        if len(sizes) != 1:
            raise ValueError(f"cams: expected one image size, got {sorted(sizes)}")
        return cls(torch.cat([c.viewmats for c in cams]), torch.cat([c.Ks for c in cams]), *sizes.pop())

    @classmethod
    def from_look_at(
        cls, eyes: Tensor, fovy_deg: float | Tensor, width: int, height: int, target: Tensor | None = None
    ) -> Cameras:
        eyes = torch.as_tensor(eyes, dtype=torch.float32).reshape(-1, 3)
        fov = torch.as_tensor(fovy_deg, dtype=torch.float32).expand(eyes.shape[0])
        return cls(look_at(eyes, target), intrinsics(fov, width, height), width, height)

    @property
    def centers(self) -> Tensor:
        """Camera centres in world coordinates [C, 3]."""
        R, t = self.viewmats[:, :3, :3], self.viewmats[:, :3, 3]
        return -(R.transpose(1, 2) @ t[..., None])[..., 0]

    @property
    def camtoworlds(self) -> Tensor:
        return torch.linalg.inv(self.viewmats)

    def fovy_deg(self) -> Tensor:
        return torch.rad2deg(2 * torch.atan(0.5 * self.height / self.Ks[:, 1, 1]))

    def fovx_deg(self) -> Tensor:
        return torch.rad2deg(2 * torch.atan(0.5 * self.width / self.Ks[:, 0, 0]))

    def resized(self, width: int, height: int) -> Cameras:
        """Same poses and fields of view at another resolution."""
        K = self.Ks.clone()
        K[:, 0] *= width / self.width
        K[:, 1] *= height / self.height
        return Cameras(self.viewmats, K, width, height)

    def project(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Pixel coordinates [C, P, 2] and camera z [C, P] of world points [P, 3] (pinhole, no clamp)."""
        pc = points.to(self.viewmats) @ self.viewmats[:, :3, :3].transpose(1, 2) + self.viewmats[:, None, :3, 3]
        uv = pc @ self.Ks.transpose(1, 2)
        return uv[..., :2] / uv[..., 2:3], pc[..., 2]

    # ----------------------------------------------------------------- converters
    def to_opengl(self) -> tuple[Tensor, Tensor]:
        """(camera-to-world poses [C, 4, 4] with OpenGL axes (x right, y up, z back), Ks [C, 3, 3]).

        This is the pose pyrender's ``IntrinsicsCamera(fx, fy, cx, cy)`` takes; its cx, cy
        are measured from the top-left corner like ours.
        """
        c2w = torch.linalg.inv(self.viewmats.double()) @ _CV_TO_GL
        return c2w.to(self.viewmats.dtype), self.Ks

    def to_mitsuba(self) -> list[dict]:
        """Per camera: ``to_world`` [4, 4] (Mitsuba axes: x left, y up, z forward), the
        horizontal ``fov`` in degrees and the principal point offsets as fractions of the
        image size (Mitsuba's ``principal_point_offset_x/y``): the renderer's own conversion
        (renderers never import gdbench)."""
        from renderers.mitsuba._lib import mitsuba_cameras

        return mitsuba_cameras(self.viewmats, self.Ks, self.width, self.height)

    def to_colmap(self) -> list[dict]:
        """Per camera: COLMAP's world-to-camera ``qvec`` (wxyz), ``tvec`` and PINHOLE ``params``
        (fx, fy, cx, cy). COLMAP's pixel centres are at +0.5 too, so K carries over unchanged."""
        out = []
        for i in range(len(self)):
            R = self.viewmats[i, :3, :3].double()
            out.append(
                {
                    "qvec": rotmat_to_quat(R),
                    "tvec": self.viewmats[i, :3, 3].double(),
                    "params": self.Ks[i, [0, 1, 0, 1], [0, 1, 2, 2]].double(),
                    "width": self.width,
                    "height": self.height,
                }
            )
        return out


def rotmat_to_quat(R: Tensor) -> Tensor:
    """Unit quaternion wxyz (w >= 0) of a rotation matrix [3, 3] (Shepperd's method)."""
    m = R
    tr = m[0, 0] + m[1, 1] + m[2, 2]
    cands = torch.stack([tr, m[0, 0], m[1, 1], m[2, 2]])
    k = int(torch.argmax(cands))
    if k == 0:
        s = torch.sqrt(tr + 1.0) * 2
        q = torch.stack([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    elif k == 1:
        s = torch.sqrt(1.0 + m[0, 0] - m[1, 1] - m[2, 2]) * 2
        q = torch.stack([(m[2, 1] - m[1, 2]) / s, 0.25 * s, (m[0, 1] + m[1, 0]) / s, (m[0, 2] + m[2, 0]) / s])
    elif k == 2:
        s = torch.sqrt(1.0 + m[1, 1] - m[0, 0] - m[2, 2]) * 2
        q = torch.stack([(m[0, 2] - m[2, 0]) / s, (m[0, 1] + m[1, 0]) / s, 0.25 * s, (m[1, 2] + m[2, 1]) / s])
    else:
        s = torch.sqrt(1.0 + m[2, 2] - m[0, 0] - m[1, 1]) * 2
        q = torch.stack([(m[1, 0] - m[0, 1]) / s, (m[0, 2] + m[2, 0]) / s, (m[1, 2] + m[2, 1]) / s, 0.25 * s])
    return q if q[0] >= 0 else -q


def quat_mul(a: Tensor, b: Tensor) -> Tensor:
    """Hamilton product a b of wxyz quaternions [..., 4] (the rotation of a after b)."""
    w1, x1, y1, z1 = a.unbind(-1)
    w2, x2, y2, z2 = b.unbind(-1)
    return torch.stack(
        [
            w1 * w2 - x1 * x2 - y1 * y2 - z1 * z2,
            w1 * x2 + x1 * w2 + y1 * z2 - z1 * y2,
            w1 * y2 - x1 * z2 + y1 * w2 + z1 * x2,
            w1 * z2 + x1 * y2 - y1 * x2 + z1 * w2,
        ],
        dim=-1,
    )


def _fold(x: Tensor, lo: float, hi: float) -> Tensor:
    """``x`` reflected at ``lo`` and ``hi`` until it lies in [lo, hi] (a triangle wave)."""
    if hi <= lo:
        return torch.full_like(x, lo)
    t = (x - lo) % (2 * (hi - lo))
    return lo + torch.where(t > hi - lo, 2 * (hi - lo) - t, t)


@dataclass(frozen=True)
class SphericalPoses:
    """Cameras on spheres around the origin, described by angles (degrees) and radius."""

    azimuth: Tensor
    """[C] degrees, 0 = looking from +X."""
    elevation: Tensor
    """[C] degrees above the XY plane."""
    radius: Tensor
    """[C] distance to the origin."""
    fovy: Tensor
    """[C] vertical field of view, degrees."""

    def __len__(self) -> int:
        return self.azimuth.shape[0]

    def cameras(self, width: int, height: int) -> Cameras:
        """Cameras looking at the origin with up +Z (``look_at`` of the eyes). Below 89 degrees of
        elevation in closed form from the angles (the trainer's per-step cameras: a dozen array
        operations instead of ~60; equal to ``look_at``'s to 1e-15, tests/test_camera.py)."""
        el = _numpy(self.elevation)
        if el.size == 0 or np.abs(el).max() >= 89.0:
            eyes = spherical_to_eye(self.azimuth.double(), self.elevation.double(), self.radius.double())
            return Cameras(look_at(eyes).float(), intrinsics(self.fovy, width, height), width, height)
        az, el = np.deg2rad(_numpy(self.azimuth)), np.deg2rad(el)
        ca, sa, ce, se = np.cos(az), np.sin(az), np.cos(el), np.sin(el)
        view = np.zeros(az.shape + (4, 4))
        # rows: right = fwd x up / |.| = (-sin az, cos az, 0); down = fwd x right; fwd = -eye / |eye|;
        # the eye lies on -fwd at distance r, so the translation -R eye is (0, 0, r)
        view[:, 0, 0], view[:, 0, 1] = -sa, ca
        view[:, 1, 0], view[:, 1, 1], view[:, 1, 2] = se * ca, se * sa, -ce
        view[:, 2, 0], view[:, 2, 1], view[:, 2, 2] = -ce * ca, -ce * sa, -se
        view[:, 2, 3], view[:, 3, 3] = _numpy(self.radius), 1.0
        return Cameras(torch.from_numpy(view).float(), intrinsics(self.fovy, width, height), width, height)

    @classmethod
    def sample(
        cls,
        n: int,
        *,
        generator: torch.Generator,
        radius: float | tuple[float, float] = 1.0,
        fovy_range: tuple[float, float] = (40.0, 70.0),
        azimuth_range: tuple[float, float] = (-180.0, 180.0),
        elevation_range: tuple[float, float] = (-45.0, 45.0),
        spread_deg: float | None = None,
    ) -> SphericalPoses:
        """The paper's random training poses: each quantity uniform in its range. With
        ``spread_deg``, poses after the first keep their own radius and fov but sit within
        +-``spread_deg`` of the first pose in azimuth and in elevation (uniform offsets, folded back
        into the ranges): a batch of nearby views. The first pose, radii and fovs are the draws
        ``spread_deg=None`` makes from the same generator."""
        if n < 1:
            raise ValueError(f"n: expected at least one pose, got {n}")
        if spread_deg is not None and not 0 < spread_deg <= 180:
            raise ValueError(f"spread_deg: expected degrees in (0, 180] or None, got {spread_deg}")
        r = (radius, radius) if isinstance(radius, (int, float)) else radius
        for name, (lo, hi) in (
            ("radius", r),
            ("fovy_range", fovy_range),
            ("azimuth_range", azimuth_range),
            ("elevation_range", elevation_range),
        ):
            if lo > hi:
                raise ValueError(f"{name}: expected (low, high) with low <= high, got ({lo}, {hi})")
        if not (-90.0 < elevation_range[0] and elevation_range[1] < 90.0):
            raise ValueError(f"elevation_range: expected degrees inside (-90, 90), got {elevation_range}")
        if r[0] <= 0:
            raise ValueError(f"radius: expected a positive distance, got {radius}")
        if not (0.0 < fovy_range[0] and fovy_range[1] < 180.0):
            raise ValueError(f"fovy_range: expected degrees inside (0, 180), got {fovy_range}")

        def uniform(lo: float, hi: float) -> Tensor:
            return lo + (hi - lo) * torch.rand(n, generator=generator, dtype=torch.float64)

        poses = cls(
            azimuth=uniform(*azimuth_range),
            elevation=uniform(*elevation_range),
            radius=uniform(*r),
            fovy=uniform(*fovy_range),
        )
        if spread_deg is None or n == 1:
            return poses
        off = spread_deg * (2 * torch.rand(2, n - 1, generator=generator, dtype=torch.float64) - 1)
        lo, hi = azimuth_range
        az = poses.azimuth[:1] + off[0]
        az = (az - lo) % 360.0 + lo if hi - lo >= 360.0 else _fold(az, lo, hi)
        el = _fold(poses.elevation[:1] + off[1], *elevation_range)
        return cls(torch.cat([poses.azimuth[:1], az]), torch.cat([poses.elevation[:1], el]), poses.radius, poses.fovy)

    @classmethod
    def orbit(
        cls, n: int, *, radius: float = 1.0, elevation: float = 15.0, fovy: float = 50.0, start: float = 0.0
    ) -> SphericalPoses:
        """n poses evenly spaced in azimuth (360/n degrees apart) at one elevation: turntables, scoring."""
        if n < 1:
            raise ValueError(f"n: expected at least one pose, got {n}")
        az = start + torch.arange(n, dtype=torch.float64) * (360.0 / n)
        az = (az + 180.0) % 360.0 - 180.0
        full = torch.full((n,), 1.0, dtype=torch.float64)
        return cls(az, elevation * full, radius * full, fovy * full)


def fovy_for_radius(object_radius: float, distance: float, margin: float = 1.15) -> float:
    """Vertical fov (degrees) at which a ball of ``object_radius`` at ``distance`` fills the frame."""
    return math.degrees(2 * math.asin(min(1.0, margin * object_radius / distance)))
