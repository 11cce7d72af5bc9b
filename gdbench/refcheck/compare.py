"""``gdbench compare``: every applicable renderer on fixture scenes, error against run time.

For a fixture (``gdbench.refcheck.scenes``) it renders the float64 twin (``reference``, the truth of
the splatting model), then each backend at a ladder of settings, and writes one row per run:
{scene, renderer, settings, against, quantity, time_s, mean_abs, max_abs, psnr}. Image rows are
compared with the twin (``against``); the gsplat peer also with ours at gsplat's alpha clamp;
pyrender points give centre (px) and depth (relative) errors against our projection.
Backends that do not apply to a scene, or are not installed here, are listed as skipped with
the reason. Outputs: ``compare.csv``, ``compare.json`` (one table over every scene compared into
the folder: a scene run again replaces its rows), error maps and a Pareto plot per scene.
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import torch

from gdbench.refcheck.scenes import Fixture, fixture_names, load_fixture

SPLAT_LADDER: list[dict] = [
    {},
    {"t_min": 1e-3},
    {"t_min": 1e-2},
    {"alpha_min": 0.02},
    {"eps2d": 0.1},
    {"backend": "torch"},
]
"""Settings of the splat renderer tried on every scene ({} is the default)."""


@dataclass
class Result:
    rows: list[dict] = field(default_factory=list)
    skipped: list[dict] = field(default_factory=list)
    images: dict[str, torch.Tensor] = field(default_factory=dict)
    verdicts: list[dict] = field(default_factory=list)
    """Conformance rows (``conformance.check``), one per renderer of the protocol's shape."""
    twins: dict = field(default_factory=dict)
    """The twin's images and gradients by alpha clamp, computed once per scene."""


def _timed(fn: Callable[[], object], repeats: int = 3) -> tuple[object, float]:
    """(result, median seconds). ``repeats=0`` times the single call that makes the result
    (for slow references, where a warm-up run would double the cost)."""
    if repeats == 0:
        t0 = time.perf_counter()
        out = fn()
        return out, time.perf_counter() - t0
    out = fn()  # warm-up (and the result)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return out, statistics.median(times)


def image_errors(img: torch.Tensor, ref: torch.Tensor) -> dict[str, float]:
    d = (img.double() - ref.double()).abs()
    mse = float((d**2).mean())
    return {
        "mean_abs": float(d.mean()),
        "max_abs": float(d.max()),
        "psnr": float("inf") if mse == 0 else -10 * torch.log10(torch.tensor(mse)).item(),
    }


def _render_args(fx: Fixture) -> dict:
    c = fx.cameras
    return dict(
        **fx.scene.render_args(), viewmats=c.viewmats, Ks=c.Ks, width=c.width, height=c.height, background=fx.background
    )


def run_reference(fx: Fixture, res: Result) -> torch.Tensor:
    from renderers.splat.reference import rasterize_reference

    out, t = _timed(lambda: rasterize_reference(**_render_args(fx), outputs=("rgb",)).rgb, repeats=1)
    res.rows.append(
        {
            "scene": fx.name,
            "renderer": "reference",
            "settings": "float64 dense",
            "against": "-",
            "quantity": "rgb",
            "time_s": t,
            "mean_abs": 0.0,
            "max_abs": 0.0,
            "psnr": float("inf"),
        }
    )
    res.images["reference"] = out
    return out


def run_splat(fx: Fixture, res: Result, truth: torch.Tensor) -> None:
    from renderers.splat import rasterize

    for settings in SPLAT_LADDER:
        out, t = _timed(lambda s=settings: rasterize(**_render_args(fx), **s, outputs=("rgb",)).rgb)
        name = ",".join(f"{k}={v}" for k, v in settings.items()) or "default"
        res.rows.append(
            {
                "scene": fx.name,
                "renderer": "splat",
                "settings": name,
                "against": "reference",
                "quantity": "rgb",
                "time_s": t,
                **image_errors(out, truth),
            }
        )
        res.images[f"splat[{name}]"] = out


