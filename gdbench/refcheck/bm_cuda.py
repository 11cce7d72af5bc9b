"""On a GPU: the renderer on CUDA (the gsplat backend and the torch path) against gsplat's CUDA
rasterizer and the C++ compositor (agreement and speed), the training step on both devices, and
the C++ compositor's scaling with CPU threads.

    python -m gdbench.refcheck.bm_cuda --out bench_results/cuda            # all four parts
    python -m gdbench.refcheck.bm_cuda --parts threads --out /tmp/cuda     # CPU part only

Parts (``--parts``):
- ``agreement``: every fixture scene and a random SH-3 scene, rendered by ``renderers.splat``
  on CUDA (the torch path, and the 'gsplat' backend: our conventions on gsplat's kernels) and by
  ``gsplat.rasterization`` (1.5.3, CUDA kernels, compiled by gsplat on first use): max and mean
  absolute difference of rgb, alpha, expected depth and of the gradients of one loss, with
  gsplat's alpha clamp (0.999) and with ours (0.99: the backend's opacity cap); each against the
  C++ compositor on the CPU (our own device consistency).
- ``speed``: forward and forward+backward at N in {10k, 100k, 1M} and 256, 512 px and 1080p,
  medians with CUDA synchronisation and peak GPU memory (``PATHS``: the gsplat backend, gsplat
  itself, our torch path, the C++ compositor on the CPU's cores); a profile of the torch path at
  100k / 512 px (the kernels that take the time).
- ``trainer``: the training step of the default gd run on the duck (``TRAIN_CASES``): at 64 px
  on the empirical and the learned prior, on the CPU and on CUDA with the gsplat backend (the
  default there) and with the torch path; at 256 and 512 px on the tiny SD models; median step
  and its parts, and a profile of the CUDA steps; and how many of the speed part's 1M Gaussians
  each renderer draws (gsplat's radii > 0, our visible flags).
- ``threads``: the C++ compositor (CPU) at 10k / 256 px and 100k / 512 px, forward and
  forward+backward, on 1, 2, 4, ... up to the machine's cores.

Writes agreement.csv, speed.csv, trainer.csv, threads.csv, profile.txt, trainer_profile.txt and
cuda_summary.json into --out. A
part that cannot run (no CUDA, gsplat missing or failing to compile) writes its reason instead.
"""

from __future__ import annotations

import argparse
import os
import time
import traceback
from pathlib import Path

import torch

from gdbench.bench.common import environment, random_cloud, timeit, write_csv, write_json

SIZES = {"256": (256, 256), "512": (512, 512), "1080p": (1920, 1080)}
COUNTS = (10_000, 100_000, 1_000_000)
GSPLAT_ALPHA_MAX = 0.999
"""gsplat 1.5.3's clamp in its CUDA kernels; ours defaults to Inria's 0.99."""


def _camera(width: int, height: int, device, radius: float = 1.6):
    from gdbench.core.camera import SphericalPoses

    return (
        SphericalPoses.orbit(1, radius=radius, elevation=20.0, fovy=50.0, start=30.0).cameras(width, height).to(device)
    )


def _ours(args: dict, cams, *, alpha_max: float, backend: str = "torch"):
    from renderers.splat import rasterize

    return rasterize(
        **args,
        viewmats=cams.viewmats,
        Ks=cams.Ks,
        width=cams.width,
        height=cams.height,
        outputs=("rgb", "alpha", "depth"),
        alpha_max=alpha_max,
        backend=backend,
    )


def _ours_images(alpha_max: float, backend: str = "torch"):
    """(rgb, alpha, depth) of ours, as ``_gsplat`` gives them."""

    def fn(args: dict, cams):
        r = _ours(args, cams, alpha_max=alpha_max, backend=backend)
        return r.rgb, r.alpha, r.depth

    return fn


def _gsplat(args: dict, cams):
    from gsplat import rasterization

    rgbd, alpha, _ = rasterization(
        args["means"],
        args["quats"],
        args["scales"],
        args["opacities"],
        args["colors"],
        cams.viewmats,
        cams.Ks,
        cams.width,
        cams.height,
        near_plane=0.01,
        far_plane=1e10,
        eps2d=0.3,
        sh_degree=args["sh_degree"],
        packed=False,
        render_mode="RGB+ED",  # expected depth sum w z / alpha, as ours
    )
    return rgbd[..., :3], alpha, rgbd[..., 3:]


