#!/usr/bin/env bash
# The 64 px world models on this CPU machine (docs/learned_prior.md, "The world models at 64 px"):
# both (uniform and front-biased) on the shipped world models' schedule (24,000 steps of batch 32,
# the same captions and held-out split), at --patch 4 (the first level at 16 px: about the work of
# the 32 px model's step), one torch thread each, at the lowest priority, from a clone frozen at one
# commit so that the weights name one version of the code.
#
#   bash scripts/train_world64.sh start CLONE [COMMIT]   clone main at COMMIT (default HEAD) into CLONE
#                                                        unless it is there, render the data (cached)
#                                                        and start (or resume) both runs in the background
#   bash scripts/train_world64.sh status CLONE           each run's step and the log's last line
#   bash scripts/train_world64.sh pause|cont CLONE       stop the runs while timings are taken, go on after
#   bash scripts/train_world64.sh distil CLONE TEACHERS [COMMIT]
#                                                        guidance in one call: clone main at COMMIT into
#                                                        CLONE (a second clone: the distillation code is
#                                                        newer than the teachers'), then distil both
#                                                        finished teachers of the clone TEACHERS at
#                                                        guidance 3 (DSTEPS, default 3000) into
#                                                        CLONE/runs/prior-world64p4-{uniform,front}-1call
#
# Resumable: `start` again after any interruption resumes both runs from their checkpoints (every
# 500 steps). Runs go to CLONE/runs/prior-world64p4-{uniform,front}; logs beside them.
# PATCH, STEPS and PYTHON override the defaults (PYTHON: this checkout's .venv, whose torch and
# packages the clone uses; the clone's own sources come first on the path).
set -euo pipefail
here=$(cd "$(dirname "$0")/.." && pwd)
usage="usage: bash scripts/train_world64.sh start CLONE [COMMIT] | distil CLONE TEACHERS [COMMIT] | status|pause|cont CLONE"
cmd=${1:?$usage}
clone=${2:?$usage}
clone_abs=$(realpath -m "$clone")
PATCH=${PATCH:-4}
STEPS=${STEPS:-24000}
PYTHON=${PYTHON:-$here/.venv/bin/python}
runs=(uniform front)
DSTEPS=${DSTEPS:-3000}
GUIDANCE=${GUIDANCE:-3}

clone_at() {  # clone main into $1 at $2 (default HEAD) unless it is there; refuse a clone at another commit
  if [ ! -d "$1/.git" ]; then
    git clone -q "$here" "$1"
    git -C "$1" checkout -q "${2:-$(git -C "$here" rev-parse HEAD)}"
  elif [ -n "${2:-}" ] && [ "$(git -C "$1" rev-parse HEAD)" != "$(git -C "$1" rev-parse "$2" 2>/dev/null)" ]; then
    echo "train_world64: $1 is at $(git -C "$1" rev-parse --short HEAD), not $2: its runs belong to that commit"
    exit 2
  fi
}

pids() {  # this clone's runs (their working folder is the clone), all or those whose name ends $1
  local p
  for p in $(pgrep -f "train-prior .*--out runs/prior-world64p${PATCH}-${1:-}" || true); do
    [ "$(readlink "/proc/$p/cwd" 2>/dev/null)" = "$clone_abs" ] && echo "$p"
  done
  true
}

data_step() {  # in the clone: the data (49,152 views at 64 px, the 32 px world models' key) in two
  # processes, cached; a file with a main guard, not stdin: the render's worker processes are spawned
  # and import it
  cat > runs/world64_data.py <<'PY'
from gdbench.priors.learned.data import data_key, load_dataset
from gdbench.priors.learned.training import world_config

if __name__ == "__main__":
    cfg = world_config(data={"views": 512}).data
    print(len(load_dataset(cfg, progress=True, workers=2)), "views, key", data_key(cfg))
PY
  nice -n 19 "$PYTHON" runs/world64_data.py > runs/world64-data.log 2>&1
}

enter_clone() {  # the clone's sources, not the editable install's; its runs' folder
  cd "$clone"
  export PYTHONPATH=$PWD
  mkdir -p runs
}

busy() {  # say so (and succeed) when this clone's runs whose name ends $1 are running; $2: what they do
  local p
  p=$(pids "$1")
  [ -n "$p" ] || return 1
  echo "train_world64: already $2 (pids $(echo $p | tr '\n' ' '))"
}

detached() {  # run the function "$@" in the background, away from this shell's terminal
  ("$@") < /dev/null > /dev/null 2>&1 &
  disown
}

train_teachers() {
  data_step
  for run in "${runs[@]}"; do
    bias=0
    [ "$run" = front ] && bias=2
    nice -n 19 "$PYTHON" -m gdbench.app.cli train-prior --catalogue world --views 512 --steps "$STEPS" \
      --front-bias "$bias" --threads 1 --size 64 --patch "$PATCH" --out "runs/prior-world64p${PATCH}-$run" \
      >> "runs/world64-$run.log" 2>&1 &
  done
  wait
}

train_students() {
  data_step  # the teachers' data (their key), rendered once here if this clone's cache lacks it
  for run in "${runs[@]}"; do
    nice -n 19 "$PYTHON" -m gdbench.app.cli train-prior \
      --teacher "$teachers/runs/prior-world64p${PATCH}-$run/model.safetensors" --teacher-guidance "$GUIDANCE" \
      --steps "$DSTEPS" --threads 1 --out "runs/prior-world64p${PATCH}-$run-1call" \
      >> "runs/world64-$run-1call.log" 2>&1 &
  done
  wait
}

case $cmd in
  start)
    clone_at "$clone" "${3:-}"
    busy "" running && exit 0
    enter_clone
    echo "train_world64: clone at $(git rev-parse --short HEAD); data, then both runs (log: runs/world64-*.log)"
    detached train_teachers
    ;;
  distil)
    teachers=${3:?$usage}
    teachers=$(cd "$teachers" && pwd)
    for run in "${runs[@]}"; do
      t=$teachers/runs/prior-world64p${PATCH}-$run/model.safetensors
      [ -f "$t" ] || { echo "train_world64: no finished teacher at $t (its training has not ended)" >&2; exit 2; }
    done
    clone_at "$clone" "${4:-}"
    busy '[a-z]*-1call' distilling && exit 0
    enter_clone
    echo "train_world64: clone at $(git rev-parse --short HEAD); distilling both teachers of $teachers at guidance $GUIDANCE"
    detached train_students
    ;;
  status)
    for run in "${runs[@]}" "${runs[@]/%/-1call}"; do
      [ -d "$clone/runs/prior-world64p${PATCH}-$run" ] || continue
      f=$clone/runs/prior-world64p${PATCH}-$run/loss.csv
      echo "$run: $(tail -n 1 "$f" 2>/dev/null || echo 'no loss yet') | $(tail -c 300 "$clone/runs/world64-$run.log" 2>/dev/null | tr '\r' '\n' | tail -n 1)"
    done
    [ -n "$(pids)" ] && echo "running: $(pids | tr '\n' ' ')" || echo "not running"
    ;;
  pause|cont)
    p=$(pids)
    [ -n "$p" ] || { echo "train_world64: no run to $cmd"; exit 0; }
    kill "-$([ "$cmd" = pause ] && echo STOP || echo CONT)" $p && echo "$cmd: $(echo $p | tr '\n' ' ')"
    ;;
  *) echo "train_world64: unknown command $cmd; $usage" >&2; exit 2 ;;
esac
