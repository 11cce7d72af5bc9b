#!/usr/bin/env bash
# The judge's fresh set (docs/judge_fresh.md): v3's 31 janus prompts at seed 5 (SEED=6 for the second
# set, docs/judge_fresh2.md), 1000 steps, figures on, in three blocks, from a clone frozen at one commit
# (CLONE, made here from this checkout's HEAD unless it exists). Resumable: run it again to go on. OUT
# gets one sweep folder per block.
#   [SEED=6] bash docs/results/judge/fresh/sweep.sh CLONE OUT
set -euo pipefail
here=$(cd "$(dirname "$0")/../../../.." && pwd)
py=$here/.venv/bin/python
[ -x "$py" ] || { echo "sweep.sh: $py is missing: run this script from the checkout that holds the virtual environment (make test or scripts/setup.sh makes it)"; exit 1; }
clone=${1:?usage: sweep.sh CLONE OUT}
out=${2:?usage: sweep.sh CLONE OUT}
[ -d "$clone/.git" ] || git clone -q "$here" "$clone"
cd "$clone"
export PYTHONPATH=$PWD  # the clone's sources, not the editable install's
mapfile -t prompts < <("$py" -c "from gdbench.experiments.v3_design import prompts; print('\n'.join(prompts()))")
[ "${#prompts[@]}" = 31 ] || { echo "sweep.sh: expected v3's 31 prompts, got ${#prompts[@]}"; exit 1; }
common=(--seeds "${SEED:-5}" --steps 1000 --no-colmap --figures --workers 2)
"$py" -m gdbench.app.cli sweep --prior learned --settings janus --presets gd gd-no-sn \
  --prompts "${prompts[@]}" "${common[@]}" --out "$out/learned-janus"
"$py" -m gdbench.app.cli sweep --prior learned --settings easy --presets gd \
  --prompts "${prompts[@]}" "${common[@]}" --out "$out/learned-uniform"
"$py" -m gdbench.app.cli sweep --prior empirical --settings janus --presets gd \
  --prompts "${prompts[@]}" "${common[@]}" --out "$out/empirical-janus"
