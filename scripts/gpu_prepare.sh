#!/usr/bin/env bash
# Prepares a GPU session of scripts/gpu_check.sh on a CPU machine with the project set up
# (make setup): what the device machine (python3 with a CUDA torch, no network) lacks.
#   .whl/       wheels of the pure-Python packages gdbench imports there, gsplat's source wheel, and
#               pyrender with its OpenGL bindings (the learned prior's data, rendered there through EGL)
#   .gl/        Debian's libglvnd packages (libEGL, libOpenGL): the loader that finds the NVIDIA
#               driver's EGL; the prior stage unpacks them there
#   .devcache/  a gdbench cache holding the duck's image banks (xz-compressed: the script unpacks
#               them there) and the tiny SD tokenizer's vocabulary, made by short runs here
# Both are git-ignored (.git/info/exclude); name them in the device call's carry list, with
# .devbuild/ (gsplat_build.tar.xz and ext_build.tar.xz from an earlier call's OUT) if there is one.
set -euo pipefail
cd "$(dirname "$0")/.."
for p in /.whl/ /.devcache/ /.devbuild/ /.gl/; do grep -qxF "$p" .git/info/exclude 2>/dev/null || echo "$p" >> .git/info/exclude; done
python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
  --platform manylinux_2_28_x86_64 --platform manylinux_2_17_x86_64 --platform manylinux2014_x86_64 -d .whl \
  tyro==1.0.17 docstring-parser typeguard plyfile==1.1.5 trimesh==5.2.0 gsplat==1.5.3 diffusers==0.42.1 importlib_metadata \
  pyrender==0.1.45 PyOpenGL==3.1.10 pyglet==2.1.19 freetype-py==2.5.1
mkdir -p .gl /tmp/amd64/partial
o=(-oAPT::Architecture=amd64 -oAPT::Architectures=amd64 -oDir::State::Lists=/tmp/amd64)
if ! { apt-get "${o[@]}" update -qq >/dev/null && (cd .gl && apt-get "${o[@]}" download -qq libegl1 libglvnd0 libopengl0 libgl1 libglx0 libgles2); }; then
  echo "gpu_prepare.sh: could not download libglvnd's packages into .gl/ (apt-get); the prior stage needs them" >&2
  exit 1
fi
export GDBENCH_CACHE=$PWD/.devcache
tmp=$(mktemp -d)
G=(.venv/bin/python -m gdbench.app.cli generate "a yellow duck" --no-progress)
"${G[@]}" --steps 4 --out "$tmp/empirical" >/dev/null                                   # the 64 px bank, held-out views
"${G[@]}" --steps 4 --resolution 16 --init-points 150 --out "$tmp/small" >/dev/null      # the zoomed 32 px bank of the tests
"${G[@]}" --prior sd --sd-model tiny --steps 2 --resolution 32 --out "$tmp/sd" >/dev/null # the tokenizer's vocabulary
rm -rf "$tmp" .devcache/ext
for f in .devcache/banks/*.npz; do xz -f -T2 "$f"; done
du -sh .whl .devcache .gl
