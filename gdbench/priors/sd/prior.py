"""Stable Diffusion as a ``Prior``: the paper's setting (3DFuse's pipeline, SJC's denoiser).

The denoiser in the VE parametrisation, as SJC converts a DDPM: for the scheduler's
cumulative alphas abar_t,

    sigma_t = sqrt((1 - abar_t) / abar_t),    D(x; sigma) = x - sigma * eps(x / sqrt(1 + sigma^2), t),

with sigma snapped to the nearest of the scheduler's ticks (in log sigma), classifier-free
guidance eps = eps_u + s (eps_c - eps_u), and v-prediction models converted to eps
(eps = sqrt(abar) v + sqrt(1 - abar) x_t). It works on SD latents, [B, h, w, 4]
channels-last like every prior here; ``encode_images`` / ``decode_latents`` are the VAE
(the GaussianDiffusion mode renders RGB and encodes it; the SJC mode renders the 4 latent
channels directly). An optional depth ControlNet conditions the UNet on a depth map, and
view-dependent prompting appends DreamFusion's ", front view" / ", side view" / ", back
view" / ", overhead view" to the prompt by camera bucket.

Weights are loaded from a local diffusers folder or the Hugging Face cache, never downloaded.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, ClassVar, Literal

import torch
from torch import Tensor

from gdbench.core.constraints import AtLeast, When, check_fields
from gdbench.priors import RunView

VIEW_SUFFIXES = (", front view", ", side view", ", back view", ", overhead view")

DOWNLOAD_HINT = (
    "On a machine with network access run\n"
    "    huggingface-cli download {repo} --local-dir {path}\n"
    "(and for the depth ControlNet: huggingface-cli download lllyasviel/sd-controlnet-depth --local-dir "
    "<folder>), then copy the folder here and pass it as the model path."
)


LATENT_RGB = torch.tensor(
    [[0.3512, 0.2297, 0.3227], [0.3250, 0.4974, 0.2350], [-0.2829, 0.1762, 0.2721], [-0.2120, -0.2616, -0.7177]]
)
"""Linear map from SD 1.x/2.x (scaled) latents to RGB in [-1, 1]: the common preview
approximation of the VAE decoder, used for per-Gaussian colours of latent-mode scenes."""


def latent_to_rgb(z: Tensor) -> Tensor:
    """Approximate RGB in [0, 1] of latents [..., 4] (a per-pixel linear preview, not the VAE)."""
    return ((z @ LATENT_RGB.to(z)) * 0.5 + 0.5).clamp(0, 1)


@dataclass(frozen=True)
class SDCond:
    prompt: str
    embeddings: Tensor
    """[V, L, E] text embeddings: one per view bucket (V = 4) or the plain prompt (V = 1)."""
    uncond: Tensor
    """[1, L, E] the empty prompt's embedding."""


def _missing(path: str | Path, what: str) -> FileNotFoundError:
    repo = str(path) if "/" in str(path) and not Path(path).exists() else "stabilityai/stable-diffusion-2-1-base"
    return FileNotFoundError(
        f"model: {what} not found at {path!s}. Weights are never downloaded at run time. "
        + DOWNLOAD_HINT.format(repo=repo, path=path)
    )


