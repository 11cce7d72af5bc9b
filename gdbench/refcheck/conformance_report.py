"""A conformance report a renderer's author can attach to a pull request: ``gdbench conformance
--renderer pkg.mod:fn --out DIR`` writes ``DIR/report.md`` with the PASS/FAIL/SKIP table over every
fixture and stiff case, the gradient errors per parameter group, error maps (twin, renderer, error)
on the fixture scenes, the error-against-time plot, and the exact versions and commits; beside it
``conformance.csv`` and ``conformance.json`` (the same rows, and the counts). The command exits 1
when a case fails."""

from __future__ import annotations

import platform
import subprocess
from pathlib import Path

import torch

from gdbench.refcheck import conformance as cf

GROUP_COLUMNS = tuple(f"grad_err_{g}" for g in cf.GROUPS.values())


def _version(module: str) -> str:
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version(module)
    except PackageNotFoundError:
        return "not installed"


def _source(spec) -> str:
    """Where a renderer's function lives, and the commit of the git checkout holding it (if any)."""
    import inspect

    from gdbench.refcheck.backends import Backend

    if isinstance(getattr(spec.fn, "__self__", None), Backend):
        return f"gdbench's built-in backend {spec.fn.__self__.name!r} ({spec.fn.__self__.what})"
    try:
        path = Path(inspect.getsourcefile(spec.fn) or "")
    except TypeError:
        return "(no source file)"
    if not path.is_file():
        return "(no source file)"
    try:
        head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=path.parent, capture_output=True,
                              text=True, timeout=30)  # fmt: skip
        dirty = subprocess.run(["git", "status", "--porcelain", "--", path.name], cwd=path.parent,
                               capture_output=True, text=True, timeout=30)  # fmt: skip
    except (OSError, subprocess.SubprocessError):
        return str(path)
    if path.is_relative_to(Path.cwd()):
        path = path.relative_to(Path.cwd())
    if head.returncode != 0:
        return f"{path} (not in a git checkout)"
    return f"{path} at {head.stdout.strip()}" + (" (with uncommitted changes)" if dirty.stdout.strip() else "")


def versions(specs) -> list[tuple[str, str]]:
    from gdbench.core.provenance import code_commit

    rows = [
        ("gdbench", code_commit()),
        ("python", platform.python_version()),
        ("torch", torch.__version__),
        ("gsplat", _version("gsplat")),
        ("mitsuba", _version("mitsuba")),
        ("machine", f"{platform.machine()}, {torch.get_num_threads()} threads, CUDA {torch.cuda.is_available()}"),
    ]
    return rows + [(f"renderer {s.name}", _source(s)) for s in specs]


def error_maps(images: dict, rows: list[dict], path: Path) -> Path | None:
    """One line per fixture case: the twin, then each renderer and its error (scaled to its own max)."""
    from gdbench.core.plotting import pyplot, save

    names = list(dict.fromkeys(r["renderer"] for r in rows))
    cases = [c for c in dict.fromkeys(r["case"] for r in rows if r["kind"] == "fixture")
             if any((c, n) in images for n in names)]  # fmt: skip
    if not cases:
        return None
    plt = pyplot()
    fig, axes = plt.subplots(len(cases), 1 + 2 * len(names), figsize=(1.6 * (1 + 2 * len(names)), 1.7 * len(cases)),
                             squeeze=False)  # fmt: skip
    for i, case in enumerate(cases):
        truth = next(images[(case, n)][1] for n in names if (case, n) in images)
        axes[i, 0].imshow(truth.clamp(0, 1).numpy())
        axes[i, 0].set_ylabel(case, fontsize=7)
        axes[i, 0].set_title("float64 twin" if i == 0 else "", fontsize=7)
        for j, name in enumerate(names):
            a, b = axes[i, 1 + 2 * j], axes[i, 2 + 2 * j]
            if (case, name) in images:
                img, twin = images[(case, name)]  # the twin at this renderer's alpha clamp
                err = (img - twin).abs().amax(-1)
                a.imshow(img.clamp(0, 1).numpy())
                b.imshow(err.numpy(), cmap="magma", vmin=0, vmax=max(float(err.max()), 1e-12))
                b.set_xlabel(f"max {float(err.max()):.1e}", fontsize=6)
            if i == 0:
                a.set_title(name, fontsize=7)
                b.set_title("|error| (own max)", fontsize=7)
    for ax in axes.flat:
        ax.set_xticks([])
        ax.set_yticks([])
    return save(fig, path, dpi=90)


