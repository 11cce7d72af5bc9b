"""The method's knobs as command-line options shared by ``gdbench generate`` and ``gdbench
sweep``: each left at None keeps the preset's own value (docs/training.md, docs/noise.md)."""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Literal


@dataclass
class MethodOptions:
    """Overrides of the preset's method settings (unset: the preset's own)."""

    views_per_step: int | None = None
    """Views rendered per step; they share one jitter, one sigma and one draw of the noise
    colours (default 1)."""
    noise_redraw: Literal["run", "ou", "step"] | None = None
    """When the noise cloud's colours are redrawn: 'run' keeps one draw for the whole run (the
    paper: every view sees one fixed 3D source; the default), 'ou' drifts them slowly
    (Ornstein-Uhlenbeck, --noise-ou-beta), 'step' redraws every step (an ablation: no two steps
    share a source)."""
    noise_ou_beta: float | None = None
    """b of the Ornstein-Uhlenbeck drift c_t = sqrt(1 - b) c_{t-1} + sqrt(b) eps."""
    noise_ratio: Literal["amplitude", "variance"] | None = None
    """How the paper's 'proportion of structured noise' (0.3 -> 0.05) mixes: 'amplitude'
    (n = r n_s + sqrt(1 - r^2) n_iid) or 'variance' (n = sqrt(r) n_s + sqrt(1 - r) n_iid)."""
    vgs_gamma: float | None = None
    """gamma of the variational jitter (theta' = theta + gamma s(sigma) eps)."""
    vgs_unit: Literal["scene", "pixel"] | None = None
    """Length unit of the means' jitter: the scene radius or the training pixel's footprint."""
    view_prompting: Literal["window", "buckets", "none"] | None = None
    """View-dependent prompting of the prior: a +-45 degree window, DreamFusion buckets, or none
    (exposes the multi-face failure; DESIGN.md 'Priors')."""

    front_bias: float | None = None
    """Empirical prior: kappa of a front-heavy bank (view weights exp(kappa cos azimuth)), the
    mechanism of multi-face results; 0 is uniform."""

    variants: int | None = None
    """Empirical prior: procedural variants per caption in the bank (1..3): instance ambiguity."""

    densify_start: int | None = None
    """First step that densifies (default 300: the paper's)."""
    densify_stop: int | None = None
    """Last step that densifies (default 1500)."""
    densify_every: int | None = None
    """Densify every this many steps (default 50: the paper's)."""
    densify_reset_every: int | None = None
    """Opacity reset interval (default 400: the paper's); scale the schedule with --steps."""

    def overrides(self) -> dict[str, object]:
        """The set options as TrainConfig overrides (dotted keys for the noise group)."""
        key = {"noise_redraw": "noise.redraw", "noise_ou_beta": "noise.ou_beta", "noise_ratio": "noise.ratio_mode"}
        key |= {f"densify_{k}": f"densify.{k}" for k in ("start", "stop", "every", "reset_every")}
        return {
            key.get(f.name, f.name): getattr(self, f.name) for f in fields(self) if getattr(self, f.name) is not None
        }
