"""Conformance: a renderer's images and gradients against the float64 twin, PASS, FAIL or SKIP per
case against the case's stated tolerance for the renderer's class (docs/references.md,
"Bring your own renderer").

The cases are the fixture scenes (``fixtures/scenes/*.json``, their ``tolerances``) and the stiff and
extreme cases of the stability benchmark (``bm_stability.cases``, their tolerances in
fixtures/stability_tolerances.json). Each carries, for every tolerance class, either a ``Tolerance`` or the
reason the class does not apply (a SKIP). A renderer picks its class (``RendererSpec.tolerance``):

- ``exact``: a rasterizer of gdbench's image model in float32 (the splat renderer, gsplat);
- ``approximate``: another image model of the same scene (a ray tracer of the ellipsoids).

Images: the max and mean absolute error of rgb and alpha against the twin run at the renderer's own
alpha clamp. Gradients (where the renderer declares them): a fixed random cotangent is pulled back
through rgb and alpha, and per parameter group (means, quats, scales, opacities, colours) the
gradient's directional derivative along ``DIRECTIONS`` seeded random directions is compared with the
twin's, exact in float64. A derivative passes when ``|d - d_twin| <= max(grad_rel * max(|d_twin|,
grad_floor * |g_twin| u), grad_atol |G_twin| u)`` with ``u = |v| / sqrt(n)`` (n: the group's size, so
``|g| u`` is a derivative's typical size along a random direction): relative, with a floor for
derivatives near zero stated as a fraction of that typical size, which scales with the group, and
an allowance for a group whose gradient is zero in exact arithmetic (an isotropic Gaussian's
rotation, where float32 leaves ~3e-8 of the scales' gradient), stated as a fraction of the case's
largest group gradient ``|G_twin|`` (at least 1), on the same footing.
With ``grad_rel`` < 1 a wrong sign fails wherever the twin's derivative is above the allowances;
the report counts such derivatives.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import torch

from gdbench.refcheck.tolerance import Tolerance, parse_tolerances

F64 = torch.float64
PARAMS = ("means", "quats", "scales", "opacities", "sh")
GROUPS = {"means": "means", "quats": "quats", "scales": "scales", "opacities": "opacities", "sh": "colors"}
"""Parameter -> the group name reports use."""
DIRECTIONS = 3
"""Random directions per parameter group."""


@dataclass
class Case:
    """One conformance case, in float64: parameters (``sh`` [N, K, 3] coefficients), cameras,
    background, SH degree, and its tolerances by class."""

    name: str
    kind: str
    params: dict[str, torch.Tensor]
    camera: dict
    background: torch.Tensor
    tolerances: dict[str, Tolerance | str]
    sh_degree: int = 0


def fixture_case(fx) -> Case:
    """A fixture scene (a ``scenes.Fixture`` or its name) as a case."""
    from gdbench.refcheck.scenes import load_fixture

    fx = load_fixture(fx) if isinstance(fx, str) else fx
    s, c = fx.scene, fx.cameras
    params = {"means": s.means, "quats": s.quats, "scales": s.scales, "opacities": s.opacities, "sh": s.sh}
    camera = {"viewmats": c.viewmats.double(), "Ks": c.Ks.double(), "width": c.width, "height": c.height}
    return Case(fx.name, "fixture", {k: v.double() for k, v in params.items()}, camera, fx.background.double(),
                fx.tolerances, s.sh_degree)  # fmt: skip


STIFF_TOLERANCES = Path(__file__).resolve().parents[2] / "fixtures" / "stability_tolerances.json"
"""The stiff and extreme cases' tolerances, by case and class (scripts/calibrate_tolerances.py)."""


def stiff_case(name: str, tolerances: dict | None = None) -> Case:
    """A stiff case (``bm_stability.cases``) with its tolerances from ``STIFF_TOLERANCES`` (or
    ``tolerances``, already parsed); a case the file does not state is an error."""
    from gdbench.refcheck.stiff_cases import C0, cases

    gs, cam = cases()[name]()
    params = {k: gs[k] for k in ("means", "quats", "scales", "opacities")}
    params["sh"] = ((gs["colors"] - 0.5) / C0)[:, None]
    if tolerances is None:
        from gdbench.core.io import read_json

        stated = read_json(STIFF_TOLERANCES, what="the stiff cases' tolerances")
        tolerances = parse_tolerances(stated.get(name), f"{STIFF_TOLERANCES.name}: case {name!r}")
    return Case(name, "stiff", params, cam, torch.ones(3, dtype=F64), tolerances)