def _scenes() -> dict:
    """Every fixture scene with its cameras, and a random cloud with random SH-3 coefficients."""
    from gdbench.core.scene import GaussianScene
    from gdbench.refcheck.scenes import fixture_names, load_fixture

    out = {}
    for name in fixture_names():
        f = load_fixture(name)
        out[name] = (f.scene, f.cameras)
    c = random_cloud(20_000, seed=3)
    g = torch.Generator().manual_seed(4)
    sh = torch.cat(
        [((c["colors"] - 0.5) / 0.28209479177387814)[:, None], 0.2 * torch.randn(20_000, 15, 3, generator=g)], 1
    )
    sh3 = GaussianScene(c["means"], torch.nn.functional.normalize(c["quats"], dim=-1), c["scales"].log(),
                        torch.logit(c["opacities"].clamp(1e-4, 1 - 1e-4)), sh)  # fmt: skip
    out["random_sh3_20k"] = (sh3, _camera(256, 256, "cpu"))
    return out


def _leaves(scene, device, grad: bool) -> dict:
    """The scene's rasterize arguments on ``device``, as leaves (activated values: the gradients
    both renderers give are of the same tensors)."""
    return {
        k: (v.detach().to(device).clone().requires_grad_(grad) if torch.is_tensor(v) else v)
        for k, v in scene.render_args().items()
    }


def _loss(rgb, alpha, depth, g: torch.Generator):
    """A fixed random linear functional of the three images (the same cotangents for both renderers)."""
    cot = [torch.randn(x.shape, generator=g).to(x) for x in (rgb, alpha, depth)]
    return (rgb * cot[0]).sum() + (alpha * cot[1]).sum() + (depth * cot[2]).sum()


def _diff_rows(scene_name: str, pair: str, a: dict, b: dict) -> list[dict]:
    rows = []
    for k in a:
        if a[k] is None or b[k] is None:
            continue
        d = (a[k].double().cpu() - b[k].double().cpu()).abs()
        scale = b[k].double().abs().max().item()
        rows.append({"scene": scene_name, "pair": pair, "quantity": k, "max_abs": d.max().item(),
                     "mean_abs": d.mean().item(), "max_ref": scale})  # fmt: skip
    return rows


def _render_and_grad(fn, scene, cams, device, seed: int) -> dict:
    args = _leaves(scene, device, True)
    rgb, alpha, depth = fn(args, cams.to(device))
    _loss(rgb, alpha, depth, torch.Generator().manual_seed(seed)).backward()
    out = {"rgb": rgb.detach(), "alpha": alpha.detach(), "depth": depth.detach()}
    return out | {f"grad_{k}": v.grad for k, v in args.items() if torch.is_tensor(v) and k != "sh_degree"}


def agreement(out: Path, device: str) -> dict:
    rows = []
    ours = _ours_images  # (alpha_max, backend) -> the renderer as _gsplat's signature
    for name, (scene, cams) in _scenes().items():
        cpu = _render_and_grad(ours(GSPLAT_ALPHA_MAX, "cpp"), scene, cams, "cpu", 0)
        cpu_default = _render_and_grad(ours(0.99, "cpp"), scene, cams, "cpu", 0)
        cuda_g = _render_and_grad(ours(GSPLAT_ALPHA_MAX), scene, cams, device, 0)
        rows += _diff_rows(name, "ours cuda (torch) vs ours cpu (cpp)", cuda_g, cpu)
        try:
            ref = _render_and_grad(_gsplat, scene, cams, device, 0)
            backend = _render_and_grad(ours(GSPLAT_ALPHA_MAX, "gsplat"), scene, cams, device, 0)
            backend_default = _render_and_grad(ours(0.99, "gsplat"), scene, cams, device, 0)
        except Exception as e:  # gsplat missing, or its kernels failed to build
            rows.append({"scene": name, "pair": "gsplat", "quantity": f"unavailable: {type(e).__name__}: {e}"[:300]})
            continue
        rows += _diff_rows(name, "ours cuda vs gsplat cuda (alpha_max 0.999 both)", cuda_g, ref)
        rows += _diff_rows(
            name, "ours cuda (alpha_max 0.99) vs gsplat cuda", _render_and_grad(ours(0.99), scene, cams, device, 0), ref
        )
        rows += _diff_rows(name, "gsplat backend vs ours cpu (cpp), alpha_max 0.999 both", backend, cpu)
        rows += _diff_rows(name, "gsplat backend (opacity cap) vs ours cpu (cpp), alpha_max 0.99", backend_default,
                           cpu_default)  # fmt: skip
    write_csv(rows, out / "agreement.csv")
    return {"rows": len(rows)}


