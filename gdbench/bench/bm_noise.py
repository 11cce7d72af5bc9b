"""Cost of structured noise against a training step's render.

For each resolution (64, 128, 512 px), times (a) structured noise for one random training
view (projection of the noise cloud, compositing C and V, normalisation, iid fill) and
(b) the forward+backward render of a 4096-Gaussian scene for one random view (the render a
training step needs), and writes their ratio. Target: at most 30% at 128 px.
Also records the coverage fraction and the spatial correlation length of the noise.

    python -m gdbench.bench.bm_noise --out bench_results/noise.csv
"""

from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import asdict
from pathlib import Path

import torch

from gdbench.bench.common import environment, random_cloud, write_csv, write_json

TARGET_SHARE_128 = 0.30


def interleaved(a, b, *, budget_s: float, warmup: int = 3, min_repeats: int = 7) -> tuple[float, float]:
    """Median times of ``a`` and ``b`` measured alternately, so that load changes on a shared
    machine hit both alike."""
    for _ in range(warmup):
        a(), b()
    ta, tb = [], []
    start = time.perf_counter()
    while len(ta) < min_repeats or (time.perf_counter() - start < budget_s and len(ta) < 200):
        t0 = time.perf_counter()
        a()
        t1 = time.perf_counter()
        b()
        t2 = time.perf_counter()
        ta.append(t1 - t0)
        tb.append(t2 - t1)
    return statistics.median(ta), statistics.median(tb)


def measure(res: int, *, scene_n: int = 4096, seed: int = 0, budget_s: float = 3.0, config=None) -> dict:
    from gdbench.core.camera import SphericalPoses
    from gdbench.mechanisms.noise import (
        NoiseConfig,
        NoiseRenderer,
        autocorrelation_length,
        init_colors,
        make_noise_cloud,
    )
    from renderers.splat import rasterize

    cfg = config or NoiseConfig()
    cloud = make_noise_cloud(cfg, 3, generator=torch.Generator().manual_seed(seed))
    g = torch.Generator().manual_seed(seed + 1)
    renderer = NoiseRenderer(cloud, v_min=cfg.v_min, cache_size=0)  # training views never repeat
    state = init_colors(cloud, generator=g)
    scene = {k: v.requires_grad_(True) for k, v in random_cloud(scene_n, seed=seed).items()}
    bg = torch.ones(3)

    # A training step builds its camera once for the render and the noise: cameras are made
    # outside both timed closures, a fresh one per repetition (training views never repeat).
    views = [SphericalPoses.sample(1, generator=g).cameras(res, res) for _ in range(256)]
    it = {"noise": 0, "step": 0}

    def next_view(key: str):
        it[key] += 1
        return views[it[key] % len(views)]

    def noise():
        return renderer.render(state.colors, next_view("noise"), generator=g)

    def step():
        cams = next_view("step")
        out = rasterize(**scene, viewmats=cams.viewmats, Ks=cams.Ks, width=res, height=res, background=bg)
        (out.rgb.sum() + out.alpha.sum()).backward()

    t_noise, t_step = interleaved(noise, step, budget_s=budget_s)
    many = make_noise_cloud(cfg, 256, generator=torch.Generator().manual_seed(seed))
    cams = SphericalPoses.sample(1, generator=torch.Generator().manual_seed(seed + 2)).cameras(res, res)
    out = NoiseRenderer(many, v_min=cfg.v_min).render(init_colors(many, generator=g).colors, cams, generator=g)
    return {
        "res": res,
        "noise_gaussians": cfg.n_gaussians,
        "noise_scale": cfg.scale,
        "noise_opacity": cfg.opacity,
        "scene_gaussians": scene_n,
        "noise_s": t_noise,
        "step_render_fwd_bwd_s": t_step,
        "share": t_noise / t_step,
        "coverage": out.coverage_fraction,
        "correlation_length_px": autocorrelation_length(out.noise[0], out.coverage[0]),
    }


def plot(rows: list[dict], path: Path) -> Path:
    from gdbench.core.plotting import pyplot, save

    plt = pyplot()

    fig, ax = plt.subplots(figsize=(5.5, 3.6))
    res = [r["res"] for r in rows]
    ax.bar([str(x) for x in res], [100 * r["share"] for r in rows], color="#4c72b0")
    ax.axhline(100 * TARGET_SHARE_128, color="k", ls="--", lw=1, label="target at 128 px (30%)")
    for i, r in enumerate(rows):
        ax.text(i, 100 * r["share"] + 1, f"{1e3 * r['noise_s']:.1f} ms", ha="center", fontsize=8)
    ax.set_xlabel("resolution (px)")
    ax.set_ylabel("structured noise / training render (%)")
    ax.set_title(f"Structured noise overhead (M={rows[0]['noise_gaussians']}, 4k-Gaussian scene)", fontsize=9)
    ax.legend(fontsize=8)
    return save(fig, path, dpi=110)


def main(argv: list[str] | None = None) -> int:
    from gdbench.mechanisms.noise import NoiseConfig

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/noise.csv"))
    ap.add_argument("--res", type=int, nargs="+", default=[64, 128, 512])
    ap.add_argument("--budget", type=float, default=3.0, help="seconds of timed repeats per measurement")
    args = ap.parse_args(argv)
    rows = []
    for res in args.res:
        rows.append(measure(res, budget_s=args.budget))
        r = rows[-1]
        print(
            f"{res:4d} px: noise {1e3 * r['noise_s']:7.2f} ms,"
            f" render fwd+bwd {1e3 * r['step_render_fwd_bwd_s']:7.2f} ms,"
            f" share {100 * r['share']:5.1f}%, coverage {r['coverage']:.2f},"
            f" corr. length {r['correlation_length_px']:.1f} px"
        )
    write_csv(rows, args.out)
    at128 = next((r for r in rows if r["res"] == 128), None)
    summary = {"environment": environment(), "config": asdict(NoiseConfig()), "rows": rows}
    if at128:
        summary["target_share_128"] = {
            "value": at128["share"],
            "target": f"<= {TARGET_SHARE_128}",
            "met": at128["share"] <= TARGET_SHARE_128,
        }
        print(
            f"target share at 128 px: {100 * at128['share']:.1f}% (want <= 30%) -> "
            f"{'met' if summary['target_share_128']['met'] else 'NOT met'}"
        )
    write_json(summary, args.out.with_name(args.out.stem + "_summary.json"))
    plot(rows, args.out.with_name(args.out.stem + "_overhead.png"))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
