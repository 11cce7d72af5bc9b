#!/usr/bin/env bash
# The fresh set's blind sheets and the raters' folders (docs/judge_fresh.md, "The labels"):
#   [DRAW_SEED=61] bash docs/results/judge/fresh/draw.sh OUT WORK   (61: the second set, docs/judge_fresh2.md)
# OUT: the sweep folder of sweep.sh (its three blocks); WORK gets sheets/ (every finished result,
# grouped by prompt and shuffled within it: --seed 58 --per-sheet 10), fresh_key.json (number ->
# run, which names block and arm: never given to a rater) and raters/p{1,2}_g{1..4} (v3's split:
# two passes of four labellers, each with a quarter of the prompts, RULE.md and PROTOCOL.md).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../../.." && pwd)
out=${1:?usage: draw.sh OUT WORK}
work=${2:?usage: draw.sh OUT WORK}
py=$root/.venv/bin/python
[ -x "$py" ] || { echo "draw.sh: $py is missing: run this script from the checkout that holds the virtual environment (make test or scripts/setup.sh makes it)"; exit 1; }
mkdir -p "$work"
"$py" -m gdbench.metrics.label_sheets --runs "$out/learned-janus" "$out/learned-uniform" "$out/empirical-janus" \
  --out "$work/sheets" --key "$work/fresh_key.json" --per-sheet 10 --seed "${DRAW_SEED:-58}"
rm -f "$work/sheets/labels_template.csv"
"$py" "$root/docs/results/v3/labelling/split.py" "$work/sheets" "$work/fresh_key.json" "$work/raters"
