"""The embedded CPU prior: the exact posterior-mean denoiser of a bank of captioned images.

For a bank {y_i} of one caption (rendered from the procedural asset), the data distribution
is the empirical one, p(x0) = sum_i pi_i delta(x0 - y_i), and for y = x0 + sigma n

    D(y; sigma) = E[x0 | y] = sum_i softmax_i(log pi_i - |y - y_i|^2 / (2 sigma^2)) y_i,

exactly (pi_i uniform by default). The posterior is taken at the query's camera:
- field of view (``fovy``): the bank is rendered once at a wide field of view and, for a query
  at fovy f, zoomed to f about the principal point (``assets/zoom.py``: a change of field of view
  at one camera position is an exact zoom of a pinhole image). Zoomed banks are cached per
  ``fov_step`` degrees (the query's fov is rounded to that grid: at 0.5 degrees the zoom is off by
  at most 0.22 px at the edge of a 64 px image), and shared by the priors of one process whose
  conditions hold the same bank data (a sweep builds one prior per cell: its next cell of the
  prompt zooms nothing);
- view-dependent prompting (``view_mode``): the posterior runs over the bank images of the
  camera's view range only: DreamFusion/3DFuse buckets (front |az| < 45, back |az| > 135,
  side otherwise, overhead when elevation > 60), or a window of +-``window_deg`` around the
  camera's azimuth;
- a front bias (``front_bias`` = kappa): bank view i gets the prior weight
  pi_i proportional to exp(kappa cos azimuth_i), as photo collections are front-heavy (the mechanism
  of multi-face results in Stable Diffusion); kappa = 0 is uniform;
- instance ambiguity (``variants``): the bank holds the views of that many procedural variants
  of the caption (``assets/library.py``), so different views may settle on different instances;
- depth conditioning (the ControlNet role): the joint posterior over (rgb, depth), i.e. the
  logits add ``-depth_weight |d - d_i|^2 / (2 sigma^2)`` for the render's depth d.
Images are [B, H, W, 3] in [-1, 1]. Distances are summed in float32 from the differences
themselves (not |x|^2 - 2 x.y + |y|^2, which cancels catastrophically at small sigma).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass
from typing import Annotated, ClassVar, Literal

import numpy as np
import torch
from torch import Tensor

from gdbench.assets.bank import Bank, BankConfig, load_bank
from gdbench.assets.library import CAPTIONS
from gdbench.assets.zoom import zoom_images
from gdbench.core.constraints import AtLeast, Range, When, check_fields
from gdbench.priors import RunView, ve_sigmas_from_betas
from gdbench.priors.compose import resolve
from gdbench.priors.text import CaptionMatcher

ViewMode = Literal["none", "buckets", "window"]


@dataclass(frozen=True)
class EmpiricalCond:
    caption: str
    images: Tensor
    """[V, h, w, 3] in [-1, 1], seen at ``fovy``."""
    depth: Tensor
    """[V, h, w] camera z, 0 where empty."""
    azimuth: Tensor
    elevation: Tensor
    fovy: float = 55.0
    """Vertical field of view (degrees) of the bank images."""
    alpha: Tensor | None = None
    """[V, h, w] coverage (weights the depth when it is zoomed)."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """In [0, 1]: what a zoom shows beyond the bank's frame."""
    similarity: float = 1.0
    """Cosine similarity of the prompt to ``caption`` (1 for an exact match)."""
    variant: Tensor | None = None
    """[V] the procedural variant of each bank view (None: all variant 0)."""


@dataclass(frozen=True)
class _Level:
    """A bank at one resolution and field of view, flattened: images [V, H*W*3], depth [V, H*W]."""

    images: Tensor
    depth: Tensor | None


@dataclass(eq=False)
class _Source:
    """The data a zoomed level is made from (a condition's images, depth, alpha, field of view and
    background): levels made from one source serve every condition that holds the same data."""

    images: Tensor
    depth: Tensor
    alpha: Tensor | None
    fovy: float
    background: tuple[float, float, float]

    def holds(self, cond: EmpiricalCond) -> bool:
        """Whether ``cond`` holds this data, value for value (the same tensors, or equal ones)."""
        if self.fovy != cond.fovy or self.background != _background(cond):
            return False
        pairs = ((self.images, cond.images), (self.depth, cond.depth), (self.alpha, cond.alpha))
        return all(_same_data(a, b) for a, b in pairs)