PATHS = ("ours_gsplat", "gsplat", "ours_torch", "cpu_cpp")
"""The speed part's renderers: rasterize with backend 'gsplat' (our conventions on gsplat's
kernels: the default on CUDA), gsplat.rasterization itself, our torch path on CUDA (10k and 100k
at 256 and 512 px: beyond, it takes seconds a call; docs/results/cuda has its 2026-11-26 figures),
and the C++ compositor on the machine's CPU cores."""


def _speed_case(path: str, n: int, size: str, mode: str, device: str) -> dict:
    if path == "cpu_cpp":
        device = "cpu"
    w, h = SIZES[size]
    c = random_cloud(n, seed=0)
    args = {"means": c["means"], "quats": c["quats"], "scales": c["scales"], "opacities": c["opacities"],
            "colors": c["colors"], "sh_degree": None}  # fmt: skip
    args = {k: (v.to(device).requires_grad_(mode != "fwd") if torch.is_tensor(v) else v) for k, v in args.items()}
    cams = _camera(w, h, device)
    on_gpu = device != "cpu"
    backend = {"ours_gsplat": "gsplat", "ours_torch": "torch", "cpu_cpp": "cpp"}
    render = _gsplat if path == "gsplat" else _ours_images(GSPLAT_ALPHA_MAX, backend[path])
    cot = torch.randn(1, h, w, 3, generator=torch.Generator().manual_seed(1)).to(device)

    def fwd():
        with torch.no_grad():
            render(args, cams)

    def fwd_bwd():
        for v in args.values():
            if torch.is_tensor(v):
                v.grad = None
        rgb, alpha, _ = render(args, cams)
        ((rgb * cot).sum() + alpha.sum()).backward()

    fn = fwd if mode == "fwd" else fwd_bwd
    if on_gpu:
        torch.cuda.empty_cache()
        torch.cuda.reset_peak_memory_stats()
    base = torch.cuda.memory_allocated() if on_gpu else 0
    t0 = time.perf_counter()
    fn()
    if on_gpu:
        torch.cuda.synchronize()
    first = time.perf_counter() - t0
    budget = 0.5 if first < 1 else 0.0
    t = timeit(fn, device=device, warmup=0 if first > 1 else 1, min_repeats=1 if first > 2 else 3, max_repeats=7,
               budget_s=budget)  # fmt: skip
    peak = (torch.cuda.max_memory_allocated() - base) / 2**20 if on_gpu else None
    return {"median_ms": 1e3 * t["median_s"], "min_ms": 1e3 * t["min_s"], "first_ms": 1e3 * first,
            "peak_mb": peak, "threads": torch.get_num_threads()}  # fmt: skip


def speed(out: Path, device: str) -> dict:
    rows = []
    for n in COUNTS:
        for size in SIZES:
            for mode in ("fwd", "fwd+bwd"):
                for path in PATHS:
                    if path == "ours_torch" and (n > 100_000 or size == "1080p"):
                        continue
                    row = {"path": path, "n": n, "size": size, "mode": mode}
                    try:
                        row |= _speed_case(path, n, size, mode, device)
                    except Exception as e:  # an OOM or a failed gsplat build: the reason, not a crash
                        row["error"] = f"{type(e).__name__}: {e}"[:300]
                        torch.cuda.empty_cache()
                    rows.append(row)
                    print(row, flush=True)
                    write_csv(rows, out / "speed.csv")
    _profile(out / "profile.txt", device)
    return {"rows": len(rows)}


