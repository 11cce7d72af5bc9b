"""Paired comparison of two sets of runs at the same seeds (CPU against CUDA, old kernels against
new): GT PSNR and the view metrics' failure rates per seed, and the mean difference of each with
its 95% t interval.

    python scripts/paired_runs.py --a 'runs/cpu_{s}/scores.json' --b 'runs/cuda_{s}/scores.json' \\
        --seeds 0-7 --out paired.csv

``{s}`` in --a and --b is the seed. Writes one row per seed and quantity, then one summary row
per quantity (seed 'mean b-a', with ci_lo and ci_hi), and prints the summary.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import statistics
from pathlib import Path

QUANTITIES = {
    "gt_psnr": ("gt", "psnr"),
    "gaussians": (None, "gaussians"),
    "featureless_rate": ("views", "featureless_rate"),
    "multi_face_rate": ("views", "multi_face_rate"),
}


def _seeds(text: str) -> list[int]:
    if "-" in text:
        lo, hi = text.split("-")
        return list(range(int(lo), int(hi) + 1))
    return [int(x) for x in text.split(",")]


def _read(path: Path) -> dict[str, float]:
    if not path.is_file():
        raise SystemExit(f"--a/--b: no scores.json at {path}")
    d = json.loads(path.read_text())
    return {q: float(d[block][key] if block else d[key]) for q, (block, key) in QUANTITIES.items()}


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
    args = ap.parse_args(argv)
    rows, diffs = [], {q: [] for q in QUANTITIES}
    for s in _seeds(args.seeds):
        a, b = _read(Path(args.a.format(s=s))), _read(Path(args.b.format(s=s)))
        for q in QUANTITIES:
            rows.append({"seed": s, "quantity": q, "a": a[q], "b": b[q], "b_minus_a": b[q] - a[q]})
            diffs[q].append(b[q] - a[q])
    for q, d in diffs.items():
        m, lo, hi = t_interval(d)
        rows.append({"seed": "mean b-a", "quantity": q, "b_minus_a": m, "ci_lo": lo, "ci_hi": hi})
        print(f"{q}: mean b - a {m:+.4g}, 95% CI [{lo:+.4g}, {hi:+.4g}] over {len(d)} seeds")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    with open(args.out, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=["seed", "quantity", "a", "b", "b_minus_a", "ci_lo", "ci_hi"])
        w.writeheader()
        w.writerows(rows)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
