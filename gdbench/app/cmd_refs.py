"""Commands that check the renderer and measure speed: ``compare`` (against the reference
renderers) and ``bench`` (the benchmarks, each writing CSV and JSON)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import tyro


@dataclass
class Compare:
    """Run every applicable renderer on fixture scenes; write error-against-time rows (CSV/JSON),
    error maps and a Pareto plot per scene, and print the table."""

    scene: str = "all"
    """A fixture name (fixtures/scenes/*.json) or 'all'."""
    out: Path = Path("runs/compare")
    """Folder for compare.csv/json, the error maps and the Pareto plots."""
    backends: tuple[str, ...] = ()
    """Only these built-in renderers (default: all of them, or none when --renderer is given); the
    float64 reference always runs."""
    renderer: tuple[str, ...] = ()
    """A renderer of your own, module:function (docs/references.md, "Bring your own renderer"):
    PASS or FAIL per scene against the scene's tolerance, SKIP where it lacks what a scene needs;
    the command exits 1 when a case fails."""


def run_compare(cmd: Compare) -> dict:
    from gdbench.refcheck.compare import run

    results = run(cmd.scene, backends=list(cmd.backends) or None, out=cmd.out, renderers=list(cmd.renderer))
    failed = list(dict.fromkeys(
        [f"{r['scene']}/{r['renderer']}" for v in results.values() for r in v.rows if r.get("verdict") == "FAIL"]
        + [f"{r['case']}/{r['renderer']}" for v in results.values() for r in v.verdicts if r["verdict"] == "FAIL"]
    ))  # fmt: skip
    if failed:
        raise SystemExit(f"compare: {len(failed)} case(s) FAIL: {', '.join(failed)}")
    return {k: {"rows": len(v.rows), "skipped": len(v.skipped)} for k, v in results.items()}


@dataclass
class Conformance:
    """Check renderers against the float64 twin on every fixture scene and stiff case, images and
    gradients, PASS/FAIL/SKIP against each case's tolerance for the renderer's class; write a report
    (report.md with the table, gradient errors, error maps, the error-against-time plot and the
    versions; conformance.csv/json) to attach to a pull request. Exits 1 when a case fails."""

    renderer: tuple[str, ...] = ()
    """Renderers of your own: module:function, path/to/file.py:function or a registered name
    (docs/references.md, "Bring your own renderer") (default: none)."""
    renderers: tuple[str, ...] = ()
    """Built-in renderers to check beside them: splat, splat_torch, gsplat_torch, gsplat_cuda,
    mitsuba_ellipsoids (default: none with --renderer, else splat and splat_torch)."""
    cases: tuple[str, ...] = ()
    """Only these cases: fixture names, stiff case names (default: all)."""
    out: Path = Path("runs/conformance")
    """Folder for report.md, its plots, conformance.csv and conformance.json."""


def run_conformance(cmd: Conformance) -> dict:
    from gdbench.refcheck.conformance_report import write
    from gdbench.refcheck.protocol import builtin, load_or_fail

    names = list(cmd.renderers) or ([] if cmd.renderer else ["splat", "splat_torch"])
    specs = [builtin(n) for n in names] + [load_or_fail(r) for r in cmd.renderer]
    rows, report = write(specs, cmd.out, list(cmd.cases) or None)
    failed = [f"{r['case']}/{r['renderer']}: {r['reason']}" for r in rows if r["verdict"] == "FAIL"]
    print(f"wrote {report} (and conformance.csv, conformance.json, plots) in {cmd.out}")
    if failed:
        raise SystemExit(f"conformance: {len(failed)} case(s) FAIL:\n" + "\n".join(failed))
    return {v: sum(r["verdict"] == v for r in rows) for v in ("PASS", "FAIL", "SKIP")}


BENCHES = {
    "render": ("gdbench.refcheck.bm_render", "render.csv", []),
    "peers": ("gdbench.refcheck.bm_render", "peers.csv", ["--peers"]),
    "error": ("gdbench.refcheck.bm_error", "error_vs_runtime.csv", []),
    "stability": ("gdbench.refcheck.bm_stability", "stability.csv", []),
    "noise": ("gdbench.bench.bm_noise", "noise.csv", []),
    "train": ("gdbench.bench.bm_train", "train.csv", []),
    "scale": ("gdbench.bench.bm_scale", "scale.csv", []),
    "cell": ("gdbench.bench.bm_cell", "cell.csv", []),
    "cuda": ("gdbench.refcheck.bm_cuda", "cuda", []),
    "judge": ("gdbench.bench.bm_judge", "judge.csv", []),
}
"""Benchmark name -> (module, CSV name (a folder for cuda), extra arguments)."""


@dataclass
class Bench:
    """Benchmarks; each writes a CSV with a JSON summary (and a plot or table) to --out.

    render: splat vs the dense all-pairs path over N and resolution (speed, memory);
    peers: splat vs gsplat_torch vs Mitsuba ellipsoids (target: splat forward >= 10x gsplat at
    10k Gaussians, 256 px, same run); error: error against run time over all fixtures (Pareto);
    stability: stiff and extreme cases on every renderer; noise: structured-noise share of a
    training step; train: denoiser, full-run and per-step timings; scale: 1M Gaussians with SH
    degree 3 at 1920x1080 (time and peak memory); cell: one scored 1000-step sweep cell in a fresh
    process and its phases, COLMAP on its scene, a cold first run (the module gdbench.bench.bm_cell
    run with a peer checkout compares two versions of the code in one run); cuda: on a GPU, the
    renderer on CUDA (the gsplat backend, the torch path) against gsplat itself and the C++
    compositor (agreement, speed), the training step on both devices, and the C++ compositor's
    scaling with CPU threads (only that part without a GPU); judge: the Janus judge on a run's
    turntable and on a sheet's six views (target: a run in at most 2 s on 2 cores)."""

    which: tyro.conf.Positional[
        Literal["render", "peers", "error", "stability", "noise", "train", "scale", "cell", "cuda", "judge"]
    ]
    """The benchmark (above)."""
    out: Path = Path("bench_results")
    """Folder for the CSV/JSON/plots."""
    quick: bool = False
    """Small grid (render and peers only; render's cases all in this process, so its peak memory
    is not per case): a smoke run, not numbers to publish."""
    renderer: tuple[str, ...] = ()
    """stability and error: renderers of your own, module:function or path/file.py:function
    (docs/references.md, "Bring your own renderer"); PASS, FAIL or SKIP per case, exit 1 on a FAIL
    (default: none)."""
    renderers: tuple[str, ...] = ()
    """stability and error: only these built-in renderers (default: all, or none with --renderer)."""
    cases: tuple[str, ...] = ()
    """stability: only these cases, named as in its table (default: all)."""
    learned_models: tuple[str, ...] = ()
    """train: learned models of your own (names or model.safetensors), each step timed in the same
    alternating blocks as the shipped learned model's, with its ratio to it (default: none)."""


def run_bench(cmd: Bench) -> dict:
    import importlib

    module, csv_name, extra = BENCHES[cmd.which]
    argv = ["--out", str(Path(cmd.out) / csv_name), *extra]
    if cmd.quick:
        if cmd.which not in ("render", "peers"):
            raise ValueError(f"quick: only render and peers have a quick grid, not {cmd.which!r}")
        argv += ["--quick"] + (["--inprocess"] if cmd.which == "render" else [])
    for flag, values, benches in (("--renderer", cmd.renderer, ("stability", "error")),
                                  ("--renderers", cmd.renderers, ("stability", "error")),
                                  ("--cases", cmd.cases, ("stability",)),
                                  ("--learned-models", cmd.learned_models, ("train",))):  # fmt: skip
        if values and cmd.which not in benches:
            raise ValueError(f"{flag[2:]}: only the {' and '.join(benches)} benchmarks take it, not {cmd.which!r}")
        argv += [flag, *values] if values else []
    code = importlib.import_module(module).main(argv)
    if code:
        raise SystemExit(f"bench {cmd.which}: a case failed (FAIL lines above; {Path(cmd.out) / csv_name})")
    return {"bench": cmd.which, "csv": str(Path(cmd.out) / csv_name), "exit": code}