def _background(cond: EmpiricalCond) -> tuple[float, ...]:
    return tuple(float(c) for c in _array(cond.background))


def _same_data(a: Tensor | None, b: Tensor | None) -> bool:
    if a is None or b is None:
        return a is b
    if a is b:
        return True
    return a.shape == b.shape and a.dtype == b.dtype and a.device == b.device and torch.equal(a, b)


_SOURCES: list[_Source] = []
"""The bank data of the process's most recent conditions (at most ``_MAX_SOURCES``, newest last).
A condition's tensors are not to be edited in place: the levels made from them would not follow
(as before, when a prior kept its levels by the condition's tensor)."""
_MAX_SOURCES = 2
_LEVELS: OrderedDict[tuple, _Level] = OrderedDict()
"""Zoomed levels by (source, H, W, fovy), least recently used first, for every prior of the process."""


def _source_for(cond: EmpiricalCond) -> _Source:
    """The registered source holding ``cond``'s data, or a new one (the oldest beyond
    ``_MAX_SOURCES`` is dropped with its levels). Data are compared only with a source of the same
    field of view and background, so a process's first condition costs no comparison."""
    for src in reversed(_SOURCES):
        if src.holds(cond):
            _SOURCES.remove(src)
            _SOURCES.append(src)
            return src
    src = _Source(cond.images, cond.depth, cond.alpha, cond.fovy, _background(cond))
    _SOURCES.append(src)
    while len(_SOURCES) > _MAX_SOURCES:
        old = _SOURCES.pop(0)
        for key in [k for k in _LEVELS if k[0] is old]:
            del _LEVELS[key]
    return src


def clear_level_cache() -> None:
    """Frees the process's zoomed levels and the bank data they were made from (they outlive the
    priors that made them, so that the next prior of the same bank finds them)."""
    _SOURCES.clear()
    _LEVELS.clear()


def bucket(azimuth: Tensor, elevation: Tensor) -> Tensor:
    """0 front, 1 side, 2 back, 3 overhead (DreamFusion's view-dependent prompt buckets)."""
    a = (azimuth + 180.0) % 360.0 - 180.0
    b = torch.where(a.abs() < 45.0, 0, torch.where(a.abs() > 135.0, 2, 1))
    return torch.where(elevation > 60.0, torch.full_like(b, 3), b)


