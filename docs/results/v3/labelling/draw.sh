#!/bin/bash
# draw.sh OUT NAME SEED...: blind sheets of the finished Janus cells of these seeds under the sweep
# folder OUT (the registered command: --seed 57 --per-sheet 10), into NAME/sheets, the key NAME_key.json.
set -e
out=$1; name=$2; shift 2
rm -rf "$name"; mkdir -p "$name/runs"
for s in "$@"; do
  for c in "$out"/blocks/janus/cells/*/*/*/*/seed"$s"/cell.json; do
    d=$(dirname "$c"); rel=${d#"$out"/blocks/janus/}
    [ -f "$d/turntable.gif" ] || continue
    mkdir -p "$name/runs/$rel"; cp "$d/run.json" "$d/turntable.gif" "$name/runs/$rel/"
  done
done
python -m gdbench.metrics.label_sheets --runs "$name/runs" --out "$name/sheets" --key "${name}_key.json" \
  --per-sheet 10 --seed 57