class StableDiffusionPrior:
    channels = 4
    factor = 8
    """Image pixels per latent pixel (the VAE's downsampling)."""

    def __init__(
        self,
        unet,
        vae,
        text_encoder,
        tokenizer,
        scheduler,
        *,
        controlnet=None,
        guidance_scale: float = 100.0,
        view_prompting: bool = True,
        controlnet_scale: float = 1.0,
        device: str | torch.device | None = None,
        dtype: torch.dtype = torch.float32,
    ):
        if guidance_scale < 1:
            raise ValueError(f"guidance_scale: expected >= 1 (1 is no guidance), got {guidance_scale}")
        self.device = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
        self.dtype = dtype

        def move(m):
            if m is None:
                return None
            p = next(m.parameters())
            return m if (p.device, p.dtype) == (self.device, dtype) else m.to(self.device, dtype)

        self.unet, self.vae, self.text_encoder, self.controlnet = map(move, (unet, vae, text_encoder, controlnet))
        self.tokenizer = tokenizer
        self.scheduler = scheduler
        self.guidance_scale = guidance_scale
        self.controlnet_scale = controlnet_scale
        self.view_prompting = view_prompting
        self.code_text: str | None = None
        self.prediction_type = scheduler.config.prediction_type
        if self.prediction_type not in ("epsilon", "v_prediction"):
            raise ValueError(f"scheduler: prediction_type {self.prediction_type!r} is not supported")
        abar = scheduler.alphas_cumprod.double()
        self.abar = abar
        self.sigmas = torch.sqrt((1 - abar) / abar).float()  # ascending with t
        self.scaling = float(getattr(vae.config, "scaling_factor", 0.18215))
        for m in (self.unet, self.vae, self.text_encoder, self.controlnet):
            if m is not None:
                m.requires_grad_(False)

    # ------------------------------------------------------------------ loading
    @classmethod
    def from_pretrained(
        cls, model: str | Path, *, controlnet: str | Path | None = None, lora: str | Path | None = None, **kw
    ) -> StableDiffusionPrior:
        """Load SD 1.x/2.x from a local diffusers folder or a repo id already in the Hugging
        Face cache (offline). ``controlnet``: a depth ControlNet folder; ``lora``: adapters
        saved by ``threedfuse.SemanticCode``."""
        from diffusers import AutoencoderKL, ControlNetModel, DDPMScheduler, UNet2DConditionModel
        from transformers import CLIPTextModel, CLIPTokenizer

        def load(klass, sub=None, src=model):
            try:
                args = {"subfolder": sub} if sub else {}
                return klass.from_pretrained(str(src), local_files_only=True, **args)
            except (OSError, ValueError) as e:
                raise _missing(src, f"{sub or klass.__name__} ({type(e).__name__})") from e

        if isinstance(model, Path) or Path(str(model)).exists():
            if not (Path(model) / "unet").is_dir():
                raise _missing(model, "a diffusers model folder (unet/, vae/, text_encoder/, tokenizer/, scheduler/)")
        prior = cls(
            load(UNet2DConditionModel, "unet"),
            load(AutoencoderKL, "vae"),
            load(CLIPTextModel, "text_encoder"),
            load(CLIPTokenizer, "tokenizer"),
            load(DDPMScheduler, "scheduler"),
            controlnet=load(ControlNetModel, src=controlnet) if controlnet is not None else None,
            **kw,
        )
        if lora is not None:
            from gdbench.priors.sd.threedfuse import load_semantic_code

            load_semantic_code(prior, lora)
        return prior

    @classmethod
    def tiny(cls, seed: int = 0, *, prediction_type: str = "epsilon", controlnet: bool = True, **kw):
        """The tiny random-weight prior of ``priors/sd/tiny.py`` (tests, smoke runs)."""
        from gdbench.priors.sd.tiny import tiny_components

        c = tiny_components(seed, prediction_type=prediction_type)
        cn = c.pop("controlnet")
        return cls(**c, controlnet=cn if controlnet else None, **kw)

    # ------------------------------------------------------------------ text
    @torch.no_grad()
    def embed(self, texts: list[str]) -> Tensor:
        ids = self.tokenizer(
            texts,
            padding="max_length",
            max_length=self.tokenizer.model_max_length,
            truncation=True,
            return_tensors="pt",
        ).input_ids.to(self.device)
        return self.text_encoder(ids)[0]

    def encode(self, prompt: str) -> SDCond:
        if not isinstance(prompt, str) or not prompt.strip():
            raise ValueError(f"prompt: expected a non-empty text, got {prompt!r}")
        text = self.code_text or prompt  # the semantic code's prompt once one is loaded
        texts = [text + s for s in VIEW_SUFFIXES] if self.view_prompting else [text]
        return SDCond(text, self.embed(texts), self.embed([""]))

    # ------------------------------------------------------------------ sigma <-> t
    def timestep(self, sigma: Tensor) -> Tensor:
        """Index of the scheduler tick nearest to each sigma (in log sigma), [B] long."""
        from gdbench.priors import nearest_tick

        return nearest_tick(self.sigmas, sigma)

    # ------------------------------------------------------------------ the denoiser
    def _buckets(self, azimuth: Tensor | None, elevation: Tensor | None, B: int, V: int) -> Tensor:
        if V == 1 or azimuth is None:
            return torch.zeros(B, dtype=torch.long)
        from gdbench.priors.empirical import bucket

        el = elevation if elevation is not None else torch.zeros_like(azimuth)
        return bucket(azimuth.float().cpu(), el.float().cpu()).long()

    def control_image(self, depth: Tensor) -> Tensor:
        """Depth [B, H, W] (0 = empty) -> the ControlNet's [B, 3, H, W] image in [0, 1]:
        inverse depth normalised per image (near = 1, as MiDaS maps feed SD's depth ControlNet)."""
        inv = torch.where(depth > 0, 1.0 / depth.clamp_min(1e-6), torch.zeros_like(depth))
        lo = torch.where(depth > 0, inv, torch.full_like(inv, math.inf)).flatten(1).amin(1)
        hi = inv.flatten(1).amax(1)
        lo = torch.where(torch.isfinite(lo), lo, torch.zeros_like(lo))
        norm = (inv - lo[:, None, None]) / (hi - lo).clamp_min(1e-8)[:, None, None]
        norm = torch.where(depth > 0, 0.1 + 0.9 * norm, torch.zeros_like(norm))
        return norm[:, None].expand(-1, 3, -1, -1)

    def eps(self, x_t: Tensor, t: Tensor, emb: Tensor, control: Tensor | None = None) -> Tensor:
        """The UNet's epsilon for DDPM inputs x_t [B, 4, h, w] (channels-first) at ticks t."""
        extra = {}
        if control is not None and self.controlnet is not None:
            down, mid = self.controlnet(
                x_t, t, encoder_hidden_states=emb, controlnet_cond=control, conditioning_scale=self.controlnet_scale,
                return_dict=False,
            )  # fmt: skip
            extra = {"down_block_additional_residuals": down, "mid_block_additional_residual": mid}
        out = self.unet(x_t, t, encoder_hidden_states=emb, **extra).sample
        if self.prediction_type == "v_prediction":
            a = self.abar.to(x_t.device)[t].to(x_t.dtype)[:, None, None, None]
            out = a.sqrt() * out + (1 - a).sqrt() * x_t
        return out

    @torch.no_grad()
    def denoise(
        self,
        x: Tensor,
        sigma: Tensor,
        cond: SDCond,
        *,
        azimuth: Tensor | None = None,
        elevation: Tensor | None = None,
        depth: Tensor | None = None,
        fovy: Tensor | None = None,
    ) -> Tensor:
        """x0 estimate [B, h, w, 4] of SD latents x [B, h, w, 4] at noise levels sigma [B].
        ``fovy`` is ignored: Stable Diffusion has no notion of the camera's field of view."""
        if x.dim() != 4 or x.shape[-1] != 4:
            raise ValueError(f"x: expected SD latents [B, h, w, 4], got {list(x.shape)}")
        B = x.shape[0]
        t = self.timestep(torch.as_tensor(sigma).reshape(-1).expand(B)).to(self.device)
        s = self.sigmas.to(self.device)[t].to(self.dtype)[:, None, None, None]  # the snapped sigma
        xc = x.permute(0, 3, 1, 2).to(self.device, self.dtype)
        x_t = xc / torch.sqrt(1 + s * s)
        emb = cond.embeddings.to(self.device)[self._buckets(azimuth, elevation, B, cond.embeddings.shape[0])]
        control = self.control_image(depth.to(self.device, self.dtype)) if depth is not None else None
        if self.guidance_scale == 1:
            e = self.eps(x_t, t, emb, control)
        else:
            e2 = self.eps(
                torch.cat([x_t, x_t]),
                torch.cat([t, t]),
                torch.cat([cond.uncond.to(self.device).expand(B, -1, -1), emb]),
                torch.cat([control, control]) if control is not None else None,
            )
            eu, ec = e2.chunk(2)
            e = eu + self.guidance_scale * (ec - eu)
        return (xc - s * e).permute(0, 2, 3, 1).to(x.dtype).to(x.device)

    def bank(self, cond) -> None:
        """Stable Diffusion has no image bank."""
        return None

    # ------------------------------------------------------------------ the VAE
    def encode_images(self, rgb: Tensor) -> Tensor:
        """RGB [B, H, W, 3] in [-1, 1] -> latents [B, H/8, W/8, 4] (the posterior mean, scaled);
        differentiable, so score distillation reaches the Gaussians through the encoder."""
        if rgb.shape[1] % self.factor or rgb.shape[2] % self.factor:
            raise ValueError(f"rgb: height and width must be multiples of {self.factor}, got {list(rgb.shape)}")
        z = self.vae.encode(rgb.permute(0, 3, 1, 2).to(self.device, self.dtype)).latent_dist.mean
        return (z * self.scaling).permute(0, 2, 3, 1).to(rgb.device, rgb.dtype)

    @torch.no_grad()
    def decode_latents(self, z: Tensor) -> Tensor:
        """Latents [B, h, w, 4] -> RGB [B, 8h, 8w, 3] in [-1, 1]."""
        img = self.vae.decode(z.permute(0, 3, 1, 2).to(self.device, self.dtype) / self.scaling).sample
        return img.clamp(-1, 1).permute(0, 2, 3, 1).float().cpu()

    # ------------------------------------------------------------------ sampling
    @torch.no_grad()
    def sample(
        self, cond: SDCond, size: int = 64, *, steps: int = 30, generator: torch.Generator, view: int = 0
    ) -> Tensor:
        """An image of the prompt, RGB [1, size, size, 3] in [-1, 1]: deterministic DDIM in the
        VE form, x <- D + (sigma_next / sigma) (x - D), from sigma_max down to 0."""
        h = size // self.factor
        ticks = torch.linspace(len(self.sigmas) - 1, 0, steps).round().long()
        sig = self.sigmas[ticks].tolist() + [0.0]
        x = torch.randn(1, h, h, 4, generator=generator) * sig[0]
        one = SDCond(cond.prompt, cond.embeddings[view : view + 1], cond.uncond)
        for s, s_next in itertools.pairwise(sig):
            D = self.denoise(x, torch.tensor([s]), one)
            x = D + (s_next / s) * (x - D)
        return self.decode_latents(x)