class EmpiricalPrior:
    channels = 3
    factor = 1
    """The prior's input is the render itself (no latent downsampling)."""
    encode_images = None
    """No image encoder: the prior works on pixels."""

    def __init__(
        self,
        *,
        view_mode: ViewMode = "buckets",
        window_deg: float = 45.0,
        depth_weight: float = 0.0,
        bank_config: BankConfig | None = None,
        banks: dict[str, Bank] | None = None,
        threshold: float = 0.5,
        fov_step: float = 0.5,
        cache_bytes: int = 4 << 30,
        front_bias: float = 0.0,
        variants: int = 1,
    ):
        if view_mode not in ("none", "buckets", "window"):
            raise ValueError(f"view_mode: expected 'none', 'buckets' or 'window', got {view_mode!r}")
        if not 0 < window_deg <= 180:
            raise ValueError(f"window_deg: expected degrees in (0, 180], got {window_deg}")
        if depth_weight < 0:
            raise ValueError(f"depth_weight: expected a non-negative weight, got {depth_weight}")
        if not fov_step > 0:
            raise ValueError(f"fov_step: expected a positive step in degrees, got {fov_step}")
        if cache_bytes < 1:
            raise ValueError(f"cache_bytes: expected a positive size, got {cache_bytes}")
        if not (math.isfinite(front_bias) and front_bias >= 0):
            raise ValueError(f"front_bias: expected kappa >= 0, got {front_bias}")
        self.front_bias = front_bias
        from gdbench.assets.library import VARIANTS

        if not 1 <= variants <= VARIANTS:
            raise ValueError(f"variants: expected 1..{VARIANTS} procedural variants per caption, got {variants}")
        self.variants = variants
        self.view_mode = view_mode
        self.window_deg = window_deg
        self.depth_weight = depth_weight
        self.bank_config = bank_config or BankConfig()
        self._banks = dict(banks or {})
        self.matcher = CaptionMatcher([*CAPTIONS, *sorted(set(self._banks) - set(CAPTIONS))], threshold)
        self.sigmas = ve_sigmas_from_betas().float()
        self.fov_step = fov_step
        self.cache_bytes = cache_bytes
        self._sources: dict[int, tuple[EmpiricalCond, _Source]] = {}

    def encode(self, prompt: str) -> EmpiricalCond:
        """The condition of the caption nearest to ``prompt``; a prompt that contradicts that
        asset (a negation, or a colour the asset lacks) raises ValueError saying why."""
        caption, similarity = resolve(prompt, self.matcher)
        bank = self._banks.get(caption) or load_bank(caption, self.bank_config)
        self._banks[caption] = bank
        banks = [bank] + [load_bank(caption, bank.config, variant=v) for v in range(1, self.variants)]

        def cat(name: str) -> Tensor:  # one bank's own tensors as they are (a condition's are read-only)
            parts = [getattr(b, name) for b in banks]
            return torch.cat(parts) if len(parts) > 1 else parts[0]

        return EmpiricalCond(
            caption,
            cat("images").mul(2).sub_(1),  # the values of images * 2 - 1, in one new tensor (70 MB) instead of three
            cat("depth"),
            cat("azimuth"),
            cat("elevation"),
            fovy=float(bank.config.fovy),
            alpha=cat("alpha"),
            background=tuple(float(c) for c in bank.config.background),
            similarity=similarity,
            variant=torch.cat([torch.full((len(b),), v) for v, b in enumerate(banks)]),
        )

    def bank(self, cond: EmpiricalCond) -> Bank | None:
        """The image bank behind a condition (for initialisation from its depth maps)."""
        return self._banks.get(cond.caption)

    def _allowed(self, cond: EmpiricalCond, azimuth: Tensor | None, elevation: Tensor | None, B: int) -> np.ndarray:
        """[B, V] mask of bank views each query may use (numpy: a few hundred entries per step,
        where torch's per-operation cost exceeded the work)."""
        V = cond.images.shape[0]
        if self.view_mode == "none" or azimuth is None:
            return np.ones((B, V), dtype=bool)
        if self.view_mode == "buckets":
            el = elevation if elevation is not None else torch.zeros_like(azimuth)
            mask = (bucket(azimuth, el)[:, None] == bucket(cond.azimuth, cond.elevation)[None, :]).numpy()
        else:  # in the queries' and the bank's dtypes, as the torch expression would
            a, c = _array(azimuth), _array(cond.azimuth)
            d = (a[:, None] - c[None, :] + 180.0) % 360.0 - 180.0
            mask = np.abs(d) <= self.window_deg
        # a query whose range holds no bank view falls back to the whole bank
        return np.where(mask.any(1, keepdims=True), mask, True)

    def fov_level(self, fovy: float) -> float:
        """The field of view (degrees) a query at ``fovy`` is served at: rounded to ``fov_step``."""
        return round(fovy / self.fov_step) * self.fov_step

    def denoise(
        self,
        x: Tensor,
        sigma: Tensor,
        cond: EmpiricalCond,
        *,
        azimuth: Tensor | None = None,
        elevation: Tensor | None = None,
        depth: Tensor | None = None,
        fovy: Tensor | None = None,
    ) -> Tensor:
        """Posterior mean [B, H, W, 3]; ``fovy`` [B] (degrees) is the query cameras' vertical field
        of view (None: the bank's own)."""
        if x.dim() != 4 or x.shape[-1] != 3:
            raise ValueError(f"x: expected shape [B, H, W, 3], got {list(x.shape)}")
        B, H, W, _ = x.shape
        sig = _per_query(sigma, B, "sigma")
        if (sig <= 0).any() or not np.isfinite(sig).all():
            raise ValueError(f"sigma: expected positive finite noise levels, got {sig.tolist()}")
        fovs = [None] * B
        if fovy is not None:
            f = _per_query(fovy, B, "fovy")
            if not ((f > 0) & (f < 180)).all():
                raise ValueError(f"fovy: expected degrees in (0, 180), got {f.tolist()}")
            fovs = [self.fov_level(float(v)) for v in f]
        use_depth = depth is not None and self.depth_weight > 0
        mask = self._allowed(cond, azimuth, elevation, B)
        xf = x.reshape(B, -1).float().cpu()  # the bank lives in host memory: queries on any device come here
        zf = depth.reshape(B, -1).float().cpu() if use_depth else None
        out = torch.empty(B, H * W * 3, dtype=torch.float32)
        az_bank = _array(cond.azimuth).astype(np.float64) if self.front_bias else None
        for b in range(B):
            level = self._level(cond, H, W, fovs[b], use_depth)
            runs = _runs(mask[b])  # the allowed views as contiguous row ranges: slices, no copies
            d2 = _cat([_sqdist(xf[b : b + 1], level.images[i:j]) for i, j in runs]).cpu().numpy()
            if use_depth:
                d2 = (
                    d2
                    + self.depth_weight
                    * _cat([_sqdist(zf[b : b + 1], level.depth[i:j]) for i, j in runs]).cpu().numpy()
                )
            # the posterior weights over the allowed views, in float64 numpy (a few hundred entries)
            logits = -d2 / (2 * float(sig[b]) ** 2)
            if self.front_bias:
                az = np.concatenate([az_bank[i:j] for i, j in runs])
                logits = logits + self.front_bias * np.cos(np.deg2rad(az))
            e = np.exp(logits - logits.max())
            w = torch.from_numpy((e / e.sum()).astype(np.float32)).to(level.images.device)
            acc, k = None, 0
            for i, j in runs:
                part = w[k : k + j - i] @ level.images[i:j]
                acc = part if acc is None else acc + part
                k += j - i
            out[b] = acc
        return out.to(device=x.device, dtype=x.dtype).reshape(B, H, W, 3)

    def _level(self, cond: EmpiricalCond, H: int, W: int, fovy: float | None, with_depth: bool) -> _Level:
        """The bank zoomed to ``fovy`` at H x W, flattened (the process's LRU cache, kept to this
        prior's ``cache_bytes``: all 61 levels of the default 64 px bank take 1.1 GB, of three
        variants 3.2 GB)."""
        held = self._sources.pop(id(cond), None)
        # the condition itself is kept, so its id stays its own; a source dropped from the process's
        # list (by other banks' conditions since) is looked up again, as its levels went with it
        if held is None or held[0] is not cond or held[1] not in _SOURCES:
            held = (cond, _source_for(cond))
        self._sources[id(cond)] = held  # most recent last
        while len(self._sources) > 4:  # a caller that encodes per query: keep the recent ones only
            self._sources.pop(next(iter(self._sources)))
        key = (held[1], H, W, fovy)
        level = _LEVELS.get(key)
        if level is not None and (level.depth is not None or not with_depth):
            _LEVELS.move_to_end(key)
            return level
        src = cond.fovy
        dst = src if fovy is None else fovy
        V = cond.images.shape[0]
        bg = torch.tensor(cond.background, dtype=torch.float32) * 2 - 1
        images = level.images if level is not None else zoom_images(cond.images, src, dst, H, W, background=bg)
        Z = None
        if with_depth:
            a = cond.alpha if cond.alpha is not None else (cond.depth > 0).float()
            za = zoom_images(torch.stack([cond.depth * a, a], -1), src, dst, H, W)
            Z = torch.where(za[..., 1] > 1e-6, za[..., 0] / za[..., 1].clamp_min(1e-6), torch.zeros_like(za[..., 0]))
            Z = Z.reshape(V, -1).float().contiguous()
        level = _Level(images.reshape(V, -1).float().contiguous(), Z)
        _LEVELS[key] = level
        _LEVELS.move_to_end(key)
        size = lambda lv: lv.images.nbytes + (lv.depth.nbytes if lv.depth is not None else 0)  # noqa: E731
        while len(_LEVELS) > 1 and sum(size(v) for v in _LEVELS.values()) > self.cache_bytes:
            _LEVELS.popitem(last=False)
        return level


