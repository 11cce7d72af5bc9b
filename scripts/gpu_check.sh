#!/usr/bin/env bash
# The GPU checks behind docs/renderer.md "On a GPU", in one call on a bare NVIDIA machine that has
# python3 with a CUDA torch but no network (how they were run for the docs). Prepare on a CPU
# machine with the project set up: scripts/gpu_prepare.sh writes the wheels that machine lacks
# (.whl/) and the cache a run reads (.devcache/: the duck's banks xz-compressed, the tiny SD
# tokenizer's vocabulary). Carry both, and .devbuild/ if an earlier call's OUT gave its builds
# (gsplat_build.tar.xz, ext_build.tar.xz: the compiled kernels), then run
# `bash scripts/gpu_check.sh OUT [SEEDS]`. The builds run first, then the tests and the paired
# runs side by side, then the benchmark alone (its timings undisturbed); results are packed into
# OUT/gpu_results.tgz after every stage, the paired runs' scenes into OUT/paired_scenes.tgz.
# GPU_STAGES picks the stages (default builds,tests,paired,bm); `prior` runs scripts/gpu_prior.sh
# (the learned prior trained there, carry .gl/ too) from the start, beside the others, and the
# benchmark waits for it. GPU_PACK_BUILDS=0 leaves the builds out of OUT (no rerun planned).
set -u
OUT=${1:-gpu_results}
SEEDS=${2:-8}
R=${GPU_CHECK_WORK:-/tmp/gpu_check}  # every log and CSV; OUT gets gpu_results.tgz and the builds only
mkdir -p "$OUT" "$R"
OUT=$(cd "$OUT" && pwd)
export PYTHONUNBUFFERED=1 GDBENCH_CACHE=$PWD/.devcache TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=16
export TORCH_EXTENSIONS_DIR=/tmp/torch_extensions
STAGES=",${GPU_STAGES:-builds,tests,paired,bm},"
has() { [[ $STAGES == *",$1,"* ]]; }
for st in ${GPU_STAGES//,/ }; do
  case $st in builds | tests | paired | bm | prior) ;; *)
    echo "GPU_STAGES: unknown stage '$st' (expected a comma-separated list of builds, tests, paired, bm, prior)"
    exit 2
    ;;
  esac
done
stamp() { echo "== $(date +%T) $*" | tee -a "$R/stages.log"; }
pack() { tar -czf "$OUT/gpu_results.tgz" -C "$R" --exclude='*.safetensors' --exclude=checkpoint.pt --exclude='*.ply' . 2>/dev/null; }

stamp setup
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
python3 -c "import glob, lzma, shutil; [shutil.copyfileobj(lzma.open(f), open(f[:-3], 'wb')) for f in glob.glob('.devcache/**/*.xz', recursive=True)]"
mkdir -p "$TORCH_EXTENSIONS_DIR" .devcache
[ -f .devbuild/gsplat_build.tar.xz ] && tar -xJf .devbuild/gsplat_build.tar.xz -C "$TORCH_EXTENSIONS_DIR"
[ -f .devbuild/ext_build.tar.xz ] && tar -xJf .devbuild/ext_build.tar.xz -C .devcache
{ nvidia-smi; nproc; python3 -c "import torch; print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"; git rev-parse HEAD; git status --short; } > "$R/machine.txt" 2>&1
PRIOR=
if has prior; then
  bash scripts/gpu_prior.sh "$R" "$OUT" > "$R/prior.log" 2>&1 &
  PRIOR=$!
fi

if has builds; then
stamp "builds: gsplat's CUDA kernels and the C++ extension, side by side"
(timeout 240 python3 -c "import time; t = time.time(); from gsplat.cuda._backend import _C; print('gsplat kernels:', _C is not None, round(time.time() - t, 1), 's')" > "$R/gsplat_build.log" 2>&1; echo "rc $?" >> "$R/gsplat_build.log") &
BUILD=$!
timeout 240 python3 -c "import time; t = time.time(); from renderers.splat._ext import load_extension; print('extension:', load_extension() is not None, round(time.time() - t, 1), 's')" > "$R/ext.log" 2>&1
wait "$BUILD"
cat "$R/gsplat_build.log" "$R/ext.log"
if [ "${GPU_PACK_BUILDS:-1}" != 0 ]; then
  tar -cJf "$OUT/gsplat_build.tar.xz" -C "$TORCH_EXTENSIONS_DIR" --exclude='*.o' --exclude='.ninja*' . 2>/dev/null
  tar -cJf "$OUT/ext_build.tar.xz" -C .devcache --exclude='*.o' --exclude='.ninja*' ext 2>/dev/null
fi
pack
fi

JOBS=()
if has tests; then
  stamp "tests (-m cuda; the renderer selection with --device cuda)"
  GDBENCH_TEST_THREADS=3 timeout 300 python3 -m pytest -q -m cuda tests/test_device.py tests/test_gsplat_backend.py \
    -p no:cacheprovider -rs --timeout 200 > "$R/pytest_cuda.log" 2>&1 &
  JOBS+=($!)
  GDBENCH_TEST_THREADS=3 timeout 300 python3 -m pytest -q --device cuda -m "not slow" tests/test_rasterize.py \
    "tests/test_compare.py::test_every_backend_puts_a_gaussian_where_the_camera_projects_it" \
    -p no:cacheprovider -rs --timeout 200 > "$R/pytest_device_cuda.log" 2>&1 &
  JOBS+=($!)
fi
if has paired; then
  stamp "$SEEDS paired runs (beside the tests)"
  for s in $(seq 0 $((SEEDS - 1))); do
    { OMP_NUM_THREADS=1 timeout 300 python3 -m gdbench.app.cli generate "a yellow duck" --seed "$s" --device cuda \
        --out "runs/paired_$s" --no-progress > "$R/paired_$s.log" 2>&1; echo "rc $?" >> "$R/paired_$s.log"; } &
    JOBS+=($!)
  done
fi
[ ${#JOBS[@]} -gt 0 ] && wait "${JOBS[@]}"
has tests && tail -n 3 "$R/pytest_cuda.log" "$R/pytest_device_cuda.log"
if has paired; then
  for s in $(seq 0 $((SEEDS - 1))); do
    cp "runs/paired_$s/scores.json" "$R/paired_${s}_scores.json" 2>/dev/null
    cp "runs/paired_$s/run.json" "$R/paired_${s}_run.json" 2>/dev/null
    cp "runs/paired_$s/scene.ply" "$R/paired_${s}_scene.ply" 2>/dev/null  # to re-score on the CPU
  done
  cp runs/paired_0/turntable_sheet.png "$R/paired_0_turntable_sheet.png" 2>/dev/null
  scenes=()
  for s in $(seq 0 $((SEEDS - 1))); do [ -f "$R/paired_${s}_scene.ply" ] && scenes+=("paired_${s}_scene.ply"); done
  [ ${#scenes[@]} -gt 0 ] && tar -czf "$OUT/paired_scenes.tgz" -C "$R" "${scenes[@]}"
fi
pack

if [ -n "$PRIOR" ]; then
  stamp "waiting for the prior stage"
  wait "$PRIOR"
  pack
fi

if has bm; then
  stamp "bm_cuda ${BM_PARTS-agreement,speed,trainer} (alone)"
  timeout 330 python3 -m gdbench.refcheck.bm_cuda --parts "${BM_PARTS-agreement,speed,trainer}" --out "$R/bm" > "$R/bm_cuda.log" 2>&1
  tail -5 "$R/bm_cuda.log"
fi
stamp done
pack
cat "$R/stages.log"
