#!/usr/bin/env bash
# The GPU checks behind docs/renderer.md "On a GPU", in one call on a bare NVIDIA machine that has
# python3 with a CUDA torch but no network (how they were run for the docs):
#   - wheels of what it lacks in .whl/ (tyro, docstring-parser, typeguard, plyfile, gsplat==1.5.3,
#     diffusers, importlib_metadata: `pip download --no-deps --only-binary=:all: --python-version 3.12
#     --platform manylinux_2_17_x86_64 -d .whl NAME`),
#   - the image banks a run reads in .devcache/banks/ (built here by pyrender, which that machine
#     lacks; xz-compressed to travel),
# then `bash scripts/gpu_check.sh OUT`. Stages run in order of need, each under its own time limit,
# and their results are packed into OUT/gpu_results.tgz after every stage.
set -u
OUT=${1:-gpu_results}
mkdir -p "$OUT/r"
R=$OUT/r
export PYTHONUNBUFFERED=1 GDBENCH_CACHE=$PWD/.devcache TORCH_CUDA_ARCH_LIST=${TORCH_CUDA_ARCH_LIST:-9.0} MAX_JOBS=16
stamp() { echo "== $(date +%T) $*" | tee -a "$R/stages.log"; }
pack() { tar -czf "$OUT/gpu_results.tgz" -C "$R" . 2>/dev/null; }

stamp setup
if [ -d .whl ]; then
  python3 -m pip install -q --no-index --no-deps --no-compile --no-cache-dir --upgrade --target /tmp/site .whl/*.whl || exit 1
  export PYTHONPATH=/tmp/site:$PWD
else
  export PYTHONPATH=$PWD
fi
python3 -c "import glob, lzma, shutil; [shutil.copyfileobj(lzma.open(f), open(f[:-3], 'wb')) for f in glob.glob('.devcache/banks/*.xz')]"
{ nvidia-smi; nproc; python3 -c "import torch; print(torch.__version__, torch.version.cuda, torch.cuda.get_device_name(0))"; git rev-parse HEAD; git status --short; } > "$R/machine.txt" 2>&1
# gsplat compiles its CUDA kernels on first use: in the background while the rest runs
(timeout 300 python3 -c "import time; t = time.time(); from gsplat.cuda._backend import _C; print('gsplat kernels:', _C is not None, round(time.time() - t, 1), 's')" > "$R/gsplat_build.log" 2>&1; echo "rc $?" >> "$R/gsplat_build.log") &
GS=$!

stamp "C++ extension"
timeout 120 python3 -c "import time; t = time.time(); from renderers.splat._ext import load_extension; print('extension:', load_extension() is not None, round(time.time() - t, 1), 's')" > "$R/ext.log" 2>&1

stamp "pytest -m cuda"
timeout 170 python3 -m pytest -q -m cuda tests/test_device.py -p no:cacheprovider -rs > "$R/pytest_cuda.log" 2>&1
tail -3 "$R/pytest_cuda.log"
pack

stamp "wait for gsplat (its build would load the CPU timings)"
wait $GS
cat "$R/gsplat_build.log"
stamp "generate on cuda and on cpu"
for dev in cuda cpu; do
  t0=$(date +%s.%N)
  timeout 110 python3 -c 'import sys; from gdbench.cli import entrypoint; sys.argv[0] = "gdbench"; entrypoint()' \
    generate "a yellow duck" --steps 1000 --device $dev --out "runs/gpu_$dev" --no-progress > "$R/generate_$dev.log" 2>&1
  echo "rc $? wall $(python3 -c "print(round($(date +%s.%N) - $t0, 2))") s" >> "$R/generate_$dev.log"
  cp "runs/gpu_$dev/run.json" "$R/run_$dev.json" 2>/dev/null
  cp "runs/gpu_$dev/turntable_sheet.png" "$R/turntable_sheet_$dev.png" 2>/dev/null
done
pack

stamp "bm_cuda agreement, speed, trainer"
timeout 200 python3 -m gdbench.bench.bm_cuda --parts agreement,speed,trainer --out "$R/bm" > "$R/bm_cuda.log" 2>&1
pack
stamp "bm_cuda threads"
timeout 70 python3 -m gdbench.bench.bm_cuda --parts threads --out "$R/bm_threads" > "$R/bm_threads.log" 2>&1
stamp done
pack