def _runs(mask) -> list[tuple[int, int]]:
    """Maximal runs [i, j) of True in a 1D mask (numpy or torch; bank views are stored
    azimuth-major, so a view window is one run, or two where it wraps around 180 degrees)."""
    idx = np.flatnonzero(np.asarray(mask, dtype=bool))
    if idx.size == 0:
        return []
    cut = np.flatnonzero(np.diff(idx) != 1)
    starts = [int(idx[0])] + idx[cut + 1].tolist()
    ends = (idx[cut] + 1).tolist() + [int(idx[-1]) + 1]
    return list(zip(starts, ends))


def _array(x) -> np.ndarray:
    """A tensor's (or array-like's) values as a 1D numpy array of its dtype."""
    return (x.detach().cpu().numpy() if isinstance(x, Tensor) else np.asarray(x)).reshape(-1)


def _per_query(x, B: int, name: str) -> np.ndarray:
    """A scalar or one value per query, as float64 [B]."""
    a = _array(x).astype(np.float64)
    if a.size not in (1, B):
        raise ValueError(f"{name}: expected one value or {B} (one per query), got {a.size}")
    return np.broadcast_to(a, (B,))


def _cat(parts: list[Tensor]) -> Tensor:
    return parts[0] if len(parts) == 1 else torch.cat(parts)


