#!/usr/bin/env bash
# The learned prior trained on a GPU (docs/learned_prior.md, "Trained on a GPU"): the world data
# rendered there by pyrender through EGL in many processes, then the world models at 64 px
# (uniform and front) and, as the controls on the same recipe, both at 32 px, the four at once on
# the one GPU. Run by scripts/gpu_check.sh when GPU_STAGES names `prior` (beside the
# other stages), or alone: `bash scripts/gpu_prior.sh WORK OUT`. Needs what scripts/gpu_prepare.sh
# carries (.whl/ with pyrender and PyOpenGL, .gl/ with libglvnd's EGL loader).
# PRIOR_RUNS picks the runs (default: the four; world<size>-<uniform|front>), PRIOR_STEPS, PRIOR_BATCH,
# PRIOR_VIEWS, PRIOR_WORKERS and PRIOR_DEVICE the rest (the defaults are the runs of 2026-11-28).
# WORK/prior gets the logs, the runs and a sample of the EGL-rendered data; OUT gets one
# prior_<run>.tgz per run (weights, loss.csv, loss.png, config.json, log; no checkpoint). The
# trainings stop at PRIOR_DEADLINE_S after this script's start (SIGTERM: a checkpoint at the end of
# the step), and a stopped run's weights are exported from that checkpoint (model-step<N>).
set -u
R=${1:?usage: bash scripts/gpu_prior.sh WORK OUT}
OUT=${2:?usage: bash scripts/gpu_prior.sh WORK OUT}
START=$(date +%s)
P=$R/prior
mkdir -p "$P"
STEPS=${PRIOR_STEPS:-6000}
BATCH=${PRIOR_BATCH:-128}
VIEWS=${PRIOR_VIEWS:-512}
WORKERS=${PRIOR_WORKERS:-12}
DEVICE=${PRIOR_DEVICE:-cuda}
DEADLINE=$((START + ${PRIOR_DEADLINE_S:-470}))
stamp() { echo "== $(date +%T) prior: $*" | tee -a "$R/stages.log"; }

if [ -d .gl ] && ! ldconfig -p | grep -q 'libEGL.so.1 '; then
  for f in .gl/*.deb; do dpkg -x "$f" /; done
  ldconfig
fi
vendor=/usr/local/nvidia/share/glvnd/egl_vendor.d/10_nvidia.json
[ -f "$vendor" ] && export __EGL_VENDOR_LIBRARY_FILENAMES=$vendor
export PYOPENGL_PLATFORM=${PYOPENGL_PLATFORM:-egl}

stamp "EGL probe (8 views of the duck, kept for a comparison with the CPU's OSMesa renders)"
timeout 120 python3 - "$P/egl_sample.npz" "$VIEWS" > "$P/probe.log" 2>&1 <<'PY' || stamp "EGL probe failed"
import sys, time
import numpy as np
from gdbench.priors.learned.data import render_subset
from gdbench.priors.learned.training import world_config
cfg = world_config(data={"views": int(sys.argv[2])}).data
t = time.perf_counter()
part = render_subset(cfg, "a yellow duck", 0)
print(f"EGL: {len(part)} views of the duck in {time.perf_counter() - t:.1f} s")
np.savez(sys.argv[1], images=part.images[:8].numpy(), azimuth=part.azimuth[:8].numpy())
PY
cat "$P/probe.log"
if [ ! -f "$P/egl_sample.npz" ]; then  # what the EGL loader saw
  { ldconfig -p | grep -i -E 'libEGL|libOpenGL'; ls /usr/local/nvidia/share/glvnd/egl_vendor.d /usr/share/glvnd/egl_vendor.d; } 2>&1 | tee -a "$P/probe.log"
  exit 1
fi

stamp "the world data ($VIEWS cameras per caption and variant, $WORKERS processes)"
# a file, not stdin, with a main guard: the render's worker processes are spawned and import it
cat > "$P/data.py" <<'PY'
import sys
import time

from gdbench.priors.learned.data import data_key, load_dataset
from gdbench.priors.learned.training import world_config

if __name__ == "__main__":
    cfg = world_config(data={"views": int(sys.argv[1])}).data
    t = time.perf_counter()
    data = load_dataset(cfg, progress=False, workers=int(sys.argv[2]))
    print(f"{len(data)} views, key {data_key(cfg)}, in {time.perf_counter() - t:.0f} s")
PY
timeout $((DEADLINE - $(date +%s))) python3 "$P/data.py" "$VIEWS" "$WORKERS" > "$P/data.log" 2>&1 \
  || { stamp "data failed"; tail -20 "$P/data.log"; exit 1; }
cat "$P/data.log"

RUNS=${PRIOR_RUNS:-world64-uniform world64-front world32-uniform world32-front}  # world<size>-<uniform|front>
stamp "training: $RUNS ($STEPS steps of batch $BATCH, at once)"
train() {
  local name=$1
  shift
  local left=$((DEADLINE - $(date +%s)))
  timeout -s TERM "$((left > 10 ? left : 10))" python3 -m gdbench.app.cli train-prior --catalogue world \
    --views "$VIEWS" --steps "$STEPS" --batch "$BATCH" --device "$DEVICE" --threads 2 --data-workers "$WORKERS" \
    --out "$P/$name" "$@" \
    > "$P/$name.log" 2>&1
  echo "rc $?" >> "$P/$name.log"
}
for name in $RUNS; do
  size=${name#world}
  size=${size%%-*}
  bias=0
  [[ $name == *-front ]] && bias=2
  train "$name" --size "$size" --front-bias "$bias" &
done
wait
stamp "training ended"
for name in $RUNS; do
  tail -n 2 "$P/$name.log"
  if [ ! -f "$P/$name/model.safetensors" ] && [ -f "$P/$name/checkpoint.pt" ]; then
    python3 -c "import sys; from gdbench.priors.learned.training import export_weights; print(export_weights(sys.argv[1]))" \
      "$P/$name" >> "$P/$name.log" 2>&1
  fi
  cp "$P/$name.log" "$P/$name/train.log" 2>/dev/null
  tar -czf "$OUT/prior_$name.tgz" -C "$P" --exclude=checkpoint.pt "$name"
done
stamp "done"
