"""Structured noise (paper section 3.2): noise rendered from one 3D cloud of noise Gaussians.

A fixed cloud of M Gaussians (positions in spherical coordinates: radius uniform in
[0, radius], azimuth in [-180, 180], elevation in [-45, 45] degrees; isotropic scale; one
opacity) carries colours ``c_i ~ N(0, I_D)``. For a view, the splat renderer gives
``C(u) = sum_i w_i(u) c_i`` and ``V(u) = sum_i w_i(u)^2`` (its ``weight_sq`` output). Since the
colours are iid standard normal, ``C(u) ~ N(0, V(u))`` exactly, so

    n_s(u) = C(u) / sqrt(V(u))  ~  N(0, 1)   per pixel and channel,

and every view of one step sees the same 3D source: pixels that see the same noise
Gaussians get correlated noise. Pixels with ``V(u) < v_min`` (nothing of the cloud there)
get iid noise instead; ``coverage`` marks the others.

Mixing keeps unit variance: ``n = a_t n_s + sqrt(1 - a_t^2) n_iid`` with the paper's "proportion
of structured noise" r_t going from ``ratio_start`` (0.3) to ``ratio_end`` (0.05) linearly over
the run. The proportion has two readings (``ratio``): the amplitude (``a_t = r_t``, so the
structured share of the variance is r_t^2, 9% at most) or the variance fraction
(``a_t = sqrt(r_t)``, 30% of the variance at the start); docs/noise.md says which is the default.

When colours are redrawn (``redraw``):
- ``"step"``: fresh colours every step (independent sources across steps);
- ``"run"``: one draw for the whole run;
- ``"ou"``: Ornstein-Uhlenbeck drift ``c_t = sqrt(1 - b) c_{t-1} + sqrt(b) eps``, which keeps
  N(0, 1) marginals while step k apart correlate as ``(1 - b)^(k/2)``.

All randomness comes from explicit ``torch.Generator``s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal

import torch
from torch import Tensor

from gdbench.core.camera import Cameras
from gdbench.core.constraints import AtLeast, Between, Flag, Positive, Range, When, check_fields
from gdbench.core.rand import randn

Redraw = Literal["step", "run", "ou"]
RatioMode = Literal["amplitude", "variance"]
CLOUD = When("source", "cloud", "pose")
"""The noise cloud's settings act only with gdbench's own sources (a user's source replaces the cloud)."""


@dataclass(frozen=True)
class NoiseConfig:
    """Settings of the noise cloud and of its use during a run."""

    OPTIONS: ClassVar[tuple[str, ...]] = ("enabled", "source", "redraw", "ou_beta", "ratio")
    """The fields that are command-line options (``core.constraints.flag`` names them:
    --structured-noise, --noise-source, --noise-redraw, --noise-ou-beta, --noise-ratio)."""
    enabled: Annotated[bool, Flag("structured-noise")] = True
    """Use the paper's structured noise (section 3.2); off, the noise is iid (the gd-no-sn ablation).
    Every other noise setting acts only with it."""
    source: str = "cloud"
    """What a view's structured noise is: 'cloud' renders the noise cloud from the view's own camera
    (the paper: views share noise at the same surface point; the default); 'pose' is a control
    (the gd-pose-locked preset): a 2D field that is a fixed function of the camera's pose, with the
    same marginals, spectrum and persistence but no 3D correspondence between views
    (mechanisms/pose_noise.py); or your own, pkg.mod:function or file.py:function
    (mechanisms/methods.py, docs/training.md "Your own method")."""
    n_gaussians: Annotated[int, AtLeast(1), CLOUD] = 3072
    """M, the number of noise Gaussians (3072 keeps the noise under 30% of a 4k-Gaussian
    training step at 128 px on 2 CPU cores; see docs/noise.md)."""
    radius: Annotated[float, Positive(), CLOUD] = 0.5
    """Largest distance of a noise Gaussian from the origin."""
    scale: Annotated[float, Positive(), CLOUD] = 0.02
    """Isotropic standard deviation of each noise Gaussian (world units); sets the noise's
    correlation length (about 10 px at 128 px, camera radius 1, see docs/noise.md)."""
    opacity: Annotated[float, Range(0, 1, lo_open=True), CLOUD] = 0.6
    """Opacity of each noise Gaussian."""
    azimuth_range: Annotated[tuple[float, float], Between(-360, 360, unit="degrees"), CLOUD] = (-180.0, 180.0)
    elevation_range: Annotated[tuple[float, float], Between(-90, 90, unit="degrees"), CLOUD] = (-45.0, 45.0)
    redraw: Annotated[Redraw, CLOUD] = "run"
    """When the noise cloud's colours are redrawn: 'run' keeps one draw for the whole run (the
    paper: every view sees one fixed 3D source; the default), 'ou' drifts them slowly
    (Ornstein-Uhlenbeck, --noise-ou-beta), 'step' redraws every step (an ablation: no two steps
    share a source)."""
    ou_beta: Annotated[float, Range(0, 1, lo_open=True), When("redraw", "ou"), CLOUD] = 0.1
    """b of the Ornstein-Uhlenbeck drift c_t = sqrt(1 - b) c_{t-1} + sqrt(b) eps (0 < b <= 1; 1 is
    the same as 'step'; default 0.1); acts only with --noise-redraw ou."""
    ratio_start: Annotated[float, Between(0, 1)] = 0.3
    """r_t at the first step."""
    ratio_end: Annotated[float, Between(0, 1)] = 0.05
    """r_t at the last step."""
    ratio: RatioMode = "variance"
    """How the paper's 'proportion of structured noise' r_t (0.3 -> 0.05) mixes: 'variance' (the
    default: n = sqrt(r) n_s + sqrt(1 - r) n_iid) or 'amplitude' (n = r n_s + sqrt(1 - r^2) n_iid)."""
    v_min: Annotated[float, AtLeast(0), CLOUD] = 1e-6
    """Pixels with sum_i w_i^2 below this get iid noise."""

    def __post_init__(self) -> None:
        check_fields(self, "noise.")  # every field against its declared type, range and choices
        from gdbench.mechanisms.methods import check

        check("noise", self.source)  # a built-in name, or the user's method loads
        if self.source == "pose" and self.redraw != "run":
            raise ValueError(
                f"noise.redraw (--noise-redraw): --noise-source pose is a fixed function of the pose for the "
                f"whole run; expected 'run', got {self.redraw!r}"
            )


@dataclass(frozen=True)
class NoiseCloud:
    """Fixed geometry of the noise Gaussians (activated values, as the renderer takes them)."""

    means: Tensor
    """[M, 3]"""
    scales: Tensor
    """[M, 3]"""
    opacities: Tensor
    """[M]"""
    channels: int
    """D, the channels of the noise (3 for pixel priors, 4 for SD latents)."""

    def __len__(self) -> int:
        return self.means.shape[0]

    @property
    def quats(self) -> Tensor:
        q = torch.zeros(len(self), 4, dtype=self.means.dtype, device=self.means.device)
        q[:, 0] = 1.0
        return q

    def to(self, *args, **kwargs) -> NoiseCloud:
        return NoiseCloud(
            self.means.to(*args, **kwargs),
            self.scales.to(*args, **kwargs),
            self.opacities.to(*args, **kwargs),
            self.channels,
        )


def make_noise_cloud(config: NoiseConfig, channels: int, *, generator: torch.Generator) -> NoiseCloud:
    """Sample the cloud's positions as in the paper (spherical coordinates)."""
    if channels < 1:
        raise ValueError(f"channels: expected at least 1 noise channel, got {channels}")
    m = config.n_gaussians

    def uniform(lo: float, hi: float) -> Tensor:
        return lo + (hi - lo) * torch.rand(m, generator=generator, dtype=torch.float64)

    r = uniform(0.0, config.radius)
    az = torch.deg2rad(uniform(*config.azimuth_range))
    el = torch.deg2rad(uniform(*config.elevation_range))
    means = torch.stack([r * el.cos() * az.cos(), r * el.cos() * az.sin(), r * el.sin()], -1).float()
    return NoiseCloud(means, torch.full((m, 3), config.scale), torch.full((m,), config.opacity), channels)


@dataclass(frozen=True)
class NoiseState:
    """The colours of the cloud at a step (explicit state, advanced by ``advance_colors``)."""

    colors: Tensor
    """[M, D], each entry N(0, 1)."""
    step: int = 0


def init_colors(cloud: NoiseCloud, *, generator: torch.Generator) -> NoiseState:
    g = torch.randn(len(cloud), cloud.channels, generator=generator, device=generator.device)
    return NoiseState(g.to(cloud.means), 0)


def advance_colors(state: NoiseState, redraw: Redraw, *, beta: float = 0.1, generator: torch.Generator) -> NoiseState:
    """Colours of the next step under the redraw policy (see the module docstring)."""
    c = state.colors
    if redraw == "run":
        return NoiseState(c, state.step + 1)
    eps = randn(c.shape, generator=generator).to(c)
    if redraw == "step":
        return NoiseState(eps, state.step + 1)
    if redraw == "ou":
        return NoiseState(math.sqrt(1 - beta) * c + math.sqrt(beta) * eps, state.step + 1)
    raise ValueError(f"redraw: expected 'step', 'run' or 'ou', got {redraw!r}")


@dataclass(frozen=True)
class StructuredNoise:
    noise: Tensor
    """[C, H, W, D] unit-variance noise: n_s where covered, iid elsewhere."""
    coverage: Tensor
    """[C, H, W, 1] 1 where V(u) >= v_min (noise comes from the cloud), else 0."""

    @property
    def coverage_fraction(self) -> float:
        return float(self.coverage.float().mean())


def _cpu_compositor() -> bool:
    from renderers.splat._ext import load_extension

    return load_extension() is not None


class NoiseRenderer:
    """Renders a cloud's noise for cameras, reusing the projection when cameras repeat.

    The projection and tile lists of the cloud depend only on the cameras (the colours are
    plain features), so they are cached per camera set (``cache_size`` most recent).

    Cameras on a GPU: the noise is rendered by the C++ compositor on the CPU and copied to the
    cameras' device (it has no gradients, and gsplat's kernels cannot give its weights, so the
    alternative is the torch compositor there, launch-bound and slower: docs/renderer.md, "On a
    GPU"); the same bits as on the CPU. Without the C++ extension it renders on the cameras'
    device."""

    def __init__(self, cloud: NoiseCloud, *, v_min: float = 1e-6, cache_size: int = 4):
        if cloud.channels < 1 or len(cloud) < 1:
            raise ValueError("cloud: expected a non-empty noise cloud with at least one channel")
        from renderers.splat._checks import check_values

        check_values({"cloud.means": cloud.means, "cloud.scales": cloud.scales}, cloud.scales, cloud.opacities)
        self.cloud = cloud
        self.v_min = v_min
        self.cache_size = cache_size
        self._cache: dict[tuple, object] = {}
        self._on: dict[torch.device, tuple[Tensor, Tensor, Tensor, Tensor]] = {}

    def _geometry(self, device: torch.device) -> tuple[Tensor, Tensor, Tensor, Tensor]:
        """The cloud's means, quats, scales and opacities on ``device``, made once per device."""
        if device not in self._on:
            c = self.cloud.to(device)
            self._on[device] = (c.means, c.quats, c.scales, c.opacities)
        return self._on[device]

    def prepared(self, cams: Cameras):
        """The projection and tile lists of the cloud for ``cams`` (cached per camera set)."""
        from renderers.splat import prepare

        key = None
        if self.cache_size > 0:
            key = (
                str(cams.viewmats.device),
                cams.viewmats.cpu().numpy().tobytes(),
                cams.Ks.cpu().numpy().tobytes(),
                cams.width,
                cams.height,
            )
            if key in self._cache:
                return self._cache[key]
        means, quats, scales, opacities = self._geometry(cams.viewmats.device)
        prepared = prepare(
            means, quats, scales, opacities, cams.viewmats, cams.Ks, cams.width, cams.height, check_values=False
        )
        if key is not None:
            self._cache[key] = prepared
            while len(self._cache) > self.cache_size:
                self._cache.pop(next(iter(self._cache)))
        return prepared

    def render(
        self, colors: Tensor, cams: Cameras, *, generator: torch.Generator, check_values: bool = True
    ) -> StructuredNoise:
        """n_s for every camera from one set of colours [M, D]; iid (from ``generator``) where
        uncovered. ``check_values=False`` skips the scan of ``colors`` for non-finite values (the
        trainer's colours are its own normal draws)."""
        from renderers.splat import normalised_features

        if colors.shape != (len(self.cloud), self.cloud.channels):
            raise ValueError(
                f"colors: expected shape [{len(self.cloud)}, {self.cloud.channels}], got {list(colors.shape)}"
            )
        if check_values and colors.numel() and not bool(torch.isfinite(colors).all()):
            raise ValueError("colors: expected finite values (NaN or infinity found)")  # before any draw
        device = cams.viewmats.device
        if device.type != "cpu" and _cpu_compositor():
            cams = cams.to("cpu")
        with torch.no_grad():
            prepared = self.prepared(cams)
            shape = prepared.batch + (prepared.n_cameras, cams.height, cams.width, self.cloud.channels)
            iid = randn(shape, generator=generator)  # drawn whether or not a pixel needs it
            noise, coverage = normalised_features(
                prepared, colors.to(cams.viewmats), iid, v_min=self.v_min, check_values=False
            )
        return StructuredNoise(noise.to(device), coverage.to(device))


def structured_noise(
    cloud: NoiseCloud, colors: Tensor, cams: Cameras, *, generator: torch.Generator, v_min: float = 1e-6
) -> StructuredNoise:
    """One-off structured noise (no projection cache); see ``NoiseRenderer``."""
    return NoiseRenderer(cloud, v_min=v_min, cache_size=1).render(colors, cams, generator=generator)


def structured_amplitude(ratio: float, mode: RatioMode = "variance") -> float:
    """The weight a of n_s in n = a n_s + sqrt(1 - a^2) n_iid for the proportion ``ratio``."""
    if not 0 <= ratio <= 1:
        raise ValueError(f"ratio: expected a value in [0, 1], got {ratio}")
    if mode == "amplitude":
        return ratio
    if mode == "variance":
        return math.sqrt(ratio)
    raise ValueError(f"mode: expected 'amplitude' or 'variance', got {mode!r}")


def mix(structured: Tensor, ratio: float, *, generator: torch.Generator, mode: RatioMode = "variance") -> Tensor:
    """n = a n_s + sqrt(1 - a^2) n_iid with a = ``structured_amplitude(ratio, mode)``: unit
    variance for any ratio in [0, 1]. The iid part is drawn from ``generator`` with the shape of
    ``structured`` (so a run without structured noise, drawing its noise from the same stream,
    sees the same iid field)."""
    a = structured_amplitude(ratio, mode)
    iid = randn(structured.shape, generator=generator).to(structured)
    return a * structured + math.sqrt(1 - a * a) * iid


def ratio_schedule(step: int, total_steps: int, start: float = 0.3, end: float = 0.05) -> float:
    """r_t, linear from ``start`` at step 0 to ``end`` at the last step."""
    if total_steps < 1:
        raise ValueError(f"total_steps: expected at least 1, got {total_steps}")
    frac = min(max(step / max(total_steps - 1, 1), 0.0), 1.0)
    return start + (end - start) * frac


def autocorrelation_length(field: Tensor, coverage: Tensor, *, weights: bool = False, max_shift: int = 16) -> float:
    """Spatial correlation length (pixels) of structured noise in one view.

    ``field`` [H, W, K] is either K independent noise draws per pixel (empirical correlation)
    or, with ``weights=True``, the exact blending weights w_i(u) over the M noise Gaussians
    (theory: corr(u, u') = w(u).w(u') / (|w(u)| |w(u')|)). Correlations at horizontal and
    vertical offsets 1..max_shift are averaged over pixel pairs that are both covered; the
    length is the offset where the mean correlation falls to 1/e (linear interpolation).
    """
    x = field.double()
    if not weights:
        x = x - x.mean(-1, keepdim=True)
    x = x / x.norm(dim=-1, keepdim=True).clamp_min(1e-300)
    cov = coverage.reshape(coverage.shape[:2]).bool()
    corr = [1.0]
    for d in range(1, max_shift + 1):
        vals = []
        if x.shape[1] > d:
            m = cov[:, d:] & cov[:, :-d]
            vals.append((x[:, d:] * x[:, :-d]).sum(-1)[m])
        if x.shape[0] > d:
            m = cov[d:] & cov[:-d]
            vals.append((x[d:] * x[:-d]).sum(-1)[m])
        v = torch.cat(vals) if vals else torch.zeros(0)
        if v.numel() == 0:
            break
        corr.append(float(v.mean()))
        if corr[-1] < math.exp(-1):
            a, b = corr[-2], corr[-1]
            return d - 1 + (a - math.exp(-1)) / (a - b)
    return float(len(corr) - 1)


def view_coupling(cloud: NoiseCloud, cams: Cameras, *, v_min: float = 1e-6) -> Tensor:
    """How much structured noise two views share: for each covered pixel u of view 0, the largest
    correlation corr(n_s(u), n_s(u')) over the pixels u' of each view (theory:
    w(u).w(u') / (|w(u)| |w(u')|) with w the blending weights over the M noise Gaussians);
    returns the mean over u, one value per camera [C] (1 for view 0 itself).

    This is the check that the mechanism can act: with the colours fixed for the run, views
    30 degrees apart share most of their noise (docs/noise.md). Memory: C H W M floats."""
    from renderers.splat import composite_features, prepare

    m = len(cloud)
    c = cloud.to(cams.viewmats.device)
    with torch.no_grad():
        p = prepare(c.means, c.quats, c.scales, c.opacities, cams.viewmats, cams.Ks, cams.width, cams.height)
        eye = torch.eye(m, dtype=cams.viewmats.dtype, device=cams.viewmats.device)
        w = composite_features(p, eye, outputs=("rgb",)).rgb.reshape(len(cams), -1, m)
        norm = w.norm(dim=-1, keepdim=True)
        unit = w / norm.clamp_min(1e-30)
        covered = norm[0, :, 0] ** 2 >= max(v_min, 1e-30)
        a = unit[0][covered]
        return torch.stack([(a @ unit[i].T).amax(1).mean() for i in range(len(cams))])
