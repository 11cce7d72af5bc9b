"""The learned prior: a small diffusion model of the procedural assets, as a ``Prior``.

Where the empirical prior is the exact posterior over stored images (an oracle that snaps to
its neighbours), this one is a network (``unet.py``) trained on the assets' renders at random
continuous cameras (``training.py``): it generalises between cameras, turns the noise it is
given into content and inherits the biases of its data, as Stable Diffusion does, while every
result still has a ground truth.

Conventions are Stable Diffusion's (``priors/sd/prior.py``), so the trainer's SJC and SDS paths
serve it unchanged: the VE denoiser of a VP epsilon model on SD's scaled-linear schedule,

    sigma_t = sqrt((1 - abar_t) / abar_t),   D(x; sigma) = x - sigma eps(x / sqrt(1 + sigma^2), t),

sigma snapped to the nearest tick (in log sigma) and classifier-free guidance
eps = eps_u + s (eps_c - eps_u), where eps_u drops every condition. The estimate is clipped to
[-1, 1], where the images live (DDPM's clipped x0; ``clip=False`` leaves it as is): at sigma 10
an error of 0.03 in epsilon's MSE is an error of 3 in x0's. The model works at its own
size (32 px for the shipped ones): a trainer rendering at ``factor`` times that hands it the
render box-filtered by ``factor`` (``encode_images``, differentiable), as Stable Diffusion sees
latents 8 times smaller than its images.

Conditions: the caption (matched from the prompt as the empirical prior does), the variant
(variant 0, or dropped when the trainer asks for the caption's ``variants`` = 3: the instance
setting) and the camera (azimuth, elevation, fovy): given as is with ``view_mode`` 'window',
snapped to the centre of DreamFusion's bucket (front 0, sides +-90, back 180 degrees) with
'buckets', dropped with 'none'. Depth is not an input (no ControlNet role).

Shipped models (``weights/``): 'uniform' (views uniform in azimuth) and 'front' (views drawn with
probability proportional to exp(2 cos azimuth)); a path to any ``model.safetensors`` written by
``gdbench train-prior`` works too.
"""

from __future__ import annotations

import itertools
import json
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import torch
from torch import Tensor

from gdbench.core.constraints import AtLeast, When, check_fields
from gdbench.priors import RunView, sd_abar, ve_sigmas_from_betas

WEIGHTS = Path(__file__).parent / "weights"
SHIPPED = {"uniform": 0.0, "front": 2.0}
"""The shipped models and the front bias kappa of their training data."""


@dataclass(frozen=True)
class LearnedCond:
    caption: str
    caption_index: int
    variant_index: int
    """A variant, or the model's null variant (the caption's variants mixed)."""
    similarity: float = 1.0


def model_path(model: str | Path) -> Path:
    """The weights file of a shipped model name or a path (a file or a run folder)."""
    if str(model) in SHIPPED:
        path = WEIGHTS / f"{model}.safetensors"
        if not path.is_file():
            raise FileNotFoundError(
                f"learned_model: the shipped weights {path} are missing from this checkout; "
                "train them with `gdbench train-prior` (docs/learned_prior.md)"
            )
        return path
    path = Path(model)
    if path.is_dir():
        path = path / "model.safetensors"
    if not path.is_file():
        raise FileNotFoundError(
            f"learned_model: expected {sorted(SHIPPED)} or a model.safetensors written by `gdbench train-prior`, "
            f"got {model!s}"
        )
    return path


def model_for_front_bias(front_bias: float) -> str:
    """The shipped model trained with front bias ``front_bias`` (exactly), or ValueError."""
    for name, kappa in SHIPPED.items():
        if abs(front_bias - kappa) < 1e-9:
            return name
    raise ValueError(
        f"front_bias: the learned prior ships models trained at kappa {sorted(SHIPPED.values())}, not "
        f"{front_bias:g}; train one with `gdbench train-prior --front-bias {front_bias:g}` and pass its folder "
        "as --learned-model"
    )


