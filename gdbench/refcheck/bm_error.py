"""Error against run time over all fixtures, in one CSV: the compare harness's rows
(``gdbench compare --scene all``) with a ``pareto`` column marking, per scene and quantity,
the runs no other run beats in both time and max error against the same reference. Renderers
that do not apply to a scene are rows too, with their reason in ``status``.

    python -m gdbench.refcheck.bm_error --out bench_results/error_vs_runtime.csv

Also writes ``<stem>_summary.json`` (the Pareto front per scene) and keeps the harness's error
maps and per-scene plots under ``<stem>/``.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

from gdbench.bench.common import environment, write_csv, write_json


def pareto_flags(rows: list[dict]) -> list[bool]:
    """True where no other row of the same (scene, quantity, against) is at least as fast and
    at least as accurate (max_abs), and strictly better in one of the two."""
    flags = []
    for r in rows:
        key = (r["scene"], r["quantity"], r["against"])
        t, e = float(r["time_s"]), float(r["max_abs"])
        dominated = any(
            (o["scene"], o["quantity"], o["against"]) == key
            and float(o["time_s"]) <= t
            and float(o["max_abs"]) <= e
            and (float(o["time_s"]) < t or float(o["max_abs"]) < e)
            for o in rows
        )
        flags.append(not dominated and math.isfinite(e))
    return flags


def run(
    out: Path, scenes: str | list[str] = "all", backends: list[str] | None = None, verbose: bool = True
) -> list[dict]:
    from gdbench.refcheck.compare import run as compare

    results = compare(scenes, backends=backends, out=out.with_suffix(""), verbose=verbose)
    rows = [r | {"status": "ok"} for res in results.values() for r in res.rows if r["renderer"] != "reference"]
    for r, flag in zip(rows, pareto_flags(rows)):
        r["pareto"] = flag
    refs = [
        r | {"status": "ok", "pareto": True}
        for res in results.values()
        for r in res.rows
        if r["renderer"] == "reference"
    ]
    skipped = [
        {"scene": s["scene"], "renderer": s["renderer"], "status": f"skipped: {s['reason']}"}
        for res in results.values()
        for s in res.skipped
    ]
    all_rows = refs + rows + skipped
    write_csv(all_rows, out)
    front = {}
    for r in rows:
        if r["pareto"]:
            front.setdefault(r["scene"], []).append(
                {k: r[k] for k in ("renderer", "settings", "against", "quantity", "time_s", "max_abs")}
            )
    write_json({"environment": environment(), "pareto": front}, out.with_name(out.stem + "_summary.json"))
    return all_rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/error_vs_runtime.csv"))
    ap.add_argument("--scene", default="all", help="a fixture name or 'all'")
    args = ap.parse_args(argv)
    rows = run(args.out, args.scene)
    print(f"wrote {args.out} ({len(rows)} rows) and {args.out.stem}_summary.json")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
