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
from pathlib import Path

import torch

from gdbench.bench.common import environment, write_csv, write_json
from gdbench.refcheck.stiff_cases import cases

F64 = torch.float64
RENDERERS = ("splat", "splat_torch", "gsplat_torch", "mitsuba_ellipsoids")


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