def _profile(path: Path, device: str) -> None:
    """The kernels and ops of ours at 100k / 512 px, forward+backward (torch.profiler, CUDA time)."""
    from torch.profiler import ProfilerActivity, profile

    c = random_cloud(100_000, seed=0)
    args = {k: c[k].to(device).requires_grad_(True) for k in ("means", "quats", "scales", "opacities", "colors")}
    cams = _camera(512, 512, device)

    def step():
        r = _ours(args | {"sh_degree": None}, cams, alpha_max=GSPLAT_ALPHA_MAX)
        (r.rgb.sum() + r.alpha.sum()).backward()

    step()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        step()
        torch.cuda.synchronize()
    path.write_text(prof.key_averages().table(sort_by="cuda_time_total", row_limit=40))


TRAIN_CASES = (
    ("empirical", 64, "cpu", "auto"), ("empirical", 64, "cuda", "gsplat"), ("empirical", 64, "cuda", "torch"),
    ("learned", 64, "cpu", "auto"), ("learned", 64, "cuda", "gsplat"), ("learned", 64, "cuda", "torch"),
    ("sd-tiny", 256, "cpu", "auto"), ("sd-tiny", 256, "cuda", "gsplat"),
    ("sd-tiny", 512, "cpu", "auto"), ("sd-tiny", 512, "cuda", "gsplat"),
)  # fmt: skip
"""(prior, resolution, device, renderer on CUDA) of the trainer part: the default gd run's step
at 64 px on both CPU priors, and at 256 and 512 px on the tiny SD models (the SD code path)."""


def _train_config(prior: str, resolution: int, device: str, out: Path):
    from gdbench.train.config import preset

    kw = dict(prompt="a yellow duck", steps=1000, device=device, progress=False, out=out, resolution=resolution)
    if prior == "sd-tiny":
        kw |= dict(prior="sd", sd_model="tiny")
    else:
        kw["prior"] = prior
    return preset("gd", **kw)


def _renderer_on_cuda(name: str) -> None:
    """'gsplat' (the default) or 'torch' for every render of the trainer on CUDA, through the
    switch a user has (GDBENCH_NO_GSPLAT)."""
    from renderers.splat.gsplat_backend import gsplat_status

    if name == "torch":
        os.environ["GDBENCH_NO_GSPLAT"] = "1"
    else:
        os.environ.pop("GDBENCH_NO_GSPLAT", None)
    gsplat_status.cache_clear()


def trainer(out: Path, device: str, steps: int = 20, warmup: int = 5) -> dict:
    from torch.profiler import ProfilerActivity, profile

    from gdbench.train.trainer import init_state, make_context, train_step

    rows = []
    parts = ("t_views", "t_render", "t_noise", "t_prior", "t_update")
    for prior, res, dev, renderer in TRAIN_CASES:
        dev = "cpu" if dev == "cpu" else device
        row = {"prior": prior, "resolution": res, "device": dev, "renderer": renderer}
        try:
            _renderer_on_cuda(renderer)
            ctx = make_context(_train_config(prior, res, dev, out / f"run_{prior}_{res}_{dev}_{renderer}"))
            state = init_state(ctx)
            for _ in range(warmup):
                train_step(state, ctx)
            ms = [train_step(state, ctx) for _ in range(steps)]
            row |= {"step_ms": _median_ms(ms, "seconds"), **{k[2:] + "_ms": _median_ms(ms, k) for k in parts},
                    "gaussians": int(state.params["means"].shape[0])}  # fmt: skip
            if (prior, res, dev, renderer) == ("empirical", 64, device, "gsplat"):
                with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
                    for _ in range(10):
                        train_step(state, ctx)
                table = prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=30)
                (out / "trainer_profile.txt").write_text(table)
        except Exception as e:  # one case's failure (a missing model, gsplat) is its row, not the part's end
            row["error"] = f"{type(e).__name__}: {e}"[:300]
        finally:
            _renderer_on_cuda("gsplat")
        rows.append(row)
        print(row, flush=True)
        write_csv(rows, out / "trainer.csv")
    try:
        visible = _visible(device)
    except Exception as e:  # gsplat missing or not built: the step timings above stand
        visible = f"unavailable: {type(e).__name__}: {e}"[:300]
    return {"rows": len(rows), "visible_1m_512": visible}


