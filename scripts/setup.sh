#!/usr/bin/env bash
# One-stop set-up, idempotent and quick when nothing is missing:
#   1. Debian packages the reference stack needs (installed when run as root, else listed); with
#      GDBENCH_BROWSER=1 (make test-slow, test-all) also Chromium, the headless browser of the
#      viewer's slow test (the same way; a failure only warns: that test then skips);
#   2. a virtual environment in .venv;
#   3. torch==2.13.0 first (the CPU build on these machines), then gdbench with test extras;
#   4. the C++ CPU compositor, compiled once into torch's extension cache, and the package's
#      bytecode (compileall: an editable install's sources are not compiled by pip);
#   5. the six assets' image banks, built once in the background at low priority (gdbench cache
#      build; a first run of a prompt then starts at once), unless GDBENCH_PREBUILD=0 (make test).
set -euo pipefail
cd "$(dirname "$0")/.."

PYTHON=${PYTHON:-python3}
TORCH_SPEC=${TORCH_SPEC:-torch==2.13.0}
# libllvm19: Dr.Jit's LLVM backend (Mitsuba); libosmesa6: pyrender offscreen (on an NVIDIA machine
# PYOPENGL_PLATFORM=egl renders through the driver instead, with libglvnd's libegl1 and libopengl0;
# where pyglet cannot load X11 there, pyrender is imported with its viewer stubbed out);
# libusb-1.0-0, libvulkan1, mesa-vulkan-drivers: Open3D (open3d-cpu) import and offscreen rendering.
DEBS="libllvm19 libosmesa6 libusb-1.0-0 libvulkan1 mesa-vulkan-drivers"

missing=()
if command -v dpkg >/dev/null 2>&1; then
  for p in $DEBS; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
fi
if [ ${#missing[@]} -gt 0 ]; then
  if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
    echo "setup: installing Debian packages: ${missing[*]}"
    apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends "${missing[@]}" >/dev/null
  else
    echo "setup: warning: missing Debian packages (the reference renderers need them): ${missing[*]}"
    echo "       install them with: sudo apt-get install ${missing[*]}"
  fi
fi

# The browser of tests/test_viewer.py's slow test (gdbench view itself needs none: any browser
# opens it). A failure here only warns: the slow test then skips with its reason.
BROWSER_DEBS="chromium chromium-driver"
if [ -n "${GDBENCH_BROWSER:-}" ] && command -v dpkg >/dev/null 2>&1; then
  missing=()
  for p in $BROWSER_DEBS; do dpkg -s "$p" >/dev/null 2>&1 || missing+=("$p"); done
  if [ ${#missing[@]} -gt 0 ]; then
    if [ "$(id -u)" = 0 ] && command -v apt-get >/dev/null 2>&1; then
      echo "setup: installing Debian packages (the viewer's slow test): ${missing[*]}"
      { apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq --no-install-recommends \
          "${missing[@]}" >/dev/null; } || echo "setup: warning: could not install ${missing[*]}; the browser test will skip"
    else
      echo "setup: note: missing Debian packages (the viewer's slow browser test skips without them): ${missing[*]}"
      echo "       install them with: sudo apt-get install ${missing[*]}"
    fi
  fi
fi

if [ ! -x .venv/bin/python ]; then
  echo "setup: creating .venv"
  "$PYTHON" -m venv .venv
fi
PIP=(.venv/bin/python -m pip --disable-pip-version-check -q)
# pip, minus the notes about this machine's local package mirrors; pip's own status survives
quiet_pip() {
  "${PIP[@]}" "$@" 2>&1 | { grep -v "is ignored: it is neither" || true; }
  return "${PIPESTATUS[0]}"
}

if ! .venv/bin/python -c "import torch" >/dev/null 2>&1; then
  echo "setup: installing $TORCH_SPEC"
  quiet_pip install "$TORCH_SPEC"
fi

stamp=.venv/.gdbench-installed
want=$(cat pyproject.toml constraints.txt scripts/setup.sh | sha256sum | cut -c1-16)
if [ "$(cat "$stamp" 2>/dev/null || true)" != "$want" ]; then
  echo "setup: installing gdbench and its test extras"
  quiet_pip install -c constraints.txt -e ".[test]"
  # pyrender pins PyOpenGL 3.1.0, which fails under OSMesa: install it without its dependencies
  # (pyproject lists the ones it needs, with PyOpenGL 3.1.10)
  quiet_pip install --no-deps pyrender==0.1.45
  # open_clip only for the BPE vocabulary the CLIP tokenizer is built from; its dependencies
  # would pull torchvision (and with it possibly another torch build)
  quiet_pip install --no-deps open_clip_torch==3.3.0
  .venv/bin/python -c "import gdbench, renderers.splat" || { echo "setup: gdbench did not install"; exit 1; }
  echo "$want" > "$stamp"
fi

# Build (or find in the cache) the C++ compositor; the pure-torch path is the fallback.
.venv/bin/python -m renderers.splat._ext >/dev/null 2>&1 \
  || echo "setup: warning: the C++ compositor did not build; the slower pure-torch path will be used"

# The package's bytecode. pip compiles what it installs, but not an editable install's sources, and
# where PYTHONDONTWRITEBYTECODE is set (as on the CI machine) Python never writes it either: every
# gdbench process then compiled its modules from source, about 0.1 s of each command and sweep
# cell. compileall writes it regardless and skips what is up to date (0.06 s); a source edited
# later is compiled in memory again until the next set-up (Python checks each file's mtime).
.venv/bin/python -m compileall -q gdbench renderers \
  || echo "setup: warning: could not compile gdbench's bytecode; its commands start about 0.1 s slower"

# The assets' image banks take 16-45 s each on the first run of a prompt: build them once, in the
# background at the lowest priority (gdbench cache build), unless GDBENCH_PREBUILD=0 (make test
# sets it: the suite builds what it needs) or they are built or being built.
cache_root=${GDBENCH_CACHE:-$HOME/.cache/gdbench}
asset_version=$(sed -n 's/^ASSET_VERSION = \([0-9]*\).*/\1/p' gdbench/assets/bank.py)
if [ "${GDBENCH_PREBUILD:-1}" != 0 ] \
  && ! grep -q "\"asset_version\": ${asset_version}[,}]" "$cache_root/banks/prebuilt.json" 2>/dev/null \
  && ! { command -v pgrep >/dev/null && pgrep -f "gdbench.app.cli cache build" >/dev/null; }; then
  mkdir -p "$cache_root"
  echo "setup: building the assets' image banks in the background (low priority: about 2 minutes on a quiet machine, longer under load; log: $cache_root/prebuild.log)"
  nohup nice -n 19 .venv/bin/python -m gdbench.app.cli cache build > "$cache_root/prebuild.log" 2>&1 < /dev/null &
fi
