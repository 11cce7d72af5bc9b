"""The decisive experiment v3 (docs/decisive_v3.md): the Janus claims across prompts,
pre-registered, with the mechanism isolated.

    python -m gdbench.experiments.v3 prompts
    python -m gdbench.experiments.v3 pilot --out runs/v3-pilot [--workers 2]
    python -m gdbench.experiments.v3 design --out runs/v3-pilot --results docs/results/v3/pilot
    python -m gdbench.experiments.v3 sweep --out runs/v3 [--workers 2] [--executor ray]
    python -m gdbench.experiments.v3 report --out runs/v3 --results docs/results/v3 --figures docs/figures

``prompts`` lists the prompts the rule gives (every caption the learned prior was trained on that
has a front). ``pilot`` runs every candidate block on a quarter of them at two seeds kept out of
the sweep. ``design`` applies the rules fixed before the pilot ran (``DESIGN_RULES``) to its
cells: which blocks the sweep runs, and the seeds per prompt from each main claim's between- and
within-prompt spread (``across.power``). ``sweep`` runs the registered design (``REGISTERED``,
set in the commit that adds the pre-registration) and refuses to run before it exists. ``report``
reads the claims with the prompt as the unit first (exact sign-flip test, Holm over the family,
t intervals), the pooled pairs second, and draws a forest plot per main claim. Resumable like
every sweep: finished cells are skipped, a cell cut short resumes from its checkpoint.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from gdbench.experiments.outcome import attach_labels
from gdbench.experiments.runner import collect, run_blocks
from gdbench.experiments.v3_design import (
    PILOT_SEEDS,
    REGISTERED,
    pilot_blocks,
    pilot_prompts,
    prompts,
    sweep_blocks,
)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawTextHelpFormatter)
    p.add_argument("stage", choices=["prompts", "pilot", "design", "sweep", "report"])
    p.add_argument("--out", type=Path, help="folder of the blocks' cells (pilot, design, sweep, report)")
    p.add_argument("--results", type=Path, help="design, report: tables and figures go here")
    p.add_argument("--executor", choices=["local", "ray"], default="local")
    p.add_argument("--address", default="", help="Ray cluster address (empty: a local instance)")
    p.add_argument("--workers", type=int, default=2, help="cells at once (default 2: one thread each here)")
    p.add_argument("--rounds", type=int, default=0, help="sweep: seeds in this many rounds (default: one per seed)")
    p.add_argument(
        "--labels",
        nargs="*",
        default=[],
        type=Path,
        help="design, report: raters' labels by run id (gdbench.metrics.label_sheets --unblind)",
    )
    p.add_argument(
        "--figures",
        type=Path,
        help="report: also copy the primary claims' forest plots and the turntables here, as v3_*.png/webp",
    )
    p.add_argument("--no-progress", dest="progress", action="store_false", help="no line per cell")
    a = p.parse_args(argv)
    if a.workers < 1 or a.rounds < 0:
        p.error(f"--workers, --rounds: expected an int >= 1 and one >= 0, got {a.workers} and {a.rounds}")
    if a.stage == "prompts":
        ps, pilot = prompts(), set(pilot_prompts())
        for i, c in enumerate(ps):
            print(f"{i:2d}  {c}{'  (pilot)' * (c in pilot)}")
        print(f"{len(ps)} prompts, {len(pilot)} in the pilot")
        return 0
    if a.out is None:
        p.error(f"{a.stage}: --out is required")
    if a.stage in ("design", "report") and a.results is None:
        p.error(f"{a.stage}: --results is required")
    if a.stage == "pilot":
        run_blocks(pilot_blocks(), PILOT_SEEDS, a.out, a, 1)
    elif a.stage == "design":
        from gdbench.experiments.v3_report import design

        design(attach_labels(collect(a.out), a.labels), a.results)
    elif a.stage == "sweep":
        if REGISTERED is None:
            raise SystemExit(
                "sweep: no design is registered yet (REGISTERED in gdbench/experiments/v3_design.py): run the "
                "pilot and the design stage, then commit the pre-registration (docs/decisive_v3.md)"
            )
        seeds = list(range(REGISTERED["seeds"]))
        run_blocks(sweep_blocks(REGISTERED), seeds, a.out, a, a.rounds or len(seeds))
    else:
        from gdbench.experiments.v3_report import report

        report(attach_labels(collect(a.out), a.labels), a.out, a.results, a.labels, figures=a.figures)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
