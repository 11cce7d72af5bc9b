"""Loader of the optional C++/OpenMP CPU extension: the compositor (``csrc/composite_cpu.cpp``),
the projection and tile binning (``csrc/project_cpu.cpp``), the SH colour without gradients
(``csrc/sh_cpu.cpp``) and, for the empirical prior's image bank, the separable zoom of
``gdbench.assets.zoom`` and the squared distances of ``gdbench.priors.empirical``
(``csrc/bank_cpu.cpp``), and the training step's normal draws (``gdbench.core.rand``,
``csrc/normal_cpu.cpp``).

The built module lives in one file, ``<cache>/gdbench_splat_cpu_<hash of the sources>.so``
(``<cache>`` is ``$GDBENCH_CACHE/ext/torch<version>-py<version>``, default under
``~/.cache/gdbench``), and is imported from there directly: no build system runs once it
exists, so checkouts with the same source share it and never rebuild it in turn. When it is
missing, it is compiled with ``torch.utils.cpp_extension.load`` (needs a C++ compiler and
``ninja``) in a private temporary folder and moved into place with one rename: concurrent
builds cannot corrupt it, and no build lock is shared, so a lock left by a killed build can
never hang a run. ``make setup`` builds it ahead of time (``python -m renderers.splat._ext``).
When it cannot be built, the pure-torch compositor runs instead and ``extension_status()``
says why. ``GDBENCH_SPLAT_BACKEND=torch`` forces the pure-torch path.
"""

from __future__ import annotations

import hashlib
import importlib.util
import os
import shutil
import sys
import tempfile
import time
import warnings
from pathlib import Path
from types import ModuleType

_STATE: dict[str, object] = {}
CSRC = Path(__file__).parent / "csrc"
SOURCES = (
    CSRC / "composite_cpu.cpp",
    CSRC / "project_cpu.cpp",
    CSRC / "sh_cpu.cpp",
    CSRC / "bank_cpu.cpp",
    CSRC / "normal_cpu.cpp",
    CSRC / "noise_cpu.cpp",
)
HEADERS = (CSRC / "splat_cpu.h", CSRC / "simd.h")


CFLAGS = ["-O3", "-fopenmp", "-march=native", "-ffp-contract=off", "-fno-trapping-math", "-fno-math-errno"]
"""Built for the CPU it runs on; no automatic fused multiply-add contraction: the compiler could
contract one expression differently where it is inlined into the forward and into the backward,
which must agree on every alpha. The kernels fuse explicitly instead (simd.h ``fmadd``: the exp's
polynomial, the power, the forward's blends), which is also faster.
``-fno-trapping-math`` only tells the compiler that no floating-point exception is trapped
(none is: torch never enables traps), so it may evaluate both sides of a comparison-select;
without it GCC 12 vectorised none of the compositor's loops that hold a select (the clamp in
fast_exp, the branch-free forward), and with it they run as 8-wide vectors: the same operations
in the same order, bit-identical outputs and gradients (checked in float32 and float64), and
about twice as fast (docs/renderer.md, "Compositor backends").
``-fno-math-errno``: sqrt and friends need not set errno (nothing reads it), so GCC vectorises
the compositor's per-row ellipse spans (a scalar sqrt, ceil and floor per row otherwise); the
same values (sqrt is correctly rounded either way), the same bits checked by scripts/ab_ext.py."""


def module_name() -> str:
    """The module's name carries a hash of every source, header and flag: a change is a new library."""
    h = hashlib.sha256(" ".join(CFLAGS).encode())
    for path in SOURCES + HEADERS:
        h.update(path.read_bytes())
    return f"gdbench_splat_cpu_{h.hexdigest()[:10]}"


def _cpu_tag() -> str:
    """A short hash of this CPU's instruction-set flags: the library is built for the CPU it runs
    on (-march=native), so a cache shared between machines keeps one build per kind of CPU."""
    try:
        with open("/proc/cpuinfo") as f:
            flags = next((line for line in f if line.startswith(("flags", "Features"))), "")
    except OSError:
        flags = ""
    import platform

    return hashlib.sha256((platform.machine() + flags).encode()).hexdigest()[:8]


def build_dir() -> Path:
    import torch

    root = Path(os.environ.get("GDBENCH_CACHE") or Path.home() / ".cache" / "gdbench") / "ext"  # as gdbench.core.cache
    py = f"py{sys.version_info.major}{sys.version_info.minor}"
    return root / f"torch{torch.__version__.split('+')[0]}-{py}-{_cpu_tag()}"


def _import_file(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot import {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def compile_sources(
    name: str, build_directory: Path, csrc: Path = CSRC, extra_cflags: tuple[str, ...] = (), verbose: bool = False
) -> ModuleType:
    """Compile the sources as they are in ``csrc`` (default: this checkout's) into
    ``build_directory`` and import the module; ``scripts/ab_ext.py`` builds other revisions."""
    from torch.utils.cpp_extension import load

    return load(
        name=name,
        sources=[str(csrc / p.name) for p in SOURCES],
        extra_include_paths=[str(csrc)],
        extra_cflags=CFLAGS + list(extra_cflags),
        extra_ldflags=["-fopenmp"],
        build_directory=str(build_directory),
        verbose=verbose,
    )


def _build(name: str, target: Path, verbose: bool) -> ModuleType:
    """Compile in a private temporary folder, then rename the library into ``target``."""
    target.parent.mkdir(parents=True, exist_ok=True)
    for old in target.parent.glob(".build-*"):  # leftovers of killed builds (older than an hour)
        if time.time() - old.stat().st_mtime > 3600:
            shutil.rmtree(old, ignore_errors=True)
    tmp = Path(tempfile.mkdtemp(prefix=".build-", dir=target.parent))
    try:
        module = compile_sources(name, tmp, verbose=verbose)
        built = tmp / f"{name}.so"
        os.chmod(built, 0o755)
        os.replace(built, target)
        return module
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


def load_extension(verbose: bool = False) -> ModuleType | None:
    """The compiled module, or None (with the reason kept for ``extension_status``)."""
    if "module" in _STATE:
        return _STATE["module"]  # type: ignore[return-value]
    module = None
    if os.environ.get("GDBENCH_SPLAT_BACKEND", "auto") == "torch":
        _STATE["reason"] = "disabled by GDBENCH_SPLAT_BACKEND=torch"
    else:
        name = module_name()
        target = build_dir() / f"{name}.so"
        try:
            if target.is_file():
                try:
                    module = _import_file(name, target)
                    _STATE["reason"] = "loaded"
                except ImportError:  # a broken or foreign library: build it again
                    target.unlink(missing_ok=True)
            if module is None:
                module = _build(name, target, verbose)
                _STATE["reason"] = "loaded (built now)"
        except Exception as e:  # compiler, ninja or headers missing; an unwritable cache
            module = None
            _STATE["reason"] = f"build failed: {type(e).__name__}: {e}".splitlines()[0]
            warnings.warn(
                "renderers.splat: the C++ CPU compositor could not be built, using the slower pure-torch "
                f"path ({_STATE['reason']}). Install g++ and `pip install ninja` to build it.",
                stacklevel=2,
            )
    _STATE["module"] = module
    _STATE["path"] = str(build_dir() / f"{module_name()}.so") if module is not None else None
    return module


def extension_status() -> str:
    load_extension()
    return str(_STATE["reason"])


if __name__ == "__main__":
    mod = load_extension(verbose=True)
    print("renderers.splat C++ compositor:", extension_status(), _STATE.get("path") or "")
    raise SystemExit(0 if mod is not None else 1)