def _median_ms(metrics: list[dict], key: str) -> float:
    return 1e3 * sorted(m[key] for m in metrics)[len(metrics) // 2]


def _visible(device: str) -> dict:
    """How many of the speed part's 1M Gaussians at 512 px each renderer keeps."""
    from gsplat import rasterization

    from renderers.splat import rasterize

    c = {k: v.to(device) for k, v in random_cloud(1_000_000, seed=0).items()}
    cams = _camera(512, 512, device)
    with torch.no_grad():
        _, _, meta = rasterization(c["means"], c["quats"], c["scales"], c["opacities"], c["colors"], cams.viewmats,
                                   cams.Ks, 512, 512, packed=False)  # fmt: skip
        ours = rasterize(c["means"], c["quats"], c["scales"], c["opacities"], c["colors"], cams.viewmats, cams.Ks,
                         512, 512, outputs=("rgb", "visible"), backend="torch")  # fmt: skip
    radii = meta["radii"]
    kept = (radii > 0).any(-1) if radii.dim() > 2 else radii > 0  # [C, N, 2] in gsplat 1.5, [C, N] before
    return {"gsplat": int(kept.sum()), "ours": int(ours.visible.sum())}


def threads(out: Path) -> dict:
    from gdbench.refcheck.bm_render import setup

    rows = []
    cores = os.cpu_count() or 1
    counts = [t for t in (1, 2, 4, 8, 16, 32, 64) if t <= cores]
    before = torch.get_num_threads()
    try:
        for n, res in ((10_000, 256), (100_000, 512)):
            for mode in ("fwd", "fwd+bwd"):
                fn = setup("splat", n, res, mode, "cpu")
                for t in counts:
                    torch.set_num_threads(t)
                    r = timeit(fn, warmup=1, min_repeats=3, max_repeats=10, budget_s=1.0)
                    rows.append({"n": n, "res": res, "mode": mode, "threads": t, "median_ms": 1e3 * r["median_s"]})
                    print(rows[-1], flush=True)
        for r in rows:
            one = next(x for x in rows if (x["n"], x["mode"], x["threads"]) == (r["n"], r["mode"], 1))
            r["speedup"] = one["median_ms"] / r["median_ms"]
            r["efficiency"] = r["speedup"] / r["threads"]
    finally:
        torch.set_num_threads(before)
    write_csv(rows, out / "threads.csv")
    return {"rows": len(rows)}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/cuda"), help="folder for the CSVs")
    ap.add_argument(
        "--parts", default="agreement,speed,trainer,threads", help="comma-separated: agreement, speed, trainer, threads"
    )
    args = ap.parse_args(argv)
    parts = [p for p in args.parts.split(",") if p]
    bad = set(parts) - {"agreement", "speed", "trainer", "threads"}
    if bad:
        ap.error(f"--parts: unknown {sorted(bad)}; expected agreement, speed, trainer, threads")
    args.out.mkdir(parents=True, exist_ok=True)
    summary: dict = {"environment": environment()}
    if torch.cuda.is_available():
        summary["gpu"] = torch.cuda.get_device_name(0)
        summary["cuda"] = torch.version.cuda
    for part in parts:
        if part != "threads" and not torch.cuda.is_available():
            summary[part] = "skipped: torch sees no CUDA device"
            continue
        t0 = time.perf_counter()
        try:
            fn = {"agreement": agreement, "speed": speed, "trainer": trainer}.get(part)
            summary[part] = fn(args.out, "cuda") if fn else threads(args.out)
        except Exception:
            summary[part] = "failed: " + traceback.format_exc()[-1500:]
        summary[f"{part}_s"] = time.perf_counter() - t0
        print(part, summary[part], flush=True)
        write_json(summary, args.out / "cuda_summary.json")
    return 0 if all(not str(summary[p]).startswith("failed") for p in parts) else 1


if __name__ == "__main__":
    raise SystemExit(main())