def pareto(rows: list[dict], path: Path) -> Path | None:
    """Max image error against run time (forward and backward), every renderer on every case run."""
    from gdbench.core.plotting import pyplot, save

    pts = [r for r in rows if r.get("time_s") is not None and "max_err_rgb" in r]
    if not pts:
        return None
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    for k, name in enumerate(dict.fromkeys(r["renderer"] for r in pts)):
        mine = [r for r in pts if r["renderer"] == name]
        ax.loglog([max(r["time_s"], 1e-5) for r in mine],
                  [max(r["max_err_rgb"], r["max_err_alpha"], 1e-10) for r in mine],
                  "osD^vx"[k % 6], label=name, alpha=0.75)  # fmt: skip
    ax.set_xlabel("run time, forward and backward (s)")
    ax.set_ylabel("max |image error| vs the float64 twin")
    ax.set_title("Error against run time, one point per case (an exact match drawn at 1e-10)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return save(fig, path, dpi=100)


def _fmt(x) -> str:
    return "-" if x is None or x == "" else f"{x:.1e}" if isinstance(x, float) else str(x)


def markdown(rows: list[dict], specs, plots: dict[str, Path | None]) -> str:
    names = [s.name for s in specs]
    counts = cf.summary(rows)
    md = ["# Conformance report", ""]
    md += ["Each renderer against gdbench's float64 twin on every fixture scene and stiff case: images (rgb,",
           "alpha) and the directional derivatives of the gradients, PASS, FAIL or SKIP against the case's",
           "tolerance for the renderer's class (docs/references.md, \"Bring your own renderer\").", ""]  # fmt: skip
    md += ["| renderer | class | PASS | FAIL | SKIP |", "|---|---|---|---|---|"]
    for s in specs:
        c = counts.get(s.name, {"PASS": 0, "FAIL": 0, "SKIP": 0})
        md.append(f"| {s.name} | {s.tolerance} | {c['PASS']} | {c['FAIL']} | {c['SKIP']} |")
    md += ["", "## Versions", "", "| what | version |", "|---|---|"]
    md += [f"| {k} | {v} |" for k, v in versions(specs)]
    md += ["", "## Cases", "", "Cells: verdict, max image error / worst gradient error (relative).", ""]
    md += ["| case | kind | " + " | ".join(names) + " |", "|---|---|" + "---|" * len(names)]
    for case in dict.fromkeys(r["case"] for r in rows):
        cells = []
        for n in names:
            r = next((r for r in rows if r["case"] == case and r["renderer"] == n), None)
            if r is None or r["verdict"] == "SKIP" or "max_err_rgb" not in r:
                cells.append("" if r is None else r["verdict"])
                continue
            img = max(r["max_err_rgb"], r["max_err_alpha"])
            cells.append(f"**{r['verdict']}** {img:.1e} / {_fmt(r.get('grad_err'))}")
        kind = next(r["kind"] for r in rows if r["case"] == case)
        md.append(f"| {case} | {kind} | " + " | ".join(cells) + " |")
    md += ["", "## Gradient errors by parameter group", ""]
    md += ["| case | renderer | " + " | ".join(cf.GROUPS.values()) + " |", "|---|---|" + "---|" * len(cf.GROUPS)]
    for r in rows:
        if r.get("grad_err") is not None:
            md.append(f"| {r['case']} | {r['renderer']} | " + " | ".join(_fmt(r.get(c)) for c in GROUP_COLUMNS) + " |")
    why = [r for r in rows if r["verdict"] != "PASS" or r.get("reason")]
    if why:
        md += ["", "## Reasons (FAIL, SKIP, what was not judged)", ""]
        md += [f"- {r['verdict']} {r['case']} / {r['renderer']}: {r['reason']}" for r in why]
    titles = {"maps": "Error maps (first camera of each fixture scene)", "pareto": "Error against run time"}
    for key, title in titles.items():
        if plots.get(key) is not None:
            md += ["", f"## {title}", "", f"![{key}]({plots[key].name})"]
    return "\n".join(md) + "\n"


def write(specs, out: Path, names: list[str] | None = None, progress: bool = True) -> tuple[list[dict], Path]:
    """Run every renderer of ``specs`` on the cases (``names``: a subset) and write the report;
    returns the rows and the report's path."""
    from gdbench.core.io import writable_folder, write_csv, write_json
    from gdbench.refcheck.bm_stability import status

    out = Path(out)
    writable_folder(out)
    images: dict = {}
    rows = cf.run(specs, names, progress=progress, images_out=images)
    for r in rows:
        r["status"] = status(r) if r["verdict"] != "SKIP" else f"skipped: {r['reason']}"
    plots = {"maps": error_maps(images, rows, out / "error_maps.png"), "pareto": pareto(rows, out / "pareto.png")}
    write_csv(rows, out / "conformance.csv")
    write_json({"versions": dict(versions(specs)), "verdicts": cf.summary(rows), "rows": rows},
               out / "conformance.json")  # fmt: skip
    report = out / "report.md"
    report.write_text(markdown(rows, specs, plots))
    return rows, report