def run_gsplat(fx: Fixture, res: Result, truth: torch.Tensor) -> None:
    from gdbench.refcheck.backends import get

    ALPHA_MAX = get("gsplat_torch").alpha_max
    from renderers.gsplat_torch import rasterize as gsplat_rasterize
    from renderers.splat import rasterize

    a = _render_args(fx)
    out, t = _timed(lambda: gsplat_rasterize(**a).rgb, repeats=1)
    ours = rasterize(**a, alpha_max=ALPHA_MAX).rgb
    base = {
        "scene": fx.name,
        "renderer": "gsplat_torch",
        "settings": "gsplat 1.5.3 torch stages",
        "quantity": "rgb",
        "time_s": t,
    }
    res.rows.append({**base, "against": f"splat[alpha_max={ALPHA_MAX}]", **image_errors(out, ours)})
    res.rows.append({**base, "against": "reference", **image_errors(out, truth)})
    res.images["gsplat_torch"] = out


def run_points(fx: Fixture, res: Result, truth: torch.Tensor) -> None:
    from renderers.pyrender_points.points import render_points
    from renderers.splat.project import project

    c, s = fx.cameras, fx.scene
    gl, t = _timed(lambda: render_points(s.means, c.viewmats, c.Ks, c.width, c.height), repeats=1)
    p = project(s.means, s.quats, s.scales, s.opacities, c.viewmats, c.Ks, c.width, c.height)
    seen = torch.isfinite(gl.depths)
    if not bool(seen.any()):
        res.skipped.append({"scene": fx.name, "renderer": "pyrender_points", "reason": "no centre inside the view"})
        return
    px = (gl.means2d[seen] - p.means2d.double()[seen]).abs().amax(-1)
    rel = ((gl.depths[seen] - p.depths.double()[seen]) / p.depths.double()[seen]).abs()
    base = {
        "scene": fx.name,
        "renderer": "pyrender_points",
        "settings": "16x supersampled points",
        "against": "splat projection",
        "time_s": t,
        "psnr": float("nan"),
    }
    res.rows.append({**base, "quantity": "centre_px", "mean_abs": float(px.mean()), "max_abs": float(px.max())})
    res.rows.append({**base, "quantity": "depth_rel", "mean_abs": float(rel.mean()), "max_abs": float(rel.max())})


MITSUBA_SPP = (4, 16, 64)


def run_mitsuba_ellipsoids(fx: Fixture, res: Result, truth: torch.Tensor) -> None:
    from renderers.mitsuba.ellipsoids import rasterize as mi_rasterize

    for spp in MITSUBA_SPP:
        out, t = _timed(lambda s=spp: mi_rasterize(**_render_args(fx), spp=s).rgb, repeats=1)
        res.rows.append(
            {
                "scene": fx.name,
                "renderer": "mitsuba_ellipsoids",
                "settings": f"spp={spp}",
                "against": "reference",
                "quantity": "rgb",
                "time_s": t,
                **image_errors(out, truth),
            }
        )
        res.images[f"mitsuba_ellipsoids[spp={spp}]"] = out


VOLUME_LADDERS = {
    # (high setting, ladder); each ladder entry varies one of S (steps), spp, R (grid resolution)
    "analytic": (
        {"steps": 512, "spp": 64},
        [
            {"steps": 16, "spp": 16},
            {"steps": 64, "spp": 16},
            {"steps": 256, "spp": 16},
            {"steps": 128, "spp": 4},
            {"steps": 128, "spp": 64},
        ],
    ),
    "grid": (
        {"resolution": 128, "steps": 256, "spp": 32},
        [
            {"resolution": 16, "steps": 128, "spp": 16},
            {"resolution": 32, "steps": 128, "spp": 16},
            {"resolution": 64, "steps": 128, "spp": 16},
            {"resolution": 64, "steps": 32, "spp": 16},
            {"resolution": 64, "steps": 128, "spp": 4},
            {"resolution": 64, "steps": 128, "spp": 32},
        ],
    ),
}


def _run_volume(mode: str, fx: Fixture, res: Result, truth: torch.Tensor) -> None:
    from renderers.mitsuba.volume import rasterize as vol_rasterize

    name = f"mitsuba_volume_{mode}"
    high_cfg, ladder = VOLUME_LADDERS[mode]
    high, t_high = _timed(lambda: vol_rasterize(**_render_args(fx), mode=mode, **high_cfg).rgb, repeats=0)
    label = lambda cfg: ",".join(f"{k}={v}" for k, v in cfg.items())  # noqa: E731
    base = {"scene": fx.name, "renderer": name, "quantity": "rgb"}
    res.rows.append(
        {**base, "settings": label(high_cfg), "against": "reference", "time_s": t_high, **image_errors(high, truth)}
    )
    res.images[f"{name}[{label(high_cfg)}]"] = high
    for cfg in ladder:
        out, t = _timed(lambda c=cfg: vol_rasterize(**_render_args(fx), mode=mode, seed=1, **c).rgb, repeats=0)
        res.rows.append(
            {
                **base,
                "settings": label(cfg),
                "against": f"{name}[{label(high_cfg)}]",
                "time_s": t,
                **image_errors(out, high),
            }
        )


