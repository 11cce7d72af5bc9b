"""Paired comparison of two sets of runs at the same seeds (CPU against CUDA, old kernels against
new): GT PSNR and the view metrics' failure rates per seed, and the mean difference of each with
its 95% t interval.

    python scripts/paired_runs.py --a 'runs/cpu_{s}/scores.json' --b 'runs/cuda_{s}/scores.json' \\
        --seeds 0-7 --out paired.csv

``{s}`` in --a and --b is the seed. Writes one row per seed and quantity, then one summary row
per quantity (seed 'mean b-a', with ci_lo and ci_hi), and prints the summary. The quantities: GT
PSNR, the Gaussians, the view metrics' class rates (the share of a result's views in each failure
class) and, per result class (``result_class``: front_everywhere, second_face, blob, fine), 1 where
the result is of that class: its mean over the seeds is the class's rate.

``--check`` applies issue 56's rule for a change of kernels (docs/performance.md): it passes when
the GT PSNR difference's 95% interval lies above -0.2 dB and no failure class's rate, over the
results or over their views, rises by more than 0.05; the exit status is 1 when it fails.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # this checkout's gdbench, without the install
from gdbench.metrics.views import CLASSES, result_class

QUANTITIES = {
    "gt_psnr": ("gt", "psnr"),
    "gaussians": (None, "gaussians"),
    "featureless_rate": ("views", "featureless_rate"),
    "multi_face_rate": ("views", "multi_face_rate"),
    "front_everywhere_rate": ("views", "front_everywhere_rate"),
    "blob_rate": ("views", "blob_rate"),
}
FAILURES = ("multi_face_rate", "front_everywhere_rate", "blob_rate", "featureless_rate") + tuple(
    f"result_{c}" for c in CLASSES if c != "fine"
)
"""The quantities whose rise is a failure class's (``--check``)."""
PSNR_FLOOR_DB, RATE_RISE = -0.2, 0.05


def _seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(x) for x in text.split(",")]


def _read(path: Path) -> dict[str, float]:
    """The quantities of one scores.json (NaN where an older file or a frontless asset has none)."""
    if not path.is_file():
        raise SystemExit(f"--a/--b: no scores.json at {path}")
    d = json.loads(path.read_text())
    out = {}
    for q, (block, key) in QUANTITIES.items():
        value = (d.get(block) or {}).get(key) if block else d.get(key)
        out[q] = math.nan if value is None else float(value)
    views = d.get("views") or {}
    got = result_class(views) if views.get("janus_rate") is not None else None
    for c in CLASSES:
        out[f"result_{c}"] = math.nan if got is None else float(got == c)
    return out


def check(summary: dict[str, tuple[float, float, float]], one_sided: dict[str, list] | None = None) -> list[str]:
    """What fails issue 56's rule in the summary {quantity: (mean b - a, ci_lo, ci_hi)}: the PSNR
    interval (which needs two seeds or more) reaching -0.2 dB, a failure class's rate rising by
    more than 0.05, or a quantity of either present on one side only at some seed (``one_sided``:
    {quantity: those seeds}; a candidate that diverges to NaN or loses a block fails)."""
    failed = []
    lo = summary["gt_psnr"][1] if "gt_psnr" in summary else None
    if lo is None:
        failed.append("gt_psnr: no seed has a GT PSNR on both sides")
    elif lo != lo:
        failed.append("gt_psnr: one seed gives no interval; expected two or more")
    elif not lo > PSNR_FLOOR_DB:
        failed.append(f"gt_psnr: the 95% interval reaches {lo:+.3f} dB, below {PSNR_FLOOR_DB} dB")
    for q in FAILURES:
        m = summary.get(q, (math.nan,))[0]  # NaN on both sides (a frontless asset's classes) raises nothing
        if m > RATE_RISE:
            failed.append(f"{q}: rises by {m:+.3f}, more than {RATE_RISE}")
    for q, seeds in (one_sided or {}).items():
        if seeds and (q == "gt_psnr" or q in FAILURES):
            failed.append(f"{q}: present on one side only at seeds {seeds}")
    return failed


def t_interval(diffs: list[float]) -> tuple[float, float, float]:
    """Mean and 95% t interval of the paired differences."""
    from scipy.stats import t

    n = len(diffs)
    m = statistics.fmean(diffs)
    if n < 2:
        return m, math.nan, math.nan
    half = t.ppf(0.975, n - 1) * statistics.stdev(diffs) / math.sqrt(n)
    return m, m - half, m + half


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--a", required=True, help="scores.json path with {s} for the seed (the reference)")
    ap.add_argument("--b", required=True, help="scores.json path with {s} for the seed (the candidate)")
    ap.add_argument("--seeds", default="0-7", help="'0-7' or '0,1,2'")
    ap.add_argument("--out", type=Path, required=True, help="the CSV to write")
    ap.add_argument("--check", action="store_true", help="apply issue 56's rule; exit 1 when it fails")
    args = ap.parse_args(argv)
    rows, diffs, summary, one_sided = [], {}, {}, {}
    for s in _seeds(args.seeds):
        a, b = _read(Path(args.a.format(s=s))), _read(Path(args.b.format(s=s)))
        for q in a:
            rows.append({"seed": s, "quantity": q, "a": a[q], "b": b[q], "b_minus_a": b[q] - a[q]})
            diffs.setdefault(q, []).append(b[q] - a[q])
            if (a[q] == a[q]) != (b[q] == b[q]):  # NaN or missing on one side only
                one_sided.setdefault(q, []).append(s)
    for q, d in diffs.items():
        d = [x for x in d if x == x]  # both sides NaN: a frontless asset has no class rates
        if not d:
            continue
        m, lo, hi = summary[q] = t_interval(d)
        rows.append({"seed": "mean b-a", "quantity": q, "b_minus_a": m, "ci_lo": lo, "ci_hi": hi})
        print(f"{q}: mean b - a {m:+.4g}, 95% CI [{lo:+.4g}, {hi:+.4g}] over {len(d)} seeds")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["seed", "quantity", "a", "b", "b_minus_a", "ci_lo", "ci_hi"])
        w.writeheader()
        w.writerows(rows)
    if args.check:
        failed = check(summary, one_sided)
        print("check (issue 56):", "passed" if not failed else "FAILED: " + "; ".join(failed))
        return 1 if failed else 0
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
