"""Error against run time over all fixtures, in one CSV: the compare harness's rows
(``gdbench compare --scene all``) with a ``pareto`` column marking, per scene and quantity,
the runs no other run beats in both time and max error against the same reference. Renderers
that do not apply to a scene are rows too, with their reason in ``status``.

    python -m gdbench.refcheck.bm_error --out bench_results/error_vs_runtime.csv

``--renderer pkg.mod:fn`` adds a renderer of your own (docs/references.md); every renderer of the
protocol's shape gets PASS, FAIL or SKIP per scene against the scene's tolerance for its class
(``<stem>_verdicts.csv``), and the command exits 1 when a case fails.

Also writes ``<stem>_summary.json`` (the Pareto front per scene, the verdicts) and keeps the harness's error
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
    out: Path,
    scenes: str | list[str] = "all",
    backends: list[str] | None = None,
    verbose: bool = True,
    renderers: list[str] | None = None,
) -> list[dict]:
    """The compare harness over ``scenes`` for the built-in ``backends`` (default: all, or none where
    ``renderers`` of the user's are given); writes the CSV (with each renderer's conformance verdict
    per scene: ``<stem>_verdicts.csv``) and the summary with the Pareto front and the verdicts."""
    from gdbench.refcheck.compare import run as compare
    from gdbench.refcheck.conformance import summary

    results = compare(scenes, backends=backends, out=out.with_suffix(""), verbose=verbose, renderers=renderers)
    verdicts = [v for res in results.values() for v in res.verdicts]
    write_csv(verdicts, out.with_name(f"{out.stem}_verdicts.csv"))
    rows = [r | {"status": "ok"} for res in results.values() for r in res.rows if r["renderer"] != "reference"]
    timed = [r for r in rows if r.get("time_s") is not None]  # a renderer that raised has no time
    for r in rows:
        if r.get("time_s") is None:
            r |= {"status": f"error: {r.get('reason', '')}", "pareto": False}
    for r, flag in zip(timed, pareto_flags(timed)):
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
    for r in timed:
        if r["pareto"]:
            front.setdefault(r["scene"], []).append(
                {k: r[k] for k in ("renderer", "settings", "against", "quantity", "time_s", "max_abs")}
            )
    write_json(
        {"environment": environment(), "pareto": front, "verdicts": summary(verdicts)},
        out.with_name(out.stem + "_summary.json"),
    )
    return all_rows


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("bench_results/error_vs_runtime.csv"))
    ap.add_argument("--scene", default="all", help="a fixture name or 'all'")
    ap.add_argument(
        "--renderers", nargs="+", default=None, help="built-in backends (default: all, or none with --renderer)"
    )
    ap.add_argument("--renderer", nargs="+", default=[], help="renderers of your own, module:function")
    args = ap.parse_args(argv)
    rows = run(args.out, args.scene, args.renderers, renderers=args.renderer)
    print(f"wrote {args.out} ({len(rows)} rows), {args.out.stem}_verdicts.csv and {args.out.stem}_summary.json")
    from gdbench.core.io import read_json

    failed = [(r, s) for r, s in read_json(args.out.with_name(args.out.stem + "_summary.json"))["verdicts"].items()
              if s["FAIL"]]  # fmt: skip
    for renderer, s in failed:
        for f in s["failed"]:
            print(f"FAIL {f['case']}/{renderer}: {f['reason']}")
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
