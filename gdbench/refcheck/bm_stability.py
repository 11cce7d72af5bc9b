"""Numerical stability on stiff and extreme cases, every renderer.

Each case is a small scene and one camera, built in float64. Every renderer gets float32
inputs, renders rgb and alpha, and back-propagates a fixed random cotangent; the row records
NaN/Inf in its outputs and in its gradients, the max error of its images against the float64
twin (``renderers.splat.reference``, run at the renderer's own alpha clamp), and the max
gradient error relative to the twin's largest gradient. The twin itself is checked for
finiteness too.

Renderers: ``splat`` (C++ compositor), ``splat_torch``, ``gsplat_torch`` (gsplat 1.5.3's torch
stages) and ``mitsuba_ellipsoids`` (ray-traced ellipsoids, 16 spp; a different image model, so its error
measures model difference and Monte Carlo noise as well; it has no near plane). Not run: the
exact volume (its grid cannot resolve sub-voxel or 1e6-anisotropic Gaussians, and the analytic
field is too slow at 10k Gaussians) and pyrender points (centres only; no images).

    python -m gdbench.refcheck.bm_stability --out bench_results/stability.csv

Writes the CSV, ``<stem>.md`` (a case x renderer table) and ``<stem>_summary.json``.
"""

from __future__ import annotations

import argparse
import math
import time
import traceback
from collections.abc import Callable
from pathlib import Path

import torch

from gdbench.bench.common import environment, write_csv, write_json

F64 = torch.float64
RENDERERS = ("splat", "splat_torch", "gsplat_torch", "mitsuba_ellipsoids")
PARAMS = ("means", "quats", "scales", "opacities", "colors")


def _gaussians(means, scales, quats=None, opacity=0.8, colors=None) -> dict[str, torch.Tensor]:
    means = torch.as_tensor(means, dtype=F64).reshape(-1, 3)
    n = means.shape[0]
    sc = torch.as_tensor(scales, dtype=F64)
    q = torch.as_tensor((1.0, 0.0, 0.0, 0.0) if quats is None else quats, dtype=F64)
    op = torch.as_tensor(opacity, dtype=F64)
    col = torch.tensor([0.9, 0.5, 0.1], dtype=F64) if colors is None else torch.as_tensor(colors, dtype=F64)
    return {
        "means": means.clone(),
        "quats": q.expand(n, 4).clone() if q.dim() == 1 else q.clone(),
        "scales": sc.expand(n, 3).clone() if sc.dim() <= 1 else sc.clone(),
        "opacities": op.expand(n).clone() if op.dim() == 0 else op.clone(),
        "colors": col.expand(n, 3).clone() if col.dim() == 1 else col.clone(),
    }


def _camera(width: int, height: int, fovy_deg: float = 60.0, viewmat=None) -> dict:
    """Pinhole camera (OpenCV axes) with the given vertical field of view; identity pose by default."""
    f = height / 2 / math.tan(math.radians(fovy_deg) / 2)
    K = torch.tensor([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1]], dtype=F64)[None]
    vm = torch.eye(4, dtype=F64)[None] if viewmat is None else torch.as_tensor(viewmat, dtype=F64)[None]
    return {"viewmats": vm, "Ks": K, "width": width, "height": height}


def _cloud(n: int, seed: int = 0, spread: float = 0.3, z: float = 2.0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g, dtype=F64) * spread
    means[:, 2] += z
    return {
        "means": means,
        "quats": torch.randn(n, 4, generator=g, dtype=F64),
        "scales": 0.01 + 0.08 * torch.rand(n, 3, generator=g, dtype=F64),
        "opacities": 0.05 + 0.95 * torch.rand(n, generator=g, dtype=F64),
        "colors": torch.rand(n, 3, generator=g, dtype=F64),
    }


def _edge_on_view(tilt_deg: float) -> torch.Tensor:
    """A camera at (0, -2, 0) looking at the origin along +y, tilted by ``tilt_deg`` about x: a disc
    in the z = 0 plane at the origin is seen edge-on (0) or nearly so."""
    t = math.radians(tilt_deg)
    # camera axes in world coordinates (OpenCV: x right, y down, z forward)
    fwd = torch.tensor([0.0, math.cos(t), math.sin(t)], dtype=F64)
    right = torch.tensor([1.0, 0.0, 0.0], dtype=F64)
    down = torch.linalg.cross(fwd, right)
    R = torch.stack([right, down, fwd])  # world -> camera rotation
    c = -2.0 * fwd
    vm = torch.eye(4, dtype=F64)
    vm[:3, :3], vm[:3, 3] = R, -R @ c
    return vm