def case_names(kinds=("fixture", "stiff")) -> dict[str, Callable[[], Case]]:
    """Every case of the given kinds, by name, built lazily."""
    from gdbench.refcheck.scenes import fixture_names
    from gdbench.refcheck.stiff_cases import cases

    out: dict[str, Callable[[], Case]] = {}
    if "fixture" in kinds:
        out |= {n: (lambda n=n: fixture_case(n)) for n in fixture_names()}
    if "stiff" in kinds:
        out |= {n: (lambda n=n: stiff_case(n)) for n in cases()}
    return out


def _pullback(images: dict[str, torch.Tensor], params: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Gradients of <w, rgb> + <w', alpha> (w, w': fixed seeded normal cotangents), zero where a
    parameter is unused."""
    loss = 0.0
    for i, x in enumerate(images.values()):
        g = torch.Generator().manual_seed(i)
        loss = loss + (x * torch.randn(x.shape, generator=g, dtype=F64).to(x)).sum()
    names = [k for k in PARAMS if params[k].numel()]
    if not names or not isinstance(loss, torch.Tensor) or not loss.requires_grad:
        return {k: torch.zeros_like(params[k]) for k in names}
    grads = torch.autograd.grad(loss, [params[k] for k in names], allow_unused=True)
    return {k: (g if g is not None else torch.zeros_like(params[k])).detach() for k, g in zip(names, grads)}


def directions(params: dict[str, torch.Tensor], k: int = DIRECTIONS) -> dict[str, torch.Tensor]:
    """``k`` seeded normal directions per parameter group, [k, *shape], float64."""
    out = {}
    for i, (name, p) in enumerate(params.items()):
        g = torch.Generator().manual_seed(1000 + i)
        out[name] = torch.randn((k, *p.shape), generator=g, dtype=F64)
    return out


def gradient_errors(grads: dict, twin: dict, dirs: dict, tol: Tolerance) -> dict[str, dict]:
    """Per group: the worst derivative's error (|d - d_twin| over its allowance's scale), whether it
    passes, and how many derivatives had the wrong sign where the twin's is above the floor."""
    out = {}
    # the case's largest group gradient, at least 1 (a cotangent's order for one pixel: where the twin's
    # gradients are all zero, as nothing is drawn, the allowance is absolute)
    top = max([float(tg.double().norm()) for tg in twin.values()] + [1.0])
    for name, tg in twin.items():
        v = dirs[name]
        d_t = (v * tg.double()).flatten(1).sum(1)
        d_r = (v * grads[name].double()).flatten(1).sum(1) if name in grads else torch.zeros_like(d_t)
        # a derivative's typical size along a random direction: |g| |v| / sqrt(n), not Cauchy-Schwarz's |g| |v|
        # (sqrt(n) times larger for a group of n numbers: a floor that large would pass anything at 10k Gaussians)
        vn = v.flatten(1).norm(dim=1) / math.sqrt(max(tg.numel(), 1))
        scale = torch.maximum(d_t.abs(), tol.grad_floor * float(tg.double().norm()) * vn)
        scale = torch.maximum(scale, tol.grad_atol / tol.grad_rel * top * vn)
        miss = (d_r - d_t).abs()
        err = torch.where(miss == 0, torch.zeros_like(miss), miss / torch.clamp_min(scale, 1e-300))
        bad = err > tol.grad_rel
        finite = bool(torch.isfinite(d_r).all()) and bool(torch.isfinite(d_t).all())  # a NaN twin passes nothing
        worst = float(err.max()) if finite else math.inf
        wrong = int((bad & (d_r * d_t < 0)).sum())
        out[GROUPS[name]] = {"err": worst, "ok": finite and not bool(bad.any()), "wrong_sign": wrong}
    return out


def _render(fn: Callable, case: Case, dtype, **kw) -> tuple[dict, dict]:
    params = {k: v.to(dtype).clone().requires_grad_(True) for k, v in case.params.items()}
    cam = case.camera
    out = fn(*(params[k] for k in PARAMS), cam["viewmats"].to(dtype), cam["Ks"].to(dtype), cam["width"],
             cam["height"], background=case.background.to(dtype), **kw)  # fmt: skip
    return out, params


def twin(case: Case, alpha_max: float) -> tuple[dict, dict]:
    """The float64 twin's images and gradients for ``case`` at the alpha clamp ``alpha_max``."""
    from renderers.splat.reference import rasterize_reference

    out, params = _render(rasterize_reference, case, F64, sh_degree=case.sh_degree, alpha_max=alpha_max)
    images = {"rgb": out.rgb, "alpha": out.alpha}
    return {k: v.detach() for k, v in images.items()}, _pullback(images, params)