def run_volume_analytic(fx: Fixture, res: Result, truth: torch.Tensor) -> None:
    _run_volume("analytic", fx, res, truth)


def run_volume_grid(fx: Fixture, res: Result, truth: torch.Tensor) -> None:
    _run_volume("grid", fx, res, truth)


BACKENDS: dict[str, Callable] = {
    "splat": run_splat,
    "gsplat_torch": run_gsplat,
    "pyrender_points": run_points,
    "mitsuba_ellipsoids": run_mitsuba_ellipsoids,
    "mitsuba_volume_analytic": run_volume_analytic,
    "mitsuba_volume_grid": run_volume_grid,
}
"""How each registered backend (``gdbench/refcheck/backends.py``) is compared against the reference:
the fixture-specific work (settings ladders, error rows), by the registry's names."""

JUDGED = {"splat": ("splat", "splat_torch"), "gsplat_torch": ("gsplat_torch",),
          "mitsuba_ellipsoids": ("mitsuba_ellipsoids",)}  # fmt: skip
"""Backend -> the renderers of the protocol's shape it stands for, each given a conformance verdict
(at the backend's comparable settings: the C++ and torch paths of splat at their defaults, Mitsuba
at 16 spp)."""


def run_renderer(spec, fx: Fixture, res: Result, truth: torch.Tensor) -> None:
    """A renderer of the user's (``protocol.RendererSpec``) against the float64 twin at its own
    alpha clamp: its image row (error against run time) and its conformance verdict (``judge``);
    SKIP with the reason where the renderer lacks what the scene needs; FAIL with one line where it
    raises or returns the wrong thing (the other cases still run)."""
    reason = spec.why_not(fx.scene.sh_degree)
    verdict = {"case": fx.name, "kind": "fixture", "renderer": spec.name, "class": spec.tolerance}
    if reason is not None:
        res.skipped.append({"scene": fx.name, "renderer": spec.name, "reason": reason, "verdict": "SKIP"})
        res.verdicts.append(verdict | {"verdict": "SKIP", "reason": reason})
        return
    a = _render_args(fx)
    if spec.alpha_max != 0.99:  # the twin at the renderer's clamp
        from renderers.splat.reference import rasterize_reference

        truth = rasterize_reference(**a, alpha_max=spec.alpha_max, outputs=("rgb",)).rgb
    base = {"scene": fx.name, "renderer": spec.name, "settings": f"{spec.tolerance} class",
            "against": f"reference[alpha_max={spec.alpha_max}]", "quantity": "rgb"}  # fmt: skip
    args = [a[k] for k in ("means", "quats", "scales", "opacities", "colors", "viewmats", "Ks", "width", "height")]
    try:
        out, t = _timed(lambda: spec.render(*args, background=a["background"], outputs=("rgb", "alpha"))["rgb"])
    except Exception as e:  # the renderer's own failure: a row of its own, then the next case
        why = f"{type(e).__name__}: {e}".splitlines()[0]
        res.rows.append(base | {"time_s": None, "verdict": "FAIL", "reason": why})
        res.verdicts.append(verdict | {"verdict": "FAIL", "reason": why})
        return
    res.rows.append(base | {"time_s": t, **image_errors(out, truth)})
    res.images[spec.name] = out
    judge(spec, fx, res, attach=True)


def judge(spec, fx: Fixture, res: Result, attach: bool = False) -> dict:
    """The conformance verdict of ``spec`` on ``fx`` (``conformance.check``: rgb, alpha and the
    gradients' directional derivatives against the twin, PASS/FAIL/SKIP against the scene's
    tolerance for the renderer's class), kept in ``res.verdicts`` and, with ``attach``, on the
    renderer's image row (a user's renderer has one; a built-in's ladder rows are other settings)."""
    from gdbench.refcheck.conformance import check, fixture_case

    row = check(spec, fixture_case(fx), res.twins)
    res.verdicts.append(row)
    for r in res.rows if attach else []:
        if r["renderer"] == spec.name and r["scene"] == fx.name and r.get("time_s") is not None:
            r |= {"verdict": row["verdict"], "reason": row["reason"], "grad_err": row.get("grad_err")}
    return row