def cases() -> dict[str, Callable[[], tuple[dict, dict]]]:
    """name -> () -> (gaussians, camera). The foundation issue's list and more."""
    rot = (0.8, 0.4, 0.3, 0.2)

    def huge_n_one_pixel():
        g = torch.Generator().manual_seed(0)
        gs = _gaussians([[0.0, 0.0, 2.0]] * 10_000, 0.2, opacity=0.5)
        gs["means"][:, 2] = 1.0 + torch.rand(10_000, generator=g, dtype=F64) * 3
        return gs, _camera(1, 1)

    return {
        "behind the camera": lambda: (_gaussians([0, 0, -1.0], 0.2), _camera(32, 32)),
        "on the near plane (z=0.0102)": lambda: (_gaussians([0, 0, 0.0102], 1e-4), _camera(32, 32)),
        "camera inside a Gaussian": lambda: (_gaussians([0, 0, 0.3], [1.0, 0.6, 0.8]), _camera(32, 32)),
        "tiny scale 1e-8": lambda: (_gaussians([0, 0, 2.0], 1e-8), _camera(32, 32)),
        "huge scale 1e4": lambda: (_gaussians([0, 0, 2.0], 1e4), _camera(32, 32)),
        "condition number 1e8": lambda: (_gaussians([0, 0, 2.0], [0.3, 3e-5, 0.2], rot), _camera(48, 48)),
        "anisotropy 1e6": lambda: (_gaussians([0, 0, 2.0], [0.3, 3e-7, 0.3], rot), _camera(48, 48)),
        "zero quaternion": lambda: (_gaussians([0, 0, 2.0], [0.3, 0.1, 0.05], (0.0, 0.0, 0.0, 0.0)), _camera(32, 32)),
        "opacity 1 - 1e-7": lambda: (_gaussians([0, 0, 2.0], 0.2, opacity=1 - 1e-7), _camera(33, 33)),
        "opacity 1e-7": lambda: (_gaussians([0, 0, 2.0], 0.2, opacity=1e-7), _camera(33, 33)),
        "empty scene": lambda: ({k: v[:0] for k, v in _gaussians([0, 0, 2.0], 0.1).items()}, _camera(16, 16)),
        "10k Gaussians on one pixel": huge_n_one_pixel,
        "grazing view: disc edge-on": lambda: (
            _gaussians([0, 0, 0], [0.3, 0.3, 1e-4]),
            _camera(48, 48, 40.0, _edge_on_view(0.0)),
        ),
        "grazing view: disc at 0.5 deg": lambda: (
            _gaussians([0, 0, 0], [0.3, 0.3, 1e-4]),
            _camera(48, 48, 40.0, _edge_on_view(0.5)),
        ),
        "fovy 1 deg": lambda: (_cloud(200, spread=0.01), _camera(48, 48, 1.0)),
        "fovy 170 deg": lambda: (_cloud(500, spread=1.0), _camera(64, 64, 170.0)),
        "image 4096 x 1": lambda: (_cloud(60, spread=0.05), _camera(4096, 1, 0.05)),
    }


def _renderer(name: str) -> tuple[Callable, float]:
    """(render function taking the rasterize signature, the alpha clamp its twin uses), from the
    backend registry with its comparable settings."""
    from gdbench.refcheck.backends import get

    if name not in RENDERERS:
        raise ValueError(f"renderer: expected one of {RENDERERS}, got {name!r}")
    b = get(name)
    return b.render, b.alpha_max


def _render_with_grads(fn: Callable, gs: dict, cam: dict, dtype) -> tuple[dict, dict]:
    params = {k: gs[k].to(dtype).clone().requires_grad_(True) for k in PARAMS}
    bg = torch.ones(3, dtype=dtype)
    out = fn(
        *(params[k] for k in PARAMS),
        cam["viewmats"].to(dtype),
        cam["Ks"].to(dtype),
        cam["width"],
        cam["height"],
        background=bg,
    )
    images = {"rgb": out.rgb, "alpha": out.alpha}
    loss = 0.0
    for i, x in enumerate(images.values()):
        g = torch.Generator().manual_seed(i)
        loss = loss + (x * torch.randn(x.shape, generator=g, dtype=F64).to(x.dtype)).sum()
    names = [k for k in PARAMS if params[k].numel()]
    grads = dict(zip(names, torch.autograd.grad(loss, [params[k] for k in names], allow_unused=True))) if names else {}
    return {k: v.detach() for k, v in images.items()}, {k: v for k, v in grads.items() if v is not None}


def _finite(ts) -> bool:
    return all(bool(torch.isfinite(t).all()) for t in ts)


