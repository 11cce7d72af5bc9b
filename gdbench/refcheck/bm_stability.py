"""Numerical stability on stiff and extreme cases, every renderer.

Each case is a small scene and one camera, built in float64. Every renderer is checked by
``conformance.check``: float32 inputs, rgb and alpha against the float64 twin
(``renderers.splat.reference``, at the renderer's own alpha clamp), and the directional derivatives
of a fixed random cotangent's pull-back against the twin's; the row records NaN/Inf in its outputs
and gradients, the errors, and PASS, FAIL or SKIP against the case's tolerance for the renderer's
class (fixtures/stability_tolerances.json). The command exits 1 when a case fails.

Renderers: ``splat`` (C++ compositor), ``splat_torch``, ``gsplat_torch`` (gsplat 1.5.3's torch
stages) and ``mitsuba_ellipsoids`` (ray-traced ellipsoids, 16 spp; a different image model, so its error
measures model difference and Monte Carlo noise as well; it has no near plane). Not run: the
exact volume (its grid cannot resolve sub-voxel or 1e6-anisotropic Gaussians, and the analytic
field is too slow at 10k Gaussians) and pyrender points (centres only; no images).

    python -m gdbench.refcheck.bm_stability --out bench_results/stability.csv
    python -m gdbench.refcheck.bm_stability --renderer mypkg.render:rasterize --cases "huge scale 1e4"

Writes the CSV, ``<stem>.md`` (a case x renderer table) and ``<stem>_summary.json``.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable
from pathlib import Path

import torch

from gdbench.bench.common import environment, write_csv, write_json

F64 = torch.float64
RENDERERS = ("splat", "splat_torch", "gsplat_torch", "mitsuba_ellipsoids")
C0 = 0.28209479177387814
"""The SH degree-0 basis constant (rgb = 0.5 + C0 * c): a case's RGB colours as coefficients."""


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


def specs(renderers=RENDERERS, refs=()) -> list:
    """The built-in ``renderers`` and the user's (``module:function`` or registered names) as
    ``protocol.RendererSpec``s; one that cannot load fails each case with its reason."""
    from gdbench.refcheck.protocol import builtin, load_or_fail

    unknown = [r for r in renderers if r not in RENDERERS]
    if unknown:
        raise ValueError(f"renderers: unknown {unknown}; expected some of {list(RENDERERS)}")
    return [builtin(r) for r in renderers] + [load_or_fail(r) for r in refs]


def status(row: dict) -> str:
    """ok, non-finite, error: <the renderer's exception> or skipped: <why>, beside the verdict."""
    if row["verdict"] == "SKIP":
        return f"skipped: {row['reason']}"
    if "time_s" not in row:
        return f"error: {row['reason']}"
    return "non-finite" if row["nan_out"] or row["nan_grad"] else "ok"


def run_case(case: str, spec, cache: dict | None = None) -> dict:
    """One renderer (a ``protocol.RendererSpec`` or a built-in name) on one case: the conformance
    row (errors, gradient errors per group, PASS/FAIL/SKIP against the case's tolerance) with the
    case's size and the run's status."""
    from gdbench.refcheck.conformance import check, stiff_case

    if isinstance(spec, str):
        (spec,) = specs((spec,))
    c = stiff_case(case)
    row = check(spec, c, cache)
    row = {"case": case, "renderer": spec.name, "n": c.params["means"].shape[0], "width": c.camera["width"],
           "height": c.camera["height"]} | row  # fmt: skip
    return row | {"status": status(row)}


def table(rows: list[dict]) -> str:
    """Markdown: one line per case, one column per renderer: image error / gradient error and the
    verdict against the case's tolerance, or the failure."""
    names = list(dict.fromkeys(r["renderer"] for r in rows))
    md = ["| case | " + " | ".join(names) + " |", "|---|" + "---|" * len(names)]
    for case in dict.fromkeys(r["case"] for r in rows):
        cells = []
        for n in names:
            r = next((r for r in rows if r["case"] == case and r["renderer"] == n), None)
            if r is None:
                cells.append("")
            elif r["verdict"] == "SKIP":
                cells.append("SKIP")
            elif r["status"].startswith("error"):
                cells.append("FAIL (error)")
            else:
                flags = [f for f, bad in (("NaN out", r["nan_out"]), ("NaN grad", r["nan_grad"])) if bad]
                err = max(r["max_err_rgb"], r["max_err_alpha"])
                grad = "-" if r.get("grad_err") is None else f"{r['grad_err']:.1e}"
                cells.append((", ".join(flags) + "; " if flags else "") + f"{err:.1e} / {grad} {r['verdict']}")
        md.append(f"| {case} | " + " | ".join(cells) + " |")
    md.append("")
    md.append("Cells: max image error against the float64 twin / worst gradient error (directional derivatives")
    md.append("against the twin's, relative; conformance.py) and the verdict against the case's tolerance for the")
    md.append("renderer's class (fixtures/stability_tolerances.json); SKIP: the class does not apply to the case, or")
    md.append("the renderer lacks what it needs (reasons in the CSV); NaN out / NaN grad flag non-finite outputs.")
    return "\n".join(md) + "\n"


def run(out: Path, renderers=RENDERERS, only: list[str] | None = None, progress: bool = True, refs=()) -> list[dict]:
    """Every renderer (built-in ``renderers`` and the user's ``refs``) on every case (``only``: a
    subset); writes the CSV, the table and the summary with PASS/FAIL/SKIP counts."""
    names = only or list(cases())
    unknown = [c for c in names if c not in cases()]
    if unknown:
        raise ValueError(f"cases: unknown {unknown}; known: {list(cases())}")
    chosen = specs(renderers, refs)
    from gdbench.core.progress import track
    from gdbench.refcheck.conformance import summary

    rows = []
    for case in track(names, desc="bm_stability", unit="case", disable=not progress):
        cache: dict = {}  # the twin once per case and alpha clamp
        rows += [run_case(case, spec, cache) for spec in chosen]
        write_csv(rows, out)
    write_csv(rows, out)
    out.with_suffix(".md").write_text(table(rows))
    bad = [r for r in rows if r["status"] != "ok" and not r["status"].startswith("skipped")]
    write_json(
        {
            "environment": environment(),
            "runs": len(rows),
            "verdicts": summary(rows),
            "not_ok": [{k: r[k] for k in ("case", "renderer", "status")} for r in bad],
        },
        out.with_name(out.stem + "_summary.json"),
    )
    return rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/stability.csv"))
    ap.add_argument("--renderers", nargs="+", default=None, choices=RENDERERS,
                    help="built-in renderers (default: all of them, or none where --renderer is given)")  # fmt: skip
    ap.add_argument("--renderer", nargs="+", default=[], help="renderers of your own, module:function")
    ap.add_argument("--cases", nargs="+", default=None, help="case names (default: all)")
    args = ap.parse_args(argv)
    builtins = args.renderers if args.renderers is not None else ([] if args.renderer else list(RENDERERS))
    rows = run(args.out, builtins, args.cases, refs=args.renderer)
    print(table(rows))
    print(f"wrote {args.out}, {args.out.with_suffix('.md')}, {args.out.stem}_summary.json")
    failed = [f"{r['case']}/{r['renderer']}: {r['reason']}" for r in rows if r["verdict"] == "FAIL"]
    for line in failed:
        print(f"FAIL {line}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
