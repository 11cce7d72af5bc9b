"""Typed configuration of the reference trainer and its named presets.

Paper defaults (GaussianDiffusion, section 4): 2000 steps, 4096 initial points (grey,
opacity 0.1, in a sphere of radius 0.5), camera radius 1, fovy 40-70, azimuth [-180, 180],
elevation [-45, 45], white background, densify every 50 steps after step 300, opacity
reset every 400 steps. One departure, for the 2-core CPU: the training resolution is 64 px
(the paper renders 512 px for Stable Diffusion).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from pathlib import Path
from typing import Literal

from ..noise import NoiseConfig


@dataclass(frozen=True)
class OptimConfig:
    """Adam learning rates per parameter group (DreamGaussian's, scaled for 64 px)."""

    means: float = 1e-3
    """Initial learning rate of the means; decays exponentially to ``means_final``."""
    means_final: float = 2e-5
    colors: float = 0.01
    opacities: float = 0.05
    scales: float = 0.005
    quats: float = 0.005


@dataclass(frozen=True)
class DensifyConfig:
    """Adaptive density control (3DGS): clone small and split large Gaussians whose screen-space
    gradient is high, prune transparent or huge ones, reset opacities periodically."""

    enabled: bool = True
    start: int = 300
    """First step that densifies (paper: after step 300)."""
    stop: int = 1500
    """Last step that densifies."""
    every: int = 50
    """Densify every this many steps (paper: 50)."""
    grad_threshold: float = 2e-4
    """Mean screen-space gradient norm (per unit of half the image size, losses averaged over pixels)
    above which a Gaussian grows; 3DGS's default. About 5% of Gaussians exceed it mid-run (measured)."""
    percent_dense: float = 0.01
    """Scale (fraction of the scene radius) separating clone (below) from split (above)."""
    prune_opacity: float = 0.01
    """Gaussians below this opacity are pruned."""
    prune_scale: float = 0.5
    """Gaussians larger than this fraction of the scene radius are pruned."""
    reset_every: int = 400
    """Opacity reset interval (paper: 400 steps)."""
    reset_value: float = 0.05
    max_gaussians: int = 30000


@dataclass(frozen=True)
class TrainConfig:
    prompt: str = "a yellow duck"
    """What to generate (the empirical prior matches it to one of its assets' captions)."""
    preset: str = "gd"
    """Name of the preset this config came from (recorded in run.json)."""
    steps: int = 2000
    """Training steps (the paper: 2000)."""
    seed: int = 0
    """Seed of every random stream of the run (train/streams.py): presets with one seed are paired."""
    resolution: int = 64
    """Training render size (CPU-sized; the paper uses 512 with Stable Diffusion)."""
    views_per_step: int = 1
    """Views rendered per step; they share one jitter, one sigma and one draw of the noise cloud's
    colours (so one step already couples views through the structured noise)."""
    # initialisation
    init: Literal["sphere", "ply", "bank-depth"] = "sphere"
    """Initial Gaussians: the paper's sphere, a point cloud (--init-ply) or the prompt's bank depth."""
    init_points: int = 4096
    """Initial Gaussians (the paper: 4096)."""
    init_ply: Path | None = None
    """init='ply': any point cloud Open3D reads."""
    init_opacity: float = 0.1
    """Initial opacity (the paper: 0.1)."""
    init_color: float = 0.5
    """Initial grey level."""
    # cameras (paper)
    camera_radius: float = 1.0
    """Distance of the training cameras from the origin (the paper: 1)."""
    fovy_range: tuple[float, float] = (40.0, 70.0)
    """Vertical field of view of the training views, degrees, drawn uniformly (the paper: 40-70)."""
    azimuth_range: tuple[float, float] = (-180.0, 180.0)
    """Azimuth of the training views, degrees (the paper: all around)."""
    elevation_range: tuple[float, float] = (-45.0, 45.0)
    """Elevation of the training views, degrees (the paper: -45 to 45)."""
    background: tuple[float, float, float] = (1.0, 1.0, 1.0)
    """Background colour of the renders and of the prior's bank (the paper: white)."""
    # score distillation
    guidance: Literal["sjc", "sds"] = "sjc"
    """sjc: g = (D(x + sigma n) - x) / sigma with sigma uniform over the prior's ticks;
    sds: the same residual with DreamGaussian's annealed timestep and weight 1 - abar."""
    sigma_min: float = 0.03
    """Smallest noise level drawn (VE sigma)."""
    sigma_max: float = 10.0
    """Largest noise level drawn at the start of the run (VE sigma)."""
    anneal: bool = True
    """Anneal sigma: the upper end decays linearly to ``sigma_min`` over the run (measured on the
    duck: neutral with asset version 3, +1 to +1.7 dB with version 2; docs/training.md)."""
    samples_per_step: int = 1
    """K, perturb-and-average: noise samples averaged per step."""
    weight: float = 1.0
    """Global scale of the score (the 'guidance' multiplier)."""
    view_prompting: Literal["none", "buckets", "window"] = "window"
    """View-dependent prompting: DreamFusion/3DFuse buckets (front/side/back/overhead), a window
    of +-``view_window_deg`` around the camera azimuth, or none (DESIGN.md 'Priors')."""
    view_window_deg: float = 45.0
    """Half-width of the view window (view_prompting='window'), degrees."""
    front_bias: float = 0.0
    variants: int = 1
    """Empirical prior: procedural variants of the caption in the bank (1..3; the instance setting
    of the ablation uses 3)."""
    """Empirical prior: kappa of the front-heavy bank, pi_i ~ exp(kappa cos azimuth_i) (0: uniform;
    the Janus setting of the ablation uses it with view prompting off)."""
    depth_conditioning: bool = False
    """Condition the prior on depth (the ControlNet role; empirical prior: joint rgb-depth posterior)."""
    # the prior
    prior: Literal["empirical", "sd"] = "empirical"
    """empirical: the embedded CPU prior (image banks of procedural assets); sd: Stable Diffusion."""
    sd_model: str = "tiny"
    """sd: a local diffusers folder or a repo id in the Hugging Face cache (offline), or 'tiny'
    (random weights built from configs: smoke runs and tests, meaningless images)."""
    sd_mode: Literal["rgb", "latent"] = "rgb"
    """rgb: render RGB and encode it with the VAE (GaussianDiffusion); latent: render the 4 latent
    channels directly at 1/8 resolution (SJC)."""
    sd_guidance: float = 100.0
    """Classifier-free guidance scale (SJC and DreamFusion use 100 with score distillation)."""
    sd_controlnet: str | None = None
    """sd with depth_conditioning: a depth ControlNet folder ('tiny' with the tiny model)."""
    sd_dtype: Literal["float32", "float16"] = "float32"
    """sd: weights' precision (float16 for CUDA; the Gaussians stay float32)."""
    semantic_code: bool = False
    """sd: 3DFuse's semantic code sampling (image, textual inversion, LoRA) before training;
    saved in <out>/semantic and reloaded on resume."""
    semantic_steps: int = 100
    """Textual-inversion and LoRA steps of the semantic code."""
    # the paper's additions
    structured_noise: bool = True
    """Use the paper's structured noise (section 3.2)."""
    noise: NoiseConfig = field(default_factory=NoiseConfig)
    vgs: bool = True
    """Use the paper's variational Gaussians (section 3.3)."""
    vgs_gamma: float = 0.05
    """gamma of the jitter theta' = theta + gamma s(sigma) eps (means in ``vgs_unit``s, log-scales as is)."""
    vgs_unit: Literal["scene", "pixel"] = "scene"
    """Length unit of the means' jitter: the scene radius (0.5) or the training pixel's footprint at
    the origin (2 r tan(fovy/2) / resolution at the middle fovy), which follows the resolution."""
    # optimisation
    optim: OptimConfig = field(default_factory=OptimConfig)
    densify: DensifyConfig = field(default_factory=DensifyConfig)
    sh_degree: int = 0
    """Spherical-harmonics degree of the Gaussians' colours (0: plain colour)."""
    # run management
    out: Path = Path("runs/duck")
    """The run folder."""
    checkpoint_every: int = 200
    """Steps between checkpoints (a run also checkpoints on Ctrl-C)."""
    log_every: int = 10
    """Steps between progress-bar updates."""
    turntable_frames: int = 36
    """Frames of the output turntable."""
    progress: bool = True
    """Show a progress bar."""
    max_bad_steps: int = 20
    """Stop with an error after this many consecutive steps with non-finite gradients."""

    def __post_init__(self) -> None:
        checks = [
            ("steps", self.steps >= 1, "an int >= 1"),
            ("resolution", self.resolution >= 8, "at least 8 px"),
            ("views_per_step", self.views_per_step >= 1, "an int >= 1"),
            ("init_points", self.init_points >= 1, "an int >= 1"),
            ("init_opacity", 0 < self.init_opacity < 1, "a value in (0, 1)"),
            ("sigma_min", 0 < self.sigma_min < self.sigma_max, "0 < sigma_min < sigma_max"),
            ("samples_per_step", self.samples_per_step >= 1, "an int >= 1"),
            ("weight", self.weight > 0, "a positive value"),
            ("vgs_gamma", self.vgs_gamma >= 0, "a non-negative value"),
            ("checkpoint_every", self.checkpoint_every >= 1, "an int >= 1"),
            ("camera_radius", self.camera_radius > 0, "a positive distance"),
            ("sh_degree", self.sh_degree in (0, 1, 2, 3), "0..3"),
            ("vgs_unit", self.vgs_unit in ("scene", "pixel"), "'scene' or 'pixel'"),
            ("front_bias", self.front_bias >= 0, "kappa >= 0"),
        ]
        for name, ok, want in checks:
            if not ok:
                raise ValueError(f"{name}: expected {want}, got {getattr(self, name)!r}")
        if self.init == "ply" and self.init_ply is None:
            raise ValueError("init_ply: init='ply' needs a PLY path (--init-ply FILE)")
        if self.prior not in ("empirical", "sd"):
            raise ValueError(f"prior: expected 'empirical' or 'sd', got {self.prior!r}")
        if self.sd_mode not in ("rgb", "latent"):
            raise ValueError(f"sd_mode: expected 'rgb' or 'latent', got {self.sd_mode!r}")
        if self.prior == "sd" and self.resolution % 8:
            raise ValueError(f"resolution: the sd prior needs a multiple of 8 (latents are 1/8), got {self.resolution}")
        if self.prior == "sd" and self.sd_guidance < 1:
            raise ValueError(f"sd_guidance: expected >= 1, got {self.sd_guidance}")
        if self.guidance not in ("sjc", "sds"):
            raise ValueError(f"guidance: expected 'sjc' or 'sds', got {self.guidance!r}")


PRESETS: dict[str, TrainConfig] = {
    "gd": TrainConfig(preset="gd"),
    "gd-no-sn": TrainConfig(preset="gd-no-sn", structured_noise=False),
    "gd-no-vgs": TrainConfig(preset="gd-no-vgs", vgs=False),
    "sjc-gs": TrainConfig(preset="sjc-gs", structured_noise=False, vgs=False),
    "sds-gs": TrainConfig(preset="sds-gs", structured_noise=False, vgs=False, guidance="sds", anneal=True),
}
"""The paper's method, its two ablations and two baselines, written out by hand."""


NESTED = {"noise": NoiseConfig, "optim": OptimConfig, "densify": DensifyConfig}
"""Nested config groups an override may reach with a dotted key ('noise.redraw')."""


def apply_overrides(cfg: TrainConfig, overrides: Mapping[str, object]) -> TrainConfig:
    """``cfg`` with ``overrides`` applied: keys are TrainConfig fields, or 'group.field' for the
    nested groups in ``NESTED``; unknown keys raise ValueError naming them."""
    top: dict[str, object] = {}
    nested: dict[str, dict[str, object]] = {}
    for key, value in overrides.items():
        group, dot, name = key.partition(".")
        if dot:
            if group not in NESTED or name not in {f.name for f in fields(NESTED[group])}:
                raise ValueError(f"overrides: unknown setting {key!r}")
            nested.setdefault(group, {})[name] = value
        elif key not in {f.name for f in fields(TrainConfig)}:
            raise ValueError(f"overrides: unknown setting {key!r}")
        else:
            top[key] = value
    for group, values in nested.items():
        top[group] = replace(top.get(group, getattr(cfg, group)), **values)
    return replace(cfg, **top)


def preset(name: str, **overrides) -> TrainConfig:
    """The named preset with ``overrides`` (``apply_overrides``; pass dotted keys as a dict:
    ``preset("gd", **{"noise.redraw": "ou"})``)."""
    if name not in PRESETS:
        raise ValueError(f"preset: unknown {name!r}; expected one of {sorted(PRESETS)}")
    return apply_overrides(PRESETS[name], overrides)
