#!/usr/bin/env bash
# The janus setting described on the 64 px one-call front-biased model (MODEL; the prior issue's
# item 5, docs/learned_prior.md): gd and gd-no-sn on v3's 31 janus prompts, seeds 0-1, 1000 steps,
# figures on, from a clone frozen at one commit (CLONE, made from this checkout's HEAD unless it
# exists). Resumable: run it again to go on. OUT gets one sweep folder, janus/.
#   bash docs/results/learned_prior/world64/janus.sh CLONE OUT MODEL
set -euo pipefail
here=$(cd "$(dirname "$0")/../../../.." && pwd)
clone=${1:?usage: janus.sh CLONE OUT MODEL}
out=${2:?usage: janus.sh CLONE OUT MODEL}
model=${3:?usage: janus.sh CLONE OUT MODEL}
model=$(cd "$(dirname "$model")" && pwd)/$(basename "$model")
[ -f "$model" ] || [ -d "$model" ] || { echo "janus.sh: no model at $model" >&2; exit 2; }
[ -d "$clone/.git" ] || git clone -q "$here" "$clone"
py=${PYTHON:-$here/.venv/bin/python}
mkdir -p "$out"
out=$(cd "$out" && pwd)
cd "$clone"
export PYTHONPATH=$PWD  # the clone's sources, not the editable install's
mapfile -t prompts < <("$py" -c "from gdbench.experiments.v3_design import prompts; print('\n'.join(prompts()))")
[ "${#prompts[@]}" = 31 ] || { echo "janus.sh: expected v3's 31 prompts, got ${#prompts[@]}"; exit 1; }
"$py" -m gdbench.app.cli sweep --prior learned --learned-model "$model" --settings janus --presets gd gd-no-sn \
  --prompts "${prompts[@]}" --seeds 0 1 --steps "${STEPS:-1000}" --no-colmap --figures --workers "${WORKERS:-2}" \
  --out "$out/janus"
