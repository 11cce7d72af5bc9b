"""Write the conformance tolerances of every case (gdbench/refcheck/conformance.py): the fixtures'
``tolerances`` blocks and fixtures/stability_tolerances.json (the stiff and extreme cases).

- ``exact`` (a float32 rasterizer of gdbench's image model): stated, not measured: images within
  1e-5 mean and 1e-4 max of the float64 twin, directional derivatives within 1e-3 relative (floor
  1e-3 of the group's gradient, allowance 1e-7 of the case's largest); one case states a smaller
  allowance (``EXACT_OVERRIDES``, with its reason).
- ``approximate`` (another image model of the same scene): what gdbench's reference ray tracer
  (Mitsuba ellipsoids, 16 spp, seed 0) reaches on the case, times 1.5; a case where its image
  differs from the splatted one by more than 0.5 somewhere is not applicable to the class (the two
  models differ there by construction), and where its gradients differ by more than 0.5 relative
  they are not judged. Run again only when the ray tracer changes; the diff shows what moved.

    python scripts/calibrate_tolerances.py
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from gdbench.refcheck import conformance
from gdbench.refcheck.protocol import builtin
from gdbench.refcheck.tolerance import CLASSES, Tolerance

ROOT = Path(__file__).resolve().parents[1]
EXACT = {"mean_abs": 1e-5, "max_abs": 1e-4, "grad_rel": 1e-3, "grad_floor": 1e-3, "grad_atol": 1e-7}
EXACT_OVERRIDES = {
    "huge scale 1e4": (
        {"grad_atol": 1e-14},
        "the scales' gradient is 3e-12 of the opacity's here (d/ds of a Gaussian 1e4 wide): a smaller "
        "allowance, so that its sign is judged (the C++ backward once flipped it)",
    ),
}
MARGIN = 1.5
FLOOR, ATOL = 0.2, 1e-4
"""The approximate class's gradient floor and allowance (tolerance.Tolerance), with which the ray
tracer's errors are measured."""


def _up(x: float, floor: float) -> float:
    """``x`` times the margin, rounded up to two significant digits, at least ``floor``."""
    x = max(x * MARGIN, floor)
    e = math.floor(math.log10(x)) - 1
    return float(f"{math.ceil(x / 10**e) * 10**e:.2g}")  # two digits, no float noise in the JSON


def approximate(row: dict) -> dict | str:
    img = max(row.get("max_err_rgb", 0.0), row.get("max_err_alpha", 0.0))
    if row.get("verdict") == "SKIP" or "time_s" not in row:
        return f"the reference ray tracer does not run here: {row.get('reason', '')}"
    if img > 0.5:
        return (f"another image model differs by construction here (the ray-traced ellipsoids differ from the "
                f"splatted image by {img:.2f})")  # fmt: skip
    mean = max(row.get("mean_err_rgb", 0.0), row.get("mean_err_alpha", 0.0))
    tol = {"mean_abs": _up(mean, 1e-4), "max_abs": _up(img, 1e-3)}
    g = row.get("grad_err")
    if g is None or g > 0.5:
        tol["gradients"] = f"the ray tracer's directional derivatives differ by {g:.2g} relative here: not judged"
    else:
        tol |= {"grad_rel": _up(g, 0.05), "grad_floor": FLOOR, "grad_atol": ATOL}
    return tol


def exact(name: str) -> dict:
    over, why = EXACT_OVERRIDES.get(name, ({}, ""))
    return EXACT | over | ({"note": why} if why else {})


def main() -> int:
    ray = builtin("mitsuba_ellipsoids")
    if ray.unavailable:
        raise SystemExit(f"calibrate_tolerances: the ray tracer is needed: {ray.unavailable}")
    # measured with every class stated as applicable, so that every case is run
    loose = {"mean_abs": 1.0, "max_abs": 1.0, "grad_rel": 1.0, "grad_floor": FLOOR, "grad_atol": ATOL}
    stiff = {}
    every = {c: Tolerance(**loose) for c in CLASSES}
    for name, make in conformance.case_names().items():
        case = make() if name in conformance.case_names(("fixture",)) else conformance.stiff_case(name, every)
        case.tolerances = every
        row = conformance.check(ray, case)
        entry = {"exact": exact(name), "approximate": approximate(row)}
        print(f"{name:32s} ray tracer: image {row.get('max_err_rgb', 0):.2e} grad {row.get('grad_err')}")
        if case.kind == "fixture":
            path = ROOT / "fixtures" / "scenes" / f"{name}.json"
            spec = json.loads(path.read_text())
            spec["tolerances"] = entry
            path.write_text(json.dumps(spec, indent=2) + "\n")
        else:
            stiff[name] = entry
    out = ROOT / "fixtures" / "stability_tolerances.json"
    out.write_text(json.dumps(stiff, indent=2) + "\n")
    print(f"wrote the fixtures' tolerances and {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