@dataclass(frozen=True)
class SDPriorConfig:
    """Stable Diffusion (``--prior sd``): the paper's prior, from a local diffusers folder or the
    Hugging Face cache, never downloaded (docs/stable_diffusion.md)."""

    kind: ClassVar[str] = "sd"
    sd_model: str = "tiny"
    """A local diffusers folder or a repo id in the Hugging Face cache (offline), or 'tiny'
    (random weights built from configs: smoke runs and tests, meaningless images)."""
    sd_mode: Literal["rgb", "latent"] = "rgb"
    """rgb: render RGB and encode it with the VAE (GaussianDiffusion); latent: render the 4 latent
    channels directly at 1/8 resolution (SJC)."""
    sd_guidance: Annotated[float, AtLeast(1)] = 100.0
    """Classifier-free guidance scale (SJC and DreamFusion use 100 with score distillation)."""
    sd_controlnet: Annotated[str | None, When("depth_conditioning", True), When("sd_model", not_=("tiny",))] = None
    """With --depth-conditioning: a depth ControlNet folder ('tiny' with the tiny model)."""
    sd_dtype: Literal["float32", "float16"] = "float32"
    """Weights' precision (float16 for CUDA; the Gaussians stay float32)."""
    semantic_code: bool = False
    """3DFuse's semantic code sampling (image, textual inversion, LoRA) before training; saved in
    <out>/semantic and reloaded on resume."""
    semantic_steps: Annotated[int, AtLeast(1), When("semantic_code", True)] = 100
    """Textual-inversion and LoRA steps of the semantic code."""
    depth_conditioning: bool = False
    """Condition the prior on the depth of the initial cloud (3DFuse's depth ControlNet)."""
    view_prompting: Literal["none", "buckets", "window"] = "window"
    """View-dependent prompting: DreamFusion/3DFuse's suffixes (', front view', ...) for
    'buckets' and 'window' alike, or none
    (docs/training.md)."""

    def __post_init__(self) -> None:
        check_fields(self, "prior.", options="")  # every field against its declared type, range and choices

    @property
    def input_space(self) -> str:
        """What the trainer renders for this prior: 'rgb' (encoded by the VAE) or 'latent' (the
        4 latent channels), with '+depth' when it conditions on depth."""
        return self.sd_mode + ("+depth" if self.depth_conditioning else "")

    def make(self, run: RunView) -> StableDiffusionPrior:
        """The prior of a training run, with its semantic code (made or reloaded)."""
        from gdbench.priors import network_device
        from gdbench.priors.sd.threedfuse import SemanticCodeConfig, load_semantic_code, semantic_code

        kw = dict(
            guidance_scale=self.sd_guidance,
            view_prompting=self.view_prompting != "none",
            dtype=getattr(torch, self.sd_dtype),
            device=network_device(run.device),
        )
        if self.sd_model == "tiny":
            prior = StableDiffusionPrior.tiny(seed=0, controlnet=self.depth_conditioning, **kw)
        else:
            controlnet = self.sd_controlnet if self.depth_conditioning else None
            if self.depth_conditioning and controlnet is None:
                raise ValueError(
                    "sd_controlnet: depth_conditioning with Stable Diffusion needs a depth ControlNet folder"
                )
            prior = StableDiffusionPrior.from_pretrained(self.sd_model, controlnet=controlnet, **kw)
        if self.semantic_code:
            folder = Path(run.out) / "semantic"
            if (folder / "semantic.json").is_file():
                load_semantic_code(prior, folder)
            else:
                n = self.semantic_steps
                sc = SemanticCodeConfig(size=max(64, run.resolution), ti_steps=n, lora_steps=n, seed=run.seed)
                semantic_code(prior, run.prompt, folder, sc)
        return prior
