#!/usr/bin/env bash
# The cost of a 1000-step janus cell (gd, "a yellow duck", seed 0, no COLMAP) on the shipped 32 px
# front model against MODEL (the prior issue's item 6), each in a fresh `gdbench sweep` process,
# alternating over ROUNDS (default 2) so both see the same phase of the machine; the cell's own
# time (cells.csv: cell_s, train_time_s) and the machine's float32 matrix product before and after.
#   bash docs/results/learned_prior/world64/janus_cell.sh MODEL OUT.csv
set -euo pipefail
here=$(cd "$(dirname "$0")/../../../.." && pwd)
model=${1:?usage: janus_cell.sh MODEL OUT.csv}
out=${2:?usage: janus_cell.sh MODEL OUT.csv}
py=${PYTHON:-$here/.venv/bin/python}
work=$(mktemp -d)
trap 'rm -rf "$work"' EXIT
gflops() { "$py" -c "from gdbench.bench.roofline import peak_gflops; print(round(peak_gflops()))"; }
before=$(gflops)
for r in $(seq 1 "${ROUNDS:-2}"); do
  for arm in shipped world64; do
    extra=(); [ "$arm" = world64 ] && extra=(--learned-model "$model")
    "$py" -m gdbench.app.cli sweep --prior learned "${extra[@]}" --settings janus --presets gd --prompts "a yellow duck" \
      --seeds 0 --steps 1000 --no-colmap --workers 1 --out "$work/$arm-$r" > /dev/null 2>&1
  done
done
after=$(gflops)
"$py" - "$work" "$out" "$before" "$after" "${ROUNDS:-2}" <<'PY'
import csv, statistics, sys
from pathlib import Path
from gdbench.core.io import write_csv
from gdbench.core.provenance import code_commit
work, out, before, after, rounds = Path(sys.argv[1]), Path(sys.argv[2]), *sys.argv[3:6]
rows = []
for r in range(1, int(rounds) + 1):
    for arm in ("shipped", "world64"):
        cell = next(csv.DictReader(open(work / f"{arm}-{r}" / "cells.csv")))
        rows.append({"round": r, "arm": arm, "cell_s": float(cell["cell_s"]), "train_time_s": float(cell["train_time_s"]),
                     "gflops_before": before, "gflops_after": after, "commit": code_commit()})
write_csv(rows, out)
for key in ("cell_s", "train_time_s"):
    m = {a: statistics.median(x[key] for x in rows if x["arm"] == a) for a in ("shipped", "world64")}
    print(f"{key}: shipped {m['shipped']:.1f} s, 64 px {m['world64']:.1f} s, ratio {m['world64'] / m['shipped']:.2f}")
print(f"machine: float32 matrix product {before} -> {after} GFLOP/s")
PY
