"""``gdbench noise --preview``: structured noise from 4 views of one source, and the per-pixel
histogram against N(0, 1)."""

from __future__ import annotations

import math
from pathlib import Path

import torch

from gdbench.core.camera import SphericalPoses
from gdbench.mechanisms.noise import (
    NoiseConfig,
    NoiseRenderer,
    autocorrelation_length,
    init_colors,
    make_noise_cloud,
    view_coupling,
)


def preview(out: Path, config: NoiseConfig | None = None, *, res: int = 128, seed: int = 0, draws: int = 64) -> dict:
    """Write the preview PNG; returns its statistics (coverage, KS distance, correlation length)."""
    from gdbench.core.plotting import pyplot, save

    plt = pyplot()
    from scipy import stats

    cfg = config or NoiseConfig()
    g = torch.Generator().manual_seed(seed)
    cloud = make_noise_cloud(cfg, 3, generator=g)
    az = torch.tensor([0.0, 30.0, 90.0, 180.0], dtype=torch.float64)
    poses = SphericalPoses(
        az,
        torch.full((4,), 15.0, dtype=torch.float64),
        torch.ones(4, dtype=torch.float64),
        torch.full((4,), 55.0, dtype=torch.float64),
    )
    cams = poses.cameras(res, res)
    renderer = NoiseRenderer(cloud, v_min=cfg.v_min)
    first = renderer.render(init_colors(cloud, generator=g).colors, cams, generator=g)
    # many independent sources for the statistics (channels are independent draws)
    many = make_noise_cloud(cfg, draws, generator=torch.Generator().manual_seed(seed))
    big = NoiseRenderer(many, v_min=cfg.v_min).render(init_colors(many, generator=g).colors, cams, generator=g)
    covered = big.coverage[..., 0].bool()
    values = big.noise[covered].flatten().double()
    ks = stats.kstest(values.numpy()[:: max(1, values.numel() // 200_000)], "norm")
    corr_len = autocorrelation_length(big.noise[0], big.coverage[0])
    coupling = view_coupling(cloud, poses.cameras(48, 48), v_min=cfg.v_min)

    fig = plt.figure(figsize=(13, 3.9), layout="constrained")  # constrained: the title is laid out too
    for i in range(4):
        ax = fig.add_subplot(1, 5, i + 1)
        img = (0.5 + 0.18 * first.noise[i]).clamp(0, 1).numpy()
        ax.imshow(img, interpolation="nearest")
        ax.contour(first.coverage[i, ..., 0].numpy(), levels=[0.5], colors="k", linewidths=0.6)
        ax.set_title(f"azimuth {az[i]:.0f}°", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    ax = fig.add_subplot(1, 5, 5)
    ax.hist(values.numpy(), bins=80, range=(-4.5, 4.5), density=True, color="#4c72b0", alpha=0.8, label="n_s(u)")
    xs = torch.linspace(-4.5, 4.5, 200)
    ax.plot(xs, torch.exp(-0.5 * xs**2) / math.sqrt(2 * math.pi), "k-", lw=1.2, label="N(0, 1)")
    ax.set_title(f"KS distance {ks.statistic:.4f}", fontsize=9)
    ax.legend(fontsize=7)
    fig.suptitle(
        f"Structured noise: one source, 4 views ({res}px, M={cfg.n_gaussians}, scale {cfg.scale}); "
        f"coverage {first.coverage_fraction:.2f} (black: edge of coverage, iid outside)\n"
        f"correlation length {corr_len:.1f} px; shared with view 1: "
        + ", ".join(f"{float(c):.2f} at {float(a):.0f}°" for a, c in zip(az[1:], coupling[1:])),
        fontsize=9,
    )
    save(fig, out, dpi=100)
    return {
        "path": str(out),
        "coverage": first.coverage_fraction,
        "ks_statistic": float(ks.statistic),
        "ks_pvalue": float(ks.pvalue),
        "correlation_length_px": corr_len,
        "view_coupling": {f"{float(a):.0f}": float(c) for a, c in zip(az, coupling)},
        "mean": float(values.mean()),
        "var": float(values.var()),
    }