def scene_key(backend: str) -> str:
    """The key under which a fixture declares a backend: the splat renderer answers to the twin."""
    return "reference" if backend == "splat" else backend


def available(name: str) -> tuple[bool, str]:
    """Whether a backend can run on this machine, and if not, what to install (the registry's)."""
    from gdbench.refcheck.backends import get

    return get(name).available()


def compare_scene(fx: Fixture, backends: list[str] | None = None, bar=None, renderers: list | None = None) -> Result:
    """Every backend of ``backends`` (default: every built-in one, unless ``renderers`` are given)
    and every renderer of the user's in ``renderers`` (``protocol.RendererSpec``s) on ``fx``
    against its float64 reference (``bar``: a progress report, advanced once per renderer)."""
    res = Result()
    truth = run_reference(fx, res)
    for spec in renderers or []:
        if bar is not None:
            bar.update(1)
            bar.set_postfix(scene=fx.name, renderer=spec.name)
        run_renderer(spec, fx, res, truth)
    for name in backends if backends is not None else ([] if renderers else list(BACKENDS)):
        if bar is not None:
            bar.update(1)
            bar.set_postfix(scene=fx.name, renderer=name)
        reason = fx.skip_reason(scene_key(name))
        if reason is None:
            ok, why = available(name)
            reason = None if ok else f"not available here: {why}"
        if reason is not None:
            res.skipped.append({"scene": fx.name, "renderer": name, "reason": reason})
            continue
        BACKENDS[name](fx, res, truth)
        for judged in JUDGED.get(name, ()):
            from gdbench.refcheck.protocol import builtin

            judge(builtin(judged), fx, res)
    return res


def earlier_report(out: Path) -> dict:
    """The compare.json already in ``out`` ({} if none); a broken one raises, naming it."""
    from gdbench.core.io import read_json

    return read_json(out / "compare.json", what="compare.json") if (out / "compare.json").is_file() else {}


def write_report(results: dict[str, Result], out: Path, old: dict | None = None) -> dict[str, Path]:
    """compare.csv and compare.json hold one table with a ``scene`` column: the rows of the
    scenes run now replace their earlier rows (``old``: the earlier compare.json), other
    scenes' rows stay, and an error map or Pareto plot of a fixture scene that has no row is
    removed (a file never outlives its rows)."""
    from gdbench.core.io import write_csv, write_json

    out.mkdir(parents=True, exist_ok=True)
    old = earlier_report(out) if old is None else old
    keep = lambda items: [r for r in items if isinstance(r, dict) and r.get("scene") not in results]  # noqa: E731
    rows = keep(old.get("rows", [])) + [r for res in results.values() for r in res.rows]
    skipped = keep(old.get("skipped", [])) + [s for res in results.values() for s in res.skipped]
    verdicts = [v for v in old.get("verdicts", []) if isinstance(v, dict) and v.get("case") not in results]
    verdicts += [v for res in results.values() for v in res.verdicts]
    paths = {
        "csv": write_csv(rows, out / "compare.csv"),
        "json": write_json({"rows": rows, "skipped": skipped, "verdicts": verdicts}, out / "compare.json"),
    }
    for scene, res in results.items():
        paths[f"{scene}_errors"] = _error_maps(res, out / f"{scene}_errors.png")
        paths[f"{scene}_pareto"] = _pareto(scene, res.rows, out / f"{scene}_pareto.png")
    scenes = {r["scene"] for r in rows}
    for scene in set(fixture_names()) - scenes:  # only names compare writes
        for kind in ("errors", "pareto"):
            (out / f"{scene}_{kind}.png").unlink(missing_ok=True)
    return paths


def _error_maps(res: Result, path: Path) -> Path:
    import imageio.v3 as iio

    truth = res.images["reference"][0].float()
    tiles = [truth.clamp(0, 1)]
    for name, img in res.images.items():
        if name == "reference":
            continue
        err = (img[0].float() - truth).abs().amax(-1, keepdim=True)
        scale = max(float(err.max()), 1e-6)
        tiles.append((err / scale).expand(*err.shape[:2], 3))  # each map normalised to its own max
    from gdbench.core.io import atomic_path

    with atomic_path(path) as tmp:
        iio.imwrite(tmp, (torch.cat(tiles, 1) * 255).round().byte().numpy())
    return path


