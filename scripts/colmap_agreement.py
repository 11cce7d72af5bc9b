"""COLMAP consistency in shares against one thread (issue 32; docs/log/2026-11-26_cell_cost.md, "COLMAP in two
shares"): both on the same images of the calibration fixtures and of trained scenes, resumable.

    python scripts/colmap_agreement.py --scenes runs/sweep/cells/easy --out docs/results/colmap_shares.csv

Each image set (the duck's four 3D fixtures and the per-view jitter, as tests/test_colmap.py
renders them, and every ``scene.ply`` under ``--scenes``) is scored with ``shares=1`` (COLMAP on
one thread throughout: the metric as the sweeps in docs/results were scored) and with the
default ``SHARES``, twice (the second run checks that the score repeats). One row per set, with
both scores, their seconds and the commit; a summary of the agreement is printed and written
beside the CSV (``_summary.json``). Rows already in the CSV (same set, same commit) are kept.
"""

from __future__ import annotations

import argparse
import csv
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

FIELDS = ("registration_rate", "failure_rate", "var_theta_deg2", "points3d")
FIXTURES = ("asset", "flicker", "floaters", "two-faced", "jittered")


def image_sets(scenes: list[Path]) -> list[tuple[str, object]]:
    """(name, a function giving the uint8 views on the 100-view circle) per set."""
    from gdbench.core.scene import GaussianScene
    from gdbench.core.turntable import render_views, to_uint8
    from gdbench.metrics.colmap_consistency import asset_circle_images, circle_poses, fixture_circle_images

    cams = circle_poses(100).cameras(256, 256)
    sets = []
    for kind in FIXTURES:
        if kind == "jittered":
            sets.append((f"fixture {kind}", lambda: asset_circle_images("a yellow duck", cams, mode="jittered")))
        else:
            sets.append(
                (f"fixture {kind}", lambda k=kind: fixture_circle_images("a yellow duck", cams, k, flicker=0.2))
            )
    for root in scenes:
        for ply in sorted(root.glob("**/scene.ply")):
            name = f"scene {ply.parent.relative_to(root)}"
            sets.append(
                (name, lambda p=ply: to_uint8(render_views(GaussianScene.load_ply(p), cams, background=(1.0,) * 3)))
            )
    return sets


def same(a: float, b: float) -> bool:
    return a == b or (math.isnan(a) and math.isnan(b))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", type=Path, nargs="*", default=[], help="folders searched for scene.ply")
    ap.add_argument("--out", type=Path, default=Path("bench_results/colmap_shares.csv"))
    args = ap.parse_args(argv)
    for root in args.scenes:
        if not root.is_dir():
            ap.error(f"--scenes: expected a folder, got {root}")
    from gdbench.core.io import write_json
    from gdbench.core.provenance import code_commit
    from gdbench.metrics.colmap_consistency import SHARES, circle_poses, score_images

    commit = code_commit()
    cams = circle_poses(100).cameras(256, 256)
    done: dict[str, dict] = {}
    if args.out.is_file():
        done = {r["set"]: r for r in csv.DictReader(args.out.open()) if r["commit"] == commit}
    rows = []
    args.out.parent.mkdir(parents=True, exist_ok=True)
    for name, views in image_sets(args.scenes):
        if name in done:
            rows.append(done[name])
            continue
        images = views()
        row = {"set": name, "commit": commit, "shares": SHARES}
        for label, shares in (("one", 1), ("shares", SHARES), ("again", SHARES)):
            t0 = time.perf_counter()
            s = score_images(images, cams, shares=shares).as_dict()
            row |= {f"{label}_{k}": s[k] for k in FIELDS} | {f"{label}_s": time.perf_counter() - t0}
        row["repeats"] = all(same(float(row[f"shares_{k}"]), float(row[f"again_{k}"])) for k in FIELDS)
        rows.append(row)
        print(f"{name}: one thread {row['one_registration_rate']:.2f}/{row['one_failure_rate']:.2f}/"
              f"{row['one_var_theta_deg2']:.3g} in {row['one_s']:.1f} s; {SHARES} shares "
              f"{row['shares_registration_rate']:.2f}/{row['shares_failure_rate']:.2f}/"
              f"{row['shares_var_theta_deg2']:.3g} in {row['shares_s']:.1f} s", flush=True)  # fmt: skip
        with args.out.open("w", newline="") as f:  # after every set: a stopped run resumes
            w = csv.DictWriter(f, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
    f = lambda r, k: float(r[k])  # noqa: E731
    summary = {
        "commit": commit,
        "sets": len(rows),
        "same_registration": sum(same(f(r, "one_registration_rate"), f(r, "shares_registration_rate")) for r in rows),
        "same_failure_rate": sum(same(f(r, "one_failure_rate"), f(r, "shares_failure_rate")) for r in rows),
        "failure_rate_within_0.02": sum(
            abs(f(r, "one_failure_rate") - f(r, "shares_failure_rate")) <= 0.02 for r in rows
        ),
        "repeats": sum(str(r["repeats"]) == "True" for r in rows),
        "median_seconds_one": sorted(f(r, "one_s") for r in rows)[len(rows) // 2],
        "median_seconds_shares": sorted(f(r, "shares_s") for r in rows)[len(rows) // 2],
    }
    write_json(summary, args.out.with_name(args.out.stem + "_summary.json"))
    print(summary)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
