"""Rendering speed and memory of the splat renderer against the dense all-pairs path and
the peer renderers.

Sweep: N in {1k, 10k, 100k} x resolution in {64, 256, 512} x path x {forward, forward+backward}.
Paths: ``splat`` (C++ compositor), ``splat_torch`` (the pure-torch compositor, any device),
``dense`` (``renderers.splat.reference`` in float32: every Gaussian at every pixel), and with
``--peers`` the references: ``gsplat_torch`` (gsplat 1.5.3's torch stages, completed on CPU)
and ``mitsuba_ellipsoids`` (Mitsuba 3 ray-traced ellipsoids, forward only, 4 spp). Slow paths run only
where they fit in time and memory (``LIMITS``); skipped cells are written with the reason.
Each case runs in its own process so that its peak RSS is its own.

    python -m gdbench.refcheck.bm_render --out bench_results/render.csv       # full sweep
    python -m gdbench.refcheck.bm_render --peers --out bench_results/peers.csv  # vs gsplat, Mitsuba
    python -m gdbench.refcheck.bm_render --quick --inprocess --out /tmp/r.csv # smoke

Writes the CSV, ``<stem>_summary.json`` (targets, fits) and ``<stem>_fit.png``.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import torch

from gdbench.bench.common import environment, peak_rss_mb, random_cloud, rss_mb, timeit, write_csv, write_json
from gdbench.core.io import nulls_to_nan

PATHS = ("splat", "splat_torch", "dense")
PEER_PATHS = ("splat", "gsplat_torch", "mitsuba_ellipsoids")
MITSUBA_SPP = 4
MODES = ("fwd", "fwd+bwd")
FULL = {"n": (1_000, 10_000, 100_000), "res": (64, 256, 512)}
QUICK = {"n": (300, 1_000), "res": (32, 64)}
# Upper limits of N x pixels per (path, mode): dense all-pairs cost is N x pixels, beyond these
# it takes minutes (fwd) or tens of GB (bwd); gsplat's torch compositing holds a
# [tiles, 256 px, Gaussians-per-tile] tensor; Mitsuba's ellipsoids are forward-only here.
LIMITS = {
    ("dense", "fwd"): 7e8,
    ("dense", "fwd+bwd"): 3e7,
    ("gsplat_torch", "fwd"): 7e9,
    ("gsplat_torch", "fwd+bwd"): 7e8,
    ("mitsuba_ellipsoids", "fwd"): 3e10,
    ("mitsuba_ellipsoids", "fwd+bwd"): 0,
}
TARGETS = {
    "gsplat_over_splat_fwd_10k_256": 10.0,  # splat forward at least 10x faster than gsplat's torch path
    "dense_over_splat_fwd_10k_256": 20.0,  # splat forward at least 20x faster than dense
    "splat_fwd_10k_256_s": 0.012,  # forward at most 12 ms (issue: the step's unit cost)
    "splat_fwdbwd_10k_256_s": 0.025,  # forward+backward at most 25 ms
    "splat_fit_intercept_s": 0.003,  # fixed cost per call (the fit's intercept) at most 3 ms
    "splat_peak_rss_mb_100k_512": 2048.0,  # 100k Gaussians at 512x512 within 2 GB
}


def _camera(res: int, device: str):
    from gdbench.core.camera import SphericalPoses

    return SphericalPoses.orbit(1, radius=1.5, elevation=20.0, fovy=50.0).cameras(res, res).to(device)


def count_intersections(scene: dict, cams, tile_size: int = 16) -> int:
    """Tile-Gaussian intersections of the scene in these cameras (the splat renderer's work)."""
    from renderers.splat.bin_tiles import bin_tiles
    from renderers.splat.project import project

    with torch.no_grad():
        p = project(
            scene["means"],
            scene["quats"],
            scene["scales"],
            scene["opacities"],
            cams.viewmats,
            cams.Ks,
            cams.width,
            cams.height,
        )
        return int(
            bin_tiles(p.means2d, p.radii, p.depths, p.visible, cams.width, cams.height, tile_size).gauss_ids.numel()
        )


FIXED = ("splat_fixed", 1, 256, "fwd")
"""The fixed cost per call, measured directly: one small Gaussian at 256 px (checks, projection,
binning, 256 empty tiles' set-up and output, allocations), next to the fit's intercept."""


def _scene(path: str, n: int, seed: int = 0) -> dict[str, torch.Tensor]:
    if path == FIXED[0]:  # one Gaussian of ~1 px at the centre
        cloud = random_cloud(n, seed=seed)
        return cloud | {"means": torch.zeros(n, 3), "scales": torch.full((n, 3), 2e-3)}
    return random_cloud(n, seed=seed)


def setup(path: str, n: int, res: int, mode: str, device: str = "cpu", seed: int = 0) -> Callable[[], object]:
    """The closure that renders (and back-propagates) one case."""
    from renderers.splat.reference import rasterize_reference

    scene = {k: v.to(device) for k, v in _scene(path, n, seed).items()}
    cams = _camera(res, device)
    view = dict(viewmats=cams.viewmats, Ks=cams.Ks, width=res, height=res)
    if path == "dense":

        def render(**s):
            return rasterize_reference(**s, **view, dtype=torch.float32, pixel_chunk=8192 if mode == "fwd" else None)
    else:
        from gdbench.refcheck.backends import get

        backend = get("splat" if path == FIXED[0] else path)

        def render(**s):
            return backend.render(**s, **view, speed=True)

    if mode == "fwd":

        def fwd():
            with torch.no_grad():
                return render(**scene).rgb

        return fwd
    params = {k: v.clone().requires_grad_(True) for k, v in scene.items()}
    g = torch.Generator(device=device).manual_seed(seed)
    cot = torch.randn(1, res, res, 3, generator=g, device=device)

    def fwd_bwd():
        for p in params.values():
            p.grad = None
        out = render(**params)
        ((out.rgb * cot).sum() + out.alpha.sum()).backward()

    return fwd_bwd


def run_case(path: str, n: int, res: int, mode: str, device: str = "cpu") -> dict:
    """Time one case in this process; returns one CSV row."""
    row = {"path": path, "n": n, "res": res, "mode": mode, "device": device, "pixels": res * res}
    fn = setup(path, n, res, mode, device)
    from gdbench.bench.roofline import pixel_pairs

    scene = {k: v.to(device) for k, v in _scene(path, n).items()}
    row["intersections"] = count_intersections(scene, _camera(res, device))
    row["pixel_pairs"] = pixel_pairs(scene, _camera(res, device))
    if device == "cuda":
        torch.cuda.reset_peak_memory_stats()
    base = rss_mb()
    slow = path in ("dense", "gsplat_torch", "mitsuba_ellipsoids")
    t = timeit(fn, device=device, warmup=1 if slow else 2, min_repeats=1 if slow else 3, budget_s=2.0)
    row.update(t)
    row["peak_rss_mb"] = peak_rss_mb()
    row["peak_above_start_mb"] = max(0.0, row["peak_rss_mb"] - base)
    row |= compositor_work(path, fn)
    if device == "cuda":
        row["peak_cuda_mb"] = torch.cuda.max_memory_allocated() / 2**20
    row["status"] = "ok"
    return row


WORK = ("fwd_pairs_visited", "fwd_blocks", "bwd_pairs_visited", "bwd_blocks")
"""The C++ compositor's work in one call (its ``work_counters``): tile-Gaussian pairs visited and
8-pixel blocks evaluated, forward and backward. Early termination and the ellipse spans make
these the work done, where ``intersections`` (every tile-Gaussian pair listed) and
``pixel_pairs`` (every pixel of every box) count work that is skipped."""


def compositor_work(path: str, fn: Callable[[], object]) -> dict:
    """One more call of ``fn`` with the C++ compositor's work counters read around it (splat paths
    on CPU only; {} elsewhere)."""
    from renderers.splat._ext import load_extension

    ext = load_extension() if path in ("splat", FIXED[0]) else None
    if ext is None:
        return {}
    ext.work_counters(True)
    fn()
    return dict(zip(WORK, ext.work_counters(True)))


def _skip_reason(path: str, n: int, res: int, mode: str) -> str | None:
    limit = LIMITS.get((path, mode))
    if limit == 0:
        return f"skipped: {path} is timed {'forward only' if mode == 'fwd+bwd' else 'backward only'}"
    if limit is not None and n * res * res > limit:
        return f"skipped: {path} {mode} of N x pixels = {n * res * res:.1e} > {limit:.0e}"
    return None


def _fit(rows: list[dict], key: str | tuple[str, ...]) -> dict:
    """Least-squares time = a + sum_k b_k * rows[k] over one key or several; returns a, the b
    (``slope_s`` for one key, ``slopes_s`` by key for several) and R^2."""
    keys = (key,) if isinstance(key, str) else key
    X = torch.tensor([[float(r[k]) for k in keys] for r in rows], dtype=torch.float64)
    y = torch.tensor([float(r["median_s"]) for r in rows], dtype=torch.float64)
    A = torch.cat([torch.ones(len(rows), 1, dtype=torch.float64), X], 1)
    coef = torch.linalg.lstsq(A, y[:, None]).solution[:, 0]
    resid = y - A @ coef
    r2 = 1 - float((resid**2).sum() / ((y - y.mean()) ** 2).sum()) if len(rows) > len(keys) + 1 else float("nan")
    # the intercept's standard error (ordinary least squares): an extrapolation to zero work, so
    # its spread says how far to trust it
    dof = len(rows) - A.shape[1]
    se = float("nan")
    if dof > 0:
        cov = float((resid**2).sum()) / dof * torch.linalg.pinv(A.T @ A)
        se = float(cov[0, 0].clamp_min(0).sqrt())
    out = {"intercept_s": float(coef[0]), "intercept_se_s": se, "r2": r2, "points": len(rows)}
    if isinstance(key, str):
        return out | {"slope_s": float(coef[1])}
    return out | {"slopes_s": {k: float(c) for k, c in zip(keys, coef[1:])}}


def _work_fit(rows: list[dict]) -> dict | None:
    """time = a + b blocks + c N: the compositor's 8-pixel blocks evaluated (forward plus backward)
    and the Gaussians projected, binned and set up; a is the fixed cost per call, an extrapolation
    to zero work (its standard error comes with it). A per-pixel term (the pixels each call
    initialises and lays out) was tried: over a 64-512 px sweep it is collinear with the blocks
    and came out negative. None without the work counters or with fewer than 4 points."""
    if len(rows) < 4 or not all("fwd_blocks" in r for r in rows):
        return None
    work = [r | {"blocks": int(r["fwd_blocks"]) + int(r.get("bwd_blocks") or 0)} for r in rows]
    return _fit(work, ("blocks", "n")) | {"model": "time = a + b blocks + c N (a: fixed cost per call)"}


def _loglog(rows: list[dict], key: str) -> dict:
    """Fit log(time) = c + k log(rows[key]): k ~ 1 means time proportional to that quantity."""
    logged = [{"x": math.log(float(r[key])), "median_s": math.log(float(r["median_s"]))} for r in rows]
    f = _fit(logged, "x")
    return {"exponent": f["slope_s"], "r2": f["r2"], "points": f["points"]}


def summarise(rows: list[dict]) -> dict:
    ok = [r for r in rows if r.get("status") == "ok"]

    def find(path, n, res, mode):
        return next((r for r in ok if (r["path"], int(r["n"]), int(r["res"]), r["mode"]) == (path, n, res, mode)), None)

    out: dict = {"environment": environment(), "targets": {}, "fits": {}}
    s = find("splat", 10_000, 256, "fwd")
    for peer in ("dense", "gsplat_torch"):
        d = find(peer, 10_000, 256, "fwd")
        if s and d:
            key = f"{peer.split('_')[0]}_over_splat_fwd_10k_256"
            ratio, target = float(d["median_s"]) / float(s["median_s"]), TARGETS[key]
            out["targets"][key] = {"value": ratio, "target": f">= {target}", "met": ratio >= target}
    # every peer against splat, case by case (same run, same machine state)
    for r in ok:
        if r["path"] != "splat":
            base = find("splat", int(r["n"]), int(r["res"]), r["mode"])
            if base:
                r["time_over_splat"] = float(r["median_s"]) / float(base["median_s"])
    for mode, key in (("fwd", "splat_fwd_10k_256_s"), ("fwd+bwd", "splat_fwdbwd_10k_256_s")):
        r = find("splat", 10_000, 256, mode)
        if r:
            v, target = float(r["median_s"]), TARGETS[key]
            out["targets"][key] = {"value": v, "target": f"<= {target}", "met": v <= target}
    big = [r for r in (find("splat", 100_000, 512, m) for m in MODES) if r]
    if big:
        v, target = max(float(r["peak_rss_mb"]) for r in big), TARGETS["splat_peak_rss_mb_100k_512"]
        out["targets"]["splat_peak_rss_mb_100k_512"] = {"value": v, "target": f"<= {target}", "met": v <= target}
    for path in ("splat", "splat_torch", "gsplat_torch", "mitsuba_ellipsoids"):
        for mode in MODES:
            sel = [r for r in ok if r["path"] == path and r["mode"] == mode]
            if len(sel) >= 3:
                for r in sel:
                    r["n_x_pixels"] = int(r["n"]) * int(r["pixels"])
                out["fits"][f"{path} {mode}"] = {
                    **({"vs_work": w} if (w := _work_fit(sel)) else {}),
                    "vs_intersections": _fit(sel, "intersections"),
                    "vs_n_x_pixels": _fit(sel, "n_x_pixels"),
                    "loglog_vs_intersections": _loglog(sel, "intersections"),
                    "loglog_vs_n_x_pixels": _loglog(sel, "n_x_pixels"),
                }
    _roofline(out, find)
    return out


def _roofline(out: dict, find) -> None:
    """The distance of splat's 10k/256 px case to the floating-point bound, and its fixed cost."""
    from gdbench.bench.roofline import flop_fraction, peak_gflops

    peak = peak_gflops()
    out["roofline"] = {}
    for mode in MODES:
        r = find("splat", 10_000, 256, mode)
        if r and r.get("pixel_pairs"):
            out["roofline"][f"splat {mode} 10k 256"] = flop_fraction(
                int(r["pixel_pairs"]), float(r["median_s"]), mode, peak
            )
        if r and r.get("fwd_blocks"):  # the lanes the forward evaluated (8 per block), counted
            out["roofline"][f"splat {mode} 10k 256, counted lanes"] = flop_fraction(
                int(r["fwd_blocks"]) * 8, float(r["median_s"]), mode, peak
            ) | {"pairs_are": "8 x the forward's blocks (work_counters): early termination and the spans, counted"}
    # the fixed cost is the intercept of the fit against the work done (blocks and N) where the
    # compositor's counters are at hand; against intersections (most of which early termination
    # skips: 32k of 74k visited at 10k/256 px) it also holds per-pixel and per-Gaussian work
    fits = out["fits"].get("splat fwd", {})
    key = "vs_work" if "vs_work" in fits else "vs_intersections"
    if key in fits:
        v, target = fits[key]["intercept_s"], TARGETS["splat_fit_intercept_s"]
        entry = {"value": v, "target": f"<= {target}", "met": v <= target, "fit": key, "r2": fits[key]["r2"]}
        slopes = fits[key].get("slopes_s") or {key.removeprefix("vs_"): fits[key]["slope_s"]}
        negative = [k for k, b in slopes.items() if not b >= 0]
        if negative:  # work that takes negative time: the fit says nothing about the fixed cost
            entry |= {"met": None, "why": f"the fit is not physical: negative cost per {', '.join(negative)}"}
        out["targets"]["splat_fit_intercept_s"] = entry
    r = find(*FIXED)
    if r:  # the same bound for the direct measure (reported; the target is the intercept)
        v, target = float(r["median_s"]), TARGETS["splat_fit_intercept_s"]
        out["fixed_cost"] = {"value": v, "target": f"<= {target}", "met": v <= target,
                             "what": "splat forward of one ~1 px Gaussian at 256 px"}  # fmt: skip


def plot(rows: list[dict], path: Path) -> Path:
    from gdbench.core.plotting import pyplot, save

    plt = pyplot()

    ok = [r for r in rows if r.get("status") == "ok"]
    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label in ((axes[0], "intersections", "tile-Gaussian intersections"), (axes[1], None, "N x pixels")):
        for p, marker in zip(PATHS + PEER_PATHS[1:], "os^dv"):
            for mode, fill in zip(MODES, ("full", "none")):
                sel = [r for r in ok if r["path"] == p and r["mode"] == mode]
                if not sel:
                    continue
                x = [float(r[key]) if key else int(r["n"]) * int(r["pixels"]) for r in sel]
                ax.loglog(x, [float(r["median_s"]) for r in sel], marker, fillstyle=fill, label=f"{p} {mode}")
        ax.set_xlabel(label)
        ax.set_ylabel("median time (s)")
        ax.grid(True, which="both", alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.suptitle("renderers.splat: time against work (one process per case)")
    return save(fig, path, dpi=110)


def sweep(
    out: Path,
    *,
    quick: bool = False,
    inprocess: bool = False,
    paths=PATHS,
    device: str = "cpu",
    timeout_s: float = 1800.0,
) -> list[dict]:
    grid = QUICK if quick else FULL
    cases = list(itertools.product(paths, grid["n"], grid["res"], MODES))
    cases = ([FIXED] if "splat" in paths and not quick else []) + cases
    rows: list[dict] = []
    from gdbench.core.progress import track

    it = track(cases, desc="bm_render", unit="case")
    for path, n, res, mode in it:
        reason = _skip_reason(path, n, res, mode)
        if reason:
            rows.append({"path": path, "n": n, "res": res, "mode": mode, "device": device, "status": reason})
            continue
        t0 = time.perf_counter()
        if inprocess:
            row = run_case(path, n, res, mode, device)
        else:
            spec = json.dumps({"path": path, "n": n, "res": res, "mode": mode, "device": device})
            try:
                proc = subprocess.run(
                    [sys.executable, "-m", "gdbench.refcheck.bm_render", "--worker", spec],
                    capture_output=True,
                    text=True,
                    timeout=timeout_s,
                )
                row = (
                    json.loads(proc.stdout.strip().splitlines()[-1])
                    if proc.returncode == 0
                    else {
                        "path": path,
                        "n": n,
                        "res": res,
                        "mode": mode,
                        "device": device,
                        "status": "failed: " + (proc.stderr.strip().splitlines() or [str(proc.returncode)])[-1],
                    }
                )
            except subprocess.TimeoutExpired:
                row = {
                    "path": path,
                    "n": n,
                    "res": res,
                    "mode": mode,
                    "device": device,
                    "status": f"timeout after {timeout_s:.0f} s",
                }
        row["wall_s"] = time.perf_counter() - t0
        rows.append(row)
        write_csv(rows, out)  # incremental: an interrupted sweep keeps what it measured
    summary = summarise(rows)  # (adds time_over_splat to the peers' rows)
    write_csv(rows, out)
    write_json(summary, out.with_name(out.stem + "_summary.json"))
    plot(rows, out.with_name(out.stem + "_fit.png"))
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/render.csv"), help="CSV to write")
    ap.add_argument("--quick", action="store_true", help="small sweep (N 300/1000, 32/64 px) for smoke tests")
    ap.add_argument("--inprocess", action="store_true", help="run cases in this process (peak memory is shared)")
    ap.add_argument("--backend", choices=("all", *PATHS, *PEER_PATHS[1:]), default="all", help="one path only")
    ap.add_argument("--peers", action="store_true", help="splat vs gsplat-torch vs Mitsuba ellipsoids")
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    ap.add_argument("--summarise", action="store_true", help="recompute summary and plot from an existing --out CSV")
    args = ap.parse_args(argv)
    if args.worker:
        spec = json.loads(args.worker)
        print(json.dumps(run_case(**spec)))
        return 0
    if args.summarise:
        import csv

        rows = [{k: v for k, v in r.items() if v != ""} for r in csv.DictReader(args.out.open())]
        for r in rows:
            r["n"], r["res"] = int(r["n"]), int(r["res"])
        write_json(summarise(rows), args.out.with_name(args.out.stem + "_summary.json"))
        plot(rows, args.out.with_name(args.out.stem + "_fit.png"))
        report(rows, _read_summary(args.out), args.out)
        return 0
    paths = (PEER_PATHS if args.peers else PATHS) if args.backend == "all" else (args.backend,)
    rows = sweep(args.out, quick=args.quick, inprocess=args.inprocess, paths=paths, device=args.device)
    report(rows, _read_summary(args.out), args.out)
    return 0


def _read_summary(out: Path) -> dict:
    """The summary as written (strict JSON), with its nulls back as NaN for the report."""
    return nulls_to_nan(json.loads(out.with_name(out.stem + "_summary.json").read_text()))


def report(rows: list[dict], summary: dict, out: Path) -> None:
    print(f"\n{'path':12s} {'N':>7s} {'res':>4s} {'mode':8s} {'median s':>9s} {'peak MB':>8s}  status")
    for r in rows:
        t = f"{float(r['median_s']):9.4f}" if "median_s" in r else " " * 9
        m = f"{float(r['peak_rss_mb']):8.0f}" if "peak_rss_mb" in r else " " * 8
        print(f"{r['path']:12s} {r['n']:>7d} {r['res']:>4d} {r['mode']:8s} {t} {m}  {r['status']}")
    for k, v in summary["targets"].items():
        verdict = f"not decided ({v['why']})" if v["met"] is None else "met" if v["met"] else "NOT met"
        print(f"target {k}: {v['value']:.4g} (want {v['target']}) -> {verdict}")
    if "fixed_cost" in summary:
        v = summary["fixed_cost"]
        print(f"fixed cost per call, measured directly ({v['what']}): {v['value']:.4g} s (want {v['target']})")
    for k, v in summary["fits"].items():
        if "vs_work" in v:
            w = v["vs_work"]
            b, c = w["slopes_s"]["blocks"], w["slopes_s"]["n"]
            print(f"fit {k} vs work: ({w['intercept_s'] * 1e3:.2f} +- {w['intercept_se_s'] * 1e3:.2f}) ms + "
                  f"{b * 1e9:.1f} ns/block + {c * 1e9:.0f} ns/Gaussian (R^2 {w['r2']:.3f})")  # fmt: skip
        r2i, r2n = v["vs_intersections"]["r2"], v["vs_n_x_pixels"]["r2"]
        ki, kn = v["loglog_vs_intersections"]["exponent"], v["loglog_vs_n_x_pixels"]["exponent"]
        print(
            f"fit {k}: linear R^2 vs intersections {r2i:.3f}, vs N x pixels {r2n:.3f}; "
            f"time ~ intersections^{ki:.2f}, ~ (N x pixels)^{kn:.2f}"
        )
    print(f"wrote {out}, {out.stem}_summary.json, {out.stem}_fit.png")


if __name__ == "__main__":
    raise SystemExit(main())