def _pareto(scene: str, rows: list[dict], path: Path) -> Path:
    from gdbench.core.plotting import pyplot, save

    plt = pyplot()

    fig, ax = plt.subplots(figsize=(6.5, 4.2))
    markers = {
        "splat": "o",
        "gsplat_torch": "s",
        "mitsuba_ellipsoids": "^",
        "mitsuba_volume_analytic": "D",
        "mitsuba_volume_grid": "P",
    }
    for r in rows:
        if r["quantity"] != "rgb" or r["against"] != "reference" or r["renderer"] == "reference":
            continue
        ax.loglog(
            max(r["time_s"], 1e-5),
            max(r["mean_abs"], 1e-9),
            markers.get(r["renderer"], "x"),
            label=f"{r['renderer']} {r['settings']}",
        )
    ax.set_xlabel("run time (s)")
    ax.set_ylabel("mean |error| against the float64 twin")
    ax.set_title(f"{scene}: error against run time", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize=6)
    return save(fig, path, dpi=100)


def print_table(results: dict[str, Result]) -> None:
    print(
        f"{'scene':18s} {'renderer':16s} {'settings':26s} {'against':24s} {'qty':10s} {'time s':>9s} "
        f"{'mean|e|':>9s} {'max|e|':>9s} {'PSNR':>7s}"
    )
    for res in results.values():
        for r in res.rows:
            head = f"{r['scene']:18s} {r['renderer']:16s} {r['settings'][:26]:26s} {r['against'][:24]:24s} "
            if r.get("time_s") is None:  # the renderer raised: no numbers
                print(head + f"FAIL: {r.get('reason', '')}")
                continue
            verdict = f" {r['verdict']}" + (f" ({r['reason']})" if r.get("reason") else "") if "verdict" in r else ""
            print(
                head + f"{r['quantity']:10s} {r['time_s']:9.4f} {r['mean_abs']:9.2e} {r['max_abs']:9.2e} "
                f"{r['psnr']:7.1f}{verdict}"
            )
        for s in res.skipped:
            print(f"{s['scene']:18s} {s['renderer']:16s} {s.get('verdict', 'skipped')}: {s['reason']}")
        for v in res.verdicts:
            errs = "" if "time_s" not in v else (
                f" (image {max(v['max_err_rgb'], v['max_err_alpha']):.1e}, gradient "
                + ("-" if v.get("grad_err") is None else f"{v['grad_err']:.1e}") + ")"
            )  # fmt: skip
            why = f": {v['reason']}" if v.get("reason") else ""
            print(f"{v['case']:18s} {v['renderer']:16s} {v['class']} class {v['verdict']}{errs}{why}")


def run(
    scenes: str | list[str] = "all",
    backends: list[str] | None = None,
    out: Path = Path("runs/compare"),
    verbose: bool = True,
    renderers: list[str] | None = None,
) -> dict[str, Result]:
    """Compare renderers on fixture scenes: the built-in ``backends`` (default: all of them, or none
    where ``renderers`` are given) and the user's ``renderers`` (``module:function`` or registered
    names, ``protocol.load_renderer``); writes the report to ``out``."""
    from gdbench.refcheck.protocol import load_or_fail

    specs = [load_or_fail(r) for r in renderers or []]  # one that cannot load fails each case, with the reason
    names = fixture_names() if scenes == "all" else ([scenes] if isinstance(scenes, str) else list(scenes))
    unknown = [b for b in backends or [] if b not in BACKENDS]
    if unknown:
        raise ValueError(f"backends: unknown {unknown}; known: {sorted(BACKENDS)}")
    missing = [n for n in names if n not in fixture_names()]
    if missing:  # before --out is made and before any progress
        raise ValueError(f"scene (--scene): no fixture named {missing[0]!r}; known: {fixture_names()}")
    from gdbench.core.io import writable_folder

    writable_folder(out)  # a read-only --out fails now, not after the rendering
    old = earlier_report(Path(out))  # a broken table is named before any rendering
    from gdbench.core.progress import progress

    results = {}
    chosen = backends if backends is not None else ([] if specs else list(BACKENDS))
    bar = progress(len(names) * (len(chosen) + len(specs)), "compare", "renderer", disable=not verbose)
    try:
        for n in names:
            results[n] = compare_scene(load_fixture(n), chosen, bar, specs)
    finally:
        if bar is not None:
            bar.close()
    paths = write_report(results, Path(out), old)
    if verbose:
        print_table(results)
        print(f"wrote {paths['csv']}, {paths['json']} and per-scene error maps and Pareto plots in {out}")
    return results