def check(spec, case: Case, twin_cache: dict | None = None, images_out: dict | None = None) -> dict:
    """One renderer (``protocol.RendererSpec``) on one case: a row with the image errors, the
    gradient errors per group and the verdict (PASS, FAIL or SKIP) with its reason. ``images_out``
    receives the first camera's rgb of the renderer and of the twin at its clamp, by (case, renderer)."""
    row: dict = {"case": case.name, "kind": case.kind, "renderer": spec.name, "class": spec.tolerance}
    tol = case.tolerances[spec.tolerance]
    why = spec.why_not(case.sh_degree) or (tol if isinstance(tol, str) else None)
    if why is not None:
        return row | {"verdict": "SKIP", "reason": why}
    key = (case.name, spec.alpha_max)
    cache = {} if twin_cache is None else twin_cache
    if key not in cache:
        cache[key] = twin(case, spec.alpha_max)
    t_images, t_grads = cache[key]
    try:
        t0 = time.perf_counter()
        images, params = _render(spec.render, case, torch.float32, outputs=("rgb", "alpha"))
        grads = _pullback(images, params) if spec.gradients else {}
        row["time_s"] = time.perf_counter() - t0
    except Exception as e:  # the renderer's own failure: this case fails with one line, the rest run
        return row | {"verdict": "FAIL", "reason": f"{type(e).__name__}: {e}".splitlines()[0][:200]}
    if images_out is not None:
        images_out[(case.name, spec.name)] = (images["rgb"][0].detach().double().cpu(), t_images["rgb"][0])
    fails = []
    finite = lambda ts: all(bool(torch.isfinite(t).all()) for t in ts)  # noqa: E731
    row["twin_finite"] = finite(t_images.values()) and finite(t_grads.values())
    row["alpha_max_twin"] = float(t_images["alpha"].max()) if t_images["alpha"].numel() else 0.0
    row["nan_out"] = not finite(images.values())
    row["nan_grad"] = not finite(grads.values())
    for name, x in images.items():
        d = (x.detach().double() - t_images[name]).abs()
        row[f"max_err_{name}"] = float(d.max()) if d.numel() else 0.0
        row[f"mean_err_{name}"] = float(d.mean()) if d.numel() else 0.0
        if not bool(torch.isfinite(x).all()):
            fails.append(f"{name} not finite")
        for stat, bound in (("max", tol.max_abs), ("mean", tol.mean_abs)):
            if not row[f"{stat}_err_{name}"] <= bound:
                fails.append(f"{name} {stat} error {row[f'{stat}_err_{name}']:.2e} > {bound:g}")
    if spec.gradients and not tol.gradients:
        errs = gradient_errors(grads, t_grads, directions(case.params), tol)
        row["grad_err"] = max((e["err"] for e in errs.values()), default=0.0)
        for group, e in errs.items():
            row[f"grad_err_{group}"] = e["err"]
            if not e["ok"]:
                sign = f", {e['wrong_sign']} of {DIRECTIONS} with the wrong sign" if e["wrong_sign"] else ""
                fails.append(f"{group} gradient error {e['err']:.2e} > {tol.grad_rel:g}{sign}")
    else:
        row["grad_err"] = None
    row["verdict"] = "FAIL" if fails else "PASS"
    unjudged = tol.gradients or ("" if spec.gradients else "the renderer declares no gradients")
    row["reason"] = "; ".join(fails) if fails else (f"images only: {unjudged}" if unjudged else "")
    return row


def run(specs: list, names: list[str] | None = None, kinds=("fixture", "stiff"), progress: bool = True,
        images_out: dict | None = None) -> list[dict]:  # fmt: skip
    """Every renderer on every case (``names``: a subset of ``case_names(kinds)``), one row each
    (``images_out``: as ``check``'s)."""
    known = case_names(kinds)
    names = list(known) if names is None else names
    unknown = [n for n in names if n not in known]
    if unknown:
        raise ValueError(f"cases: unknown {unknown}; known: {list(known)}")
    from gdbench.core.progress import track

    rows = []
    for n in track(names, desc="conformance", unit="case", disable=not progress):
        case, cache = known[n](), {}
        rows += [check(spec, case, cache, images_out) for spec in specs]
    return rows


def summary(rows: list[dict]) -> dict:
    """Counts of PASS, FAIL and SKIP per renderer, and the failing cases with their reasons."""
    out: dict = {}
    for r in rows:
        s = out.setdefault(r["renderer"], {"PASS": 0, "FAIL": 0, "SKIP": 0, "failed": []})
        s[r["verdict"]] += 1
        if r["verdict"] == "FAIL":
            s["failed"].append({"case": r["case"], "reason": r["reason"]})
    return out
