#!/usr/bin/env bash
# The janus setting on the 64 px front model (item 5): blind sheets and the raters' folders, as the
# judge's fresh set drew its own (docs/learned_prior.md, "The janus setting on the 64 px model"):
#   bash docs/results/learned_prior/world64/draw_janus.sh OUT WORK
# OUT: the OUT of janus.sh (its janus/ sweep); WORK gets sheets/ (every finished result, grouped by
# prompt and shuffled within it: --seed 60 --per-sheet 10), key.json (number -> run, which names the
# arm: never given to a rater) and raters/p{1,2}_g{1..4} (v3's split: two passes of four labellers,
# each with a quarter of the prompts, RULE.md and PROTOCOL.md).
set -euo pipefail
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../../../.." && pwd)
out=${1:?usage: draw_janus.sh OUT WORK}
work=${2:?usage: draw_janus.sh OUT WORK}
py=$root/.venv/bin/python
mkdir -p "$work"
"$py" -m gdbench.metrics.label_sheets --runs "$out/janus" --out "$work/sheets" --key "$work/key.json" \
  --per-sheet 10 --seed 60
rm -f "$work/sheets/labels_template.csv"
"$py" "$root/docs/results/v3/labelling/split.py" "$work/sheets" "$work/key.json" "$work/raters"