def _sqdist(x: Tensor, Y: Tensor) -> Tensor:
    """Squared distances [V] (float64) of one flattened image x [1, P] to the rows of Y [V, P].
    On CPU with the C++ extension: one pass over Y, each float32 difference squared and summed
    in double (relative error ~1e-8). Otherwise torch.cdist's direct mode (~5e-6 at P = 12288;
    a difference tensor and a dot product would be exact to ~1e-7 but need a [V, P] temporary,
    whose page faults made the training step 30% slower)."""
    from renderers.splat._ext import load_extension

    ext = load_extension() if Y.device.type == "cpu" and Y.dtype in (torch.float32, torch.float64) else None
    if ext is not None:
        return ext.sqdist_rows(x.reshape(-1).to(Y.dtype).contiguous(), Y)
    d = torch.cdist(x, Y, compute_mode="donot_use_mm_for_euclid_dist")[0].double()
    return d * d


def bank_config_for(resolution: int, fovy_range: tuple[float, float], **kw) -> BankConfig:
    """The bank a trainer at ``resolution`` px and fovy in ``fovy_range`` needs: rendered at the
    widest field of view, with enough pixels that the narrowest one still gets at least
    ``resolution`` source pixels across (rounded up to a multiple of 8)."""
    lo, hi = fovy_range
    if not 0 < lo <= hi < 180:
        raise ValueError(f"fovy_range: expected 0 < min <= max < 180 degrees, got {fovy_range}")
    ratio = math.tan(math.radians(hi) / 2) / math.tan(math.radians(lo) / 2)
    res = int(math.ceil(resolution * ratio / 8 - 1e-9) * 8)
    return BankConfig(resolution=res, fovy=hi, **kw)


@dataclass(frozen=True)
class EmpiricalPriorConfig:
    """The embedded CPU prior (``--prior empirical``): the exact posterior over image banks of the
    procedural assets, rendered from where the trainer's cameras look."""

    kind: ClassVar[str] = "empirical"
    front_bias: Annotated[float, AtLeast(0)] = 0.0
    """kappa of the front-heavy bank, pi_i ~ exp(kappa cos azimuth_i) (0: uniform; the Janus setting
    of the ablation uses it with view prompting off)."""
    variants: Annotated[int, AtLeast(1)] = 1
    """Procedural variants of the caption in the bank (1..3; the instance setting of the ablation
    uses 3)."""
    depth_conditioning: bool = False
    """Condition the prior on depth (the ControlNet role: the joint rgb-depth posterior)."""
    view_prompting: Literal["none", "buckets", "window"] = "window"
    """View-dependent prompting: DreamFusion/3DFuse buckets (front/side/back/overhead), a window
    around the camera azimuth (its half-width --view-window-deg), or none
    (docs/training.md)."""
    view_window_deg: Annotated[float, Range(0, 180, lo_open=True, unit="degrees"), When("view_prompting", "window")] = (
        45.0
    )
    """Half-width of the view window (--view-prompting window), degrees."""

    def __post_init__(self) -> None:
        check_fields(self, "prior.", options="")  # every field against its declared type, range and choices

    @property
    def input_space(self) -> str:
        """What the trainer renders for this prior: 'rgb', with '+depth' when it conditions on depth."""
        return "rgb+depth" if self.depth_conditioning else "rgb"

    def make(self, run: RunView) -> EmpiricalPrior:
        """The prior of a training run: its bank rendered at the run's camera distance, background
        and widest field of view, so it sees the object from where the trainer's cameras do (the
        object keeps its size in the world)."""
        return EmpiricalPrior(
            view_mode=self.view_prompting,
            window_deg=self.view_window_deg,
            depth_weight=1.0 if self.depth_conditioning else 0.0,
            front_bias=self.front_bias,
            variants=self.variants,
            bank_config=bank_config_for(
                run.resolution, run.fovy_range, background=tuple(run.background), radius=float(run.camera_radius)
            ),
        )