def _metadata(path: Path) -> dict:
    """The string metadata of a weights file (no tensors read)."""
    from safetensors import safe_open

    with safe_open(str(path), framework="pt") as f:
        return dict(f.metadata() or {})


def _captions_of(meta: dict) -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(captions, held-out captions) named by a model's metadata; models written before
    compositional captions know the six paper assets."""
    from gdbench.priors.learned.data import captions

    return tuple(json.loads(meta.get("captions", "null")) or captions()), tuple(json.loads(meta.get("held_out", "[]")))


def model_captions(model: str | Path = "uniform") -> tuple[tuple[str, ...], tuple[str, ...]]:
    """(captions, held-out captions) a model knows, read from its metadata alone (no weights load)."""
    return _captions_of(_metadata(model_path(model)))


def load_model(model: str | Path, device: torch.device | str = "cpu"):
    """(UNet in float32 eval mode, metadata dict) of a shipped name or a weights path."""
    from safetensors.torch import load_file

    from gdbench.priors.learned.unet import UNet, UNetConfig

    path = model_path(model)
    meta = _metadata(path)
    if "unet" not in meta:
        raise ValueError(f"learned_model: {path} has no 'unet' settings in its metadata (not written by train-prior)")
    cfg = json.loads(meta["unet"])
    cfg["widths"] = tuple(cfg["widths"])
    cfg["parts"] = tuple(tuple(r) for r in cfg.get("parts", ()))
    cfg["part_sizes"] = tuple(cfg.get("part_sizes", ()))
    cfg.setdefault("prediction", "epsilon")  # models written before v prediction
    cfg.setdefault("coords", False)  # ... and before coordinates
    net = UNet(UNetConfig(**cfg))
    net.load_state_dict({k: v.float() for k, v in load_file(str(path)).items()})
    return net.to(device).eval().requires_grad_(False), meta


class LearnedPrior:
    channels = 3

    def __init__(
        self,
        model: str | Path = "uniform",
        *,
        guidance_scale: float = 3.0,
        view_mode: str = "window",
        variants: int = 1,
        resolution: int | None = None,
        device: str | torch.device | None = None,
        threshold: float = 0.5,
        clip: bool = True,
    ):
        from gdbench.assets.library import VARIANTS
        from gdbench.priors.text import CaptionMatcher

        if guidance_scale < 1:
            raise ValueError(f"guidance_scale: expected >= 1 (1 is no guidance), got {guidance_scale}")
        if view_mode not in ("none", "buckets", "window"):
            raise ValueError(f"view_mode: expected 'none', 'buckets' or 'window', got {view_mode!r}")
        if variants not in (1, VARIANTS):
            raise ValueError(
                f"variants: the learned prior knows one variant (1) or the caption's {VARIANTS} mixed ({VARIANTS}), "
                f"got {variants}"
            )
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        path = model_path(model).resolve()
        self.unet, self.meta = load_model(path, self.device)
        stat = path.stat()
        self._file = (str(path), stat.st_mtime_ns, stat.st_size)
        """The weights file as loaded (the process's graphs are kept for it: ``_GRAPHS``)."""
        self.size = self.unet.config.size
        resolution = resolution or self.size
        if resolution % self.size:
            raise ValueError(
                f"resolution: the learned prior works at {self.size} px; expected a multiple, got {resolution}"
            )
        self.factor = resolution // self.size
        self.encode_images = self._pool if self.factor > 1 else None
        self.guidance_scale = guidance_scale
        self.clip = clip
        self.view_mode = view_mode
        self.variants = variants
        from gdbench.assets.library import PARTS

        self.captions, self.held_out = _captions_of(self.meta)
        """The captions the model knows, in the order of its caption rows (its metadata's), and those
        of them it never saw in training (compositional models: the generalisation check)."""
        unknown = [c for c in self.captions if c not in PARTS]
        if unknown or self.unet.config.captions != len(self.captions):
            raise ValueError(
                f"learned_model: {model} knows the captions {list(self.captions)}, of which this code's catalogue "
                f"lacks {unknown}; retrain it with `gdbench train-prior`"
            )
        self.matcher = CaptionMatcher(list(self.captions), threshold)
        self.front_bias = float(json.loads(self.meta.get("train", "{}")).get("front_bias", 0.0))
        """kappa of the model's training views (from its metadata)."""
        self.distilled = float(json.loads(self.meta.get("train", "{}")).get("teacher_guidance", 0.0))
        """The guidance scale a one-call model was distilled at (``distillation.py``); 0 for a model
        that guides with two calls."""
        if self.distilled and guidance_scale != self.distilled:
            raise ValueError(
                f"learned_guidance (--learned-guidance): the model {model} gives guidance {self.distilled:g} in one "
                f"call (distilled); it takes --learned-guidance {self.distilled:g} only, got {guidance_scale:g}"
            )
        self.abar = sd_abar()
        self.sigmas = ve_sigmas_from_betas().float()
        self._graphs: dict[tuple[bool, bool, float], torch.nn.Module] = {}

    def check_cameras(self, radius: float, background, fovy_range, elevation_range) -> None:
        """ValueError naming the trainer's setting the model was not trained for: another camera
        distance or background (the model would draw the object at its training size and on its
        training background), or fields of view or elevations outside its training ranges."""
        data = json.loads(self.meta.get("train", "{}")).get("data")
        if not data:
            return
        if abs(float(data["radius"]) - float(radius)) > 1e-6:
            raise ValueError(
                f"camera_radius: the learned model was trained at distance {data['radius']}, the training cameras "
                f"are at {radius}; train a model at that distance (train-prior) or use --prior empirical"
            )
        if any(abs(float(a) - float(b)) > 1e-6 for a, b in zip(data["background"], background)):
            raise ValueError(
                f"background: the learned model was trained on {tuple(data['background'])}, got {tuple(background)}"
            )
        for name, have, want in (("fovy_range", data["fovy_range"], fovy_range),
                                 ("elevation_range", data["elevation_range"], elevation_range)):  # fmt: skip
            if want[0] < have[0] - 1e-6 or want[1] > have[1] + 1e-6:
                raise ValueError(
                    f"{name}: the learned model saw {tuple(have)} degrees in training; expected a range inside it, "
                    f"got {tuple(want)}"
                )

    def _pool(self, rgb: Tensor) -> Tensor:
        """Renders [B, H, W, 3] -> the model's input [B, H/f, W/f, 3]: the f x f box filter."""
        x = torch.nn.functional.avg_pool2d(rgb.permute(0, 3, 1, 2), self.factor)
        return x.permute(0, 2, 3, 1)

    def encode(self, prompt: str) -> LearnedCond:
        from gdbench.priors.compose import resolve

        caption, similarity = resolve(prompt, self.matcher)
        variant = 0 if self.variants == 1 else self.unet.config.variants
        return LearnedCond(caption, self.captions.index(caption), variant, similarity)

    def bank(self, cond) -> None:
        """The learned prior has no image bank."""
        return None

    def timestep(self, sigma: Tensor) -> Tensor:
        """Index of the tick nearest to each sigma (in log sigma), [B] long."""
        from gdbench.priors import nearest_tick

        return nearest_tick(self.sigmas, sigma)

    def camera(self, azimuth: Tensor | None, elevation: Tensor | None, fovy: Tensor | None, B: int) -> Tensor | None:
        """[B, 3] (azimuth, elevation, fovy) the model is conditioned on, or None (dropped)."""
        if self.view_mode == "none" or azimuth is None:
            return None
        az = torch.as_tensor(azimuth, dtype=torch.float32).reshape(-1).expand(B).cpu()
        el = torch.zeros(B) if elevation is None else torch.as_tensor(elevation, dtype=torch.float32).reshape(-1)
        fv = torch.full((B,), 55.0) if fovy is None else torch.as_tensor(fovy, dtype=torch.float32).reshape(-1)
        if self.view_mode == "buckets":
            a = (az + 180.0) % 360.0 - 180.0
            az = torch.where(a.abs() < 45, 0.0, torch.where(a.abs() > 135, 180.0, torch.sign(a) * 90.0))
        return torch.stack([az, el.cpu().expand(B), fv.cpu().expand(B)], 1)

    @torch.no_grad()
    def eps(self, x_t: Tensor, t: Tensor, cond: LearnedCond, camera: Tensor | None, *, guided: bool = True) -> Tensor:
        """Guided epsilon [B, 3, h, w] for DDPM inputs x_t [B, 3, h, w] at ticks t [B]."""
        B = x_t.shape[0]
        cap = torch.full((B,), cond.caption_index, device=self.device)
        var = torch.full((B,), cond.variant_index, device=self.device)
        cam = camera.to(self.device) if camera is not None else None
        guided = guided and self.guidance_scale != 1 and not self.distilled  # a distilled model: one call, guided
        args = (x_t, t, cap, var) + (() if cam is None else (cam,))
        return self._graph(guided, cam is not None)(*args)

    def _graph(self, guided: bool, camera: bool) -> torch.nn.Module:
        """The guided epsilon (``_Epsilon``) as a frozen TorchScript graph on the CPU, traced at the
        first call of each kind: bit for bit the eager module's results, in less time (the network's
        ~200 small operations run without Python between them); the eager module elsewhere. The
        graph holds the weights and the guidance scale as constants: it is kept per process for the
        weights file as it is on disk (``_GRAPHS``: the next cell of a sweep traces nothing) and the
        scale, so weights loaded into ``unet`` later are not seen: make a prior from their file."""
        scale = self.guidance_scale if guided else 1.0
        key = (guided, camera, scale)
        if key not in self._graphs:
            shared = self._file + (str(self.device), *key)
            graph = _GRAPHS.pop(shared, None)
            if graph is None:
                module = _Epsilon(self.unet, self.abar.to(self.device), scale, camera)
                graph = _freeze(module, self.device) if self.device.type == "cpu" else module
            _GRAPHS[shared] = graph  # most recent last
            while len(_GRAPHS) > 8:
                _GRAPHS.pop(next(iter(_GRAPHS)))
            self._graphs[key] = graph
        return self._graphs[key]

    @torch.no_grad()
    def denoise(
        self,
        x: Tensor,
        sigma: Tensor,
        cond: LearnedCond,
        *,
        azimuth: Tensor | None = None,
        elevation: Tensor | None = None,
        depth: Tensor | None = None,
        fovy: Tensor | None = None,
    ) -> Tensor:
        """x0 estimate [B, h, w, 3] of noisy images x [B, h, w, 3] (h = w = the model's size) at
        noise levels sigma [B]. ``depth`` is ignored (the learned prior has no depth input)."""
        if x.dim() != 4 or x.shape[-1] != 3:
            raise ValueError(f"x: expected shape [B, H, W, 3], got {list(x.shape)}")
        B, H, W, _ = x.shape
        if (H, W) != (self.size, self.size):
            raise ValueError(f"x: the learned prior works at {self.size} x {self.size} px, got {H} x {W}")
        t = self.timestep(torch.as_tensor(sigma).reshape(-1).expand(B))
        s = self.sigmas[t].to(self.device)[:, None, None, None]
        xc = x.permute(0, 3, 1, 2).to(self.device, torch.float32)
        e = self.eps(xc / torch.sqrt(1 + s * s), t.to(self.device), cond, self.camera(azimuth, elevation, fovy, B))
        D = xc - s * e
        if self.clip:  # the images live in [-1, 1]: the projection can only bring the estimate closer
            D = D.clamp(-1, 1)
        return D.permute(0, 2, 3, 1).to(x.device, x.dtype)

    @torch.no_grad()
    def sample(
        self,
        cond: LearnedCond,
        camera: Tensor | None,
        *,
        generator: torch.Generator,
        steps: int = 30,
        n: int = 1,
    ) -> Tensor:
        """n images [n, size, size, 3] in [-1, 1] by deterministic DDIM in the VE form
        (x <- D + (sigma_next / sigma)(x - D)), from sigma_max to 0; ``camera`` [3] or [n, 3]
        (azimuth, elevation, fovy) with this prior's view mode, or None (the camera dropped)."""
        ticks = torch.linspace(len(self.sigmas) - 1, 0, steps).round().long()
        sig = self.sigmas[ticks].tolist() + [0.0]
        x = torch.randn(n, self.size, self.size, 3, generator=generator) * sig[0]
        cam = None if camera is None else torch.as_tensor(camera, dtype=torch.float32).reshape(-1, 3).expand(n, 3)
        mode = self.view_mode
        if cam is None:
            self.view_mode = "none"
        try:
            for s, s_next in itertools.pairwise(sig):
                D = self.denoise(
                    x,
                    torch.full((n,), s),
                    cond,
                    azimuth=None if cam is None else cam[:, 0],
                    elevation=None if cam is None else cam[:, 1],
                    fovy=None if cam is None else cam[:, 2],
                )
                x = D + (s_next / s) * (x - D)
        finally:
            self.view_mode = mode
        return x.clamp(-1, 1)


_GRAPHS: dict[tuple, torch.nn.Module] = {}
"""The process's traced graphs (``LearnedPrior._graph``), by weights file (path, mtime, size),
device, kind and guidance scale: a prior made again for the next cell of a sweep reuses them."""


class _Epsilon(torch.nn.Module):
    """Epsilon [B, 3, h, w] of the network for inputs x_t [B, 3, h, w] at ticks t [B], caption and
    variant indices [B] and, where ``camera``, cameras [B, 3]: with guidance (``scale`` > 1) the
    classifier-free eps_u + s (eps_c - eps_u), eps_u dropping caption, variant and camera, the two
    evaluated as one batch; v models' outputs converted (eps = sqrt(abar) v + sqrt(1 - abar) x_t, as
    the SD prior converts v-prediction models)."""

    def __init__(self, unet, abar: Tensor, scale: float, camera: bool):
        super().__init__()
        self.unet, self.scale, self.camera = unet, float(scale), camera
        self.v = unet.config.prediction == "v"
        self.register_buffer("abar", abar, persistent=False)

    def forward(self, x_t: Tensor, t: Tensor, cap: Tensor, var: Tensor, cam: Tensor | None = None) -> Tensor:
        c = self.unet.config
        if self.scale == 1:
            return self._to_eps(self.unet(x_t, self.unet.embedding(t, cap, var, cam)), x_t, t)
        B = x_t.shape[0]
        tt = torch.cat([t, t])
        drop = None
        if cam is not None:
            cam = torch.cat([cam, cam])
            drop = torch.cat([torch.ones(B, dtype=torch.bool), torch.zeros(B, dtype=torch.bool)]).to(x_t.device)
        emb = self.unet.embedding(
            tt,
            torch.cat([torch.full_like(cap, c.captions), cap]),
            torch.cat([torch.full_like(var, c.variants), var]),
            cam,
            drop,
        )
        x2 = torch.cat([x_t, x_t])
        eu, ec = self._to_eps(self.unet(x2, emb), x2, tt).chunk(2)
        return eu + self.scale * (ec - eu)

    def _to_eps(self, out: Tensor, x_t: Tensor, t: Tensor) -> Tensor:
        if not self.v:
            return out
        a = self.abar[t].to(x_t.dtype)[:, None, None, None]
        return a.sqrt() * out + (1 - a).sqrt() * x_t


def _freeze(module: _Epsilon, device: torch.device) -> torch.nn.Module:
    """``module`` traced at a batch of two and frozen, or ``module`` itself where the trace is not
    the module: checked once against it at a batch of three on random inputs, bit for bit (a trace
    records sizes, not their values, but a Python value computed from an input would be frozen in;
    tests/test_learned_prior.py checks more batches, kinds and repeated calls). ``torch.jit.trace``
    is deprecated in favour of ``torch.compile``, whose compile costs ~45 s a process here; where
    it is gone, the eager module too."""
    import warnings

    c = module.unet.config
    g = torch.Generator().manual_seed(0)

    def inputs(B: int) -> tuple:
        x = torch.randn(B, c.channels, c.size, c.size, generator=g).to(device)
        t, cap = torch.randint(0, 1000, (B,), generator=g), torch.randint(0, c.captions, (B,), generator=g)
        var = torch.randint(0, c.variants, (B,), generator=g)
        cam = torch.rand(B, 3, generator=g) * torch.tensor([360.0, 60.0, 30.0]) - torch.tensor([180.0, 30.0, -40.0])
        return (x, t.to(device), cap.to(device), var.to(device)) + ((cam.to(device),) if module.camera else ())

    try:
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", DeprecationWarning)
            warnings.simplefilter("ignore", torch.jit.TracerWarning)  # group norm's size check; the check below
            graph = torch.jit.freeze(torch.jit.trace(module.eval(), inputs(2), check_trace=False))
        check = inputs(3)
        with torch.no_grad():
            same = torch.equal(graph(*check), module(*check))
    except (AttributeError, RuntimeError):
        return module
    if not same:
        warnings.warn("the learned prior's traced network differs from its module; running the module", stacklevel=3)
        return module
    return graph


@dataclass(frozen=True)
class LearnedPriorConfig:
    """The learned prior (``--prior learned``): a small diffusion model trained on the procedural
    assets' renders (docs/learned_prior.md)."""

    kind: ClassVar[str] = "learned"
    learned_model: str = "auto"
    """'uniform', 'front' (the shipped models, trained on views uniform in azimuth or drawn with
    probability ~ exp(2 cos azimuth)), a model.safetensors or run folder of `gdbench train-prior`,
    or 'auto' (the shipped model of --front-bias)."""
    learned_guidance: Annotated[float, AtLeast(1)] = 3.0
    """Classifier-free guidance scale (1: none, one network evaluation per view)."""
    front_bias: Annotated[float, AtLeast(0), When("learned_model", "auto")] = 0.0
    """Picks the shipped model trained at that kappa (0 or 2) when --learned-model is 'auto'."""
    variants: Annotated[int, AtLeast(1)] = 1
    """1 (variant 0) or 3 (the variant dropped: all three of the caption's)."""

    view_prompting: Literal["none", "buckets", "window"] = "window"
    """View-dependent prompting: DreamFusion/3DFuse buckets (front/side/back/overhead), a window
    around the camera azimuth, or none
    (docs/training.md)."""

    def __post_init__(self) -> None:
        check_fields(self, "prior.", options="")  # every field against its declared type, range and choices
        if self.variants not in (1, 3):
            raise ValueError(f"variants: the learned prior takes 1 or 3 (all of a caption's), got {self.variants}")

    input_space: ClassVar[str] = "rgb"
    """What the trainer renders for this prior (it has no depth input)."""

    @property
    def model(self) -> str:
        """The model this config loads: the shipped one of ``front_bias`` for 'auto'."""
        return model_for_front_bias(self.front_bias) if self.learned_model == "auto" else self.learned_model

    def make(self, run: RunView) -> LearnedPrior:
        """The prior of a training run, checked against its cameras."""
        from gdbench.priors import network_device

        prior = LearnedPrior(
            self.model,
            device=network_device(run.device),
            guidance_scale=self.learned_guidance,
            view_mode=self.view_prompting,
            variants=self.variants,
            resolution=run.resolution,
        )
        prior.check_cameras(run.camera_radius, run.background, run.fovy_range, run.elevation_range)
        return prior