def run_case(case: str, renderer: str) -> dict:
    gs, cam = cases()[case]()
    row: dict = {
        "case": case,
        "renderer": renderer,
        "n": gs["means"].shape[0],
        "width": cam["width"],
        "height": cam["height"],
    }
    try:
        fn, alpha_max = _renderer(renderer)
        t0 = time.perf_counter()
        imgs, grads = _render_with_grads(fn, gs, cam, torch.float32)
        row["time_s"] = time.perf_counter() - t0
        from renderers.splat.reference import rasterize_reference

        twin = lambda *a, **k: rasterize_reference(*a, **k, alpha_max=alpha_max)  # noqa: E731
        timgs, tgrads = _render_with_grads(twin, gs, cam, F64)
    except Exception as e:  # a crash is a result here, recorded with its message
        row |= {"status": f"error: {type(e).__name__}: {str(e).splitlines()[0][:160]}"}
        row["traceback"] = traceback.format_exc(limit=3).replace("\n", " | ")[-400:]
        return row
    row["nan_out"] = not _finite(imgs.values())
    row["nan_grad"] = not _finite(grads.values())
    row["twin_finite"] = _finite(timgs.values()) and _finite(tgrads.values())
    row["alpha_max_twin"] = float(timgs["alpha"].max()) if timgs["alpha"].numel() else 0.0
    row["max_err_rgb"] = float((imgs["rgb"].double() - timgs["rgb"]).abs().max()) if imgs["rgb"].numel() else 0.0
    row["mean_err_rgb"] = float((imgs["rgb"].double() - timgs["rgb"]).abs().mean()) if imgs["rgb"].numel() else 0.0
    row["max_err_alpha"] = (
        float((imgs["alpha"].double() - timgs["alpha"]).abs().max()) if imgs["alpha"].numel() else 0.0
    )
    errs = []
    for k, tg in tgrads.items():
        if k in grads and tg.numel():
            scale = float(tg.abs().max())
            errs.append(float((grads[k].double() - tg).abs().max()) / max(scale, 1e-12))
    row["max_rel_err_grad"] = max(errs) if errs else 0.0
    row["status"] = "ok" if not (row["nan_out"] or row["nan_grad"]) else "non-finite"
    return row


def table(rows: list[dict]) -> str:
    """Markdown: one line per case, one column per renderer: image error vs the twin, or the failure."""
    names = list(dict.fromkeys(r["renderer"] for r in rows))
    md = ["| case | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for case in dict.fromkeys(r["case"] for r in rows):
        cells = []
        for n in names:
            r = next((r for r in rows if r["case"] == case and r["renderer"] == n), None)
            if r is None:
                cells.append("")
            elif r["status"].startswith("error"):
                cells.append("error")
            else:
                flags = [f for f, bad in (("NaN out", r["nan_out"]), ("NaN grad", r["nan_grad"])) if bad]
                err = max(r["max_err_rgb"], r["max_err_alpha"])
                cells.append((", ".join(flags) + "; " if flags else "") + f"{err:.1e} / {r['max_rel_err_grad']:.1e}")
        md.append(f"| {case} | " + " | ".join(cells) + " |")
    md.append("")
    md.append("Cells: max image error against the float64 twin / max gradient error relative to the twin's")
    md.append("largest gradient; NaN out / NaN grad flag non-finite outputs / gradients.")
    return "\n".join(md) + "\n"


def run(out: Path, renderers=RENDERERS, only: list[str] | None = None, progress: bool = True) -> list[dict]:

    names = only or list(cases())
    unknown = [c for c in names if c not in cases()]
    if unknown:
        raise ValueError(f"cases: unknown {unknown}; known: {list(cases())}")
    rows = []
    todo = [(c, r) for c in names for r in renderers]
    from gdbench.core.progress import track

    it = track(todo, desc="bm_stability", unit="run", disable=not progress)
    from gdbench.refcheck.backends import get

    for case, r in it:
        ok, why = get(r).available() if r != "splat_torch" else (True, "")
        if not ok:
            rows.append({"case": case, "renderer": r, "status": f"skipped: {why}"})
            continue
        rows.append(run_case(case, r))
        write_csv(rows, out)
    write_csv(rows, out)
    out.with_suffix(".md").write_text(table([r for r in rows if not r["status"].startswith("skipped")]))
    bad = [r for r in rows if r["status"] != "ok" and not r["status"].startswith("skipped")]
    write_json(
        {
            "environment": environment(),
            "runs": len(rows),
            "not_ok": [{k: r[k] for k in ("case", "renderer", "status")} for r in bad],
        },
        out.with_name(out.stem + "_summary.json"),
    )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/stability.csv"))
    ap.add_argument("--renderers", nargs="+", default=list(RENDERERS), choices=RENDERERS)
    ap.add_argument("--cases", nargs="+", default=None, help="case names (default: all)")
    args = ap.parse_args(argv)
    rows = run(args.out, args.renderers, args.cases)
    print(table([r for r in rows if not r["status"].startswith("skipped")]))
    print(f"wrote {args.out}, {args.out.with_suffix('.md')}, {args.out.stem}_summary.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
