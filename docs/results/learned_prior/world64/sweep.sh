#!/usr/bin/env bash
# Text to 3D on all 38 captions at the defaults (view prompting on), seed 0: the 64 px one-call
# uniform model (MODEL) against the shipped 32 px uniform model, both from one clone frozen at one
# commit (CLONE, made from this checkout's HEAD unless it exists), and the duck at seeds 0-3 on
# MODEL (the prior issue's item 4; docs/learned_prior.md). Resumable: run it again to go on. OUT
# gets one sweep folder each: shipped/, world64/, duck/.
#   bash docs/results/learned_prior/world64/sweep.sh CLONE OUT MODEL
#   python -m gdbench.experiments.prior64 --runs OUT --to docs/results/learned_prior/world64 --model MODEL
set -euo pipefail
here=$(cd "$(dirname "$0")/../../../.." && pwd)
clone=${1:?usage: sweep.sh CLONE OUT MODEL}
out=${2:?usage: sweep.sh CLONE OUT MODEL}
model=${3:?usage: sweep.sh CLONE OUT MODEL}
model=$(cd "$(dirname "$model")" && pwd)/$(basename "$model")
[ -f "$model" ] || [ -d "$model" ] || { echo "sweep.sh: no model at $model" >&2; exit 2; }
[ -d "$clone/.git" ] || git clone -q "$here" "$clone"
py=${PYTHON:-$here/.venv/bin/python}
mkdir -p "$out"
out=$(cd "$out" && pwd)
cd "$clone"
export PYTHONPATH=$PWD  # the clone's sources, not the editable install's
mapfile -t prompts < <("$py" -c "from gdbench.assets.library import CAPTIONS; print('\n'.join(CAPTIONS))")
[ "${#prompts[@]}" = 38 ] || { echo "sweep.sh: expected the 38 captions, got ${#prompts[@]}"; exit 1; }
common=(--prior learned --presets gd --no-colmap --figures --workers "${WORKERS:-2}")
"$py" -m gdbench.app.cli sweep --learned-model uniform --prompts "${prompts[@]}" --seeds 0 "${common[@]}" \
  --out "$out/shipped"
"$py" -m gdbench.app.cli sweep --learned-model "$model" --prompts "${prompts[@]}" --seeds 0 "${common[@]}" \
  --out "$out/world64"
"$py" -m gdbench.app.cli sweep --learned-model "$model" --prompts "a yellow duck" --seeds 0 1 2 3 "${common[@]}" \
  --out "$out/duck"
