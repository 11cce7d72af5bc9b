"""Loader of the optional C++/OpenMP CPU compositor (``csrc/composite_cpu.cpp``).

It is compiled on first use with ``torch.utils.cpp_extension.load`` (needs a C++ compiler
and the ``ninja`` package) and cached in ``$TORCH_EXTENSIONS_DIR`` (default
``~/.cache/torch_extensions``); ``make setup`` builds it ahead of time with
``python -m renderers.splat._ext``. When it cannot be built, the pure-torch compositor runs
instead and ``extension_status()`` says why. ``GDBENCH_SPLAT_BACKEND=torch`` forces the
pure-torch path.
"""

from __future__ import annotations

import hashlib
import os
import warnings
from pathlib import Path
from types import ModuleType

_STATE: dict[str, object] = {}


def load_extension(verbose: bool = False) -> ModuleType | None:
    """The compiled module, or None (with the reason kept for ``extension_status``)."""
    if "module" in _STATE:
        return _STATE["module"]  # type: ignore[return-value]
    module = None
    if os.environ.get("GDBENCH_SPLAT_BACKEND", "auto") == "torch":
        _STATE["reason"] = "disabled by GDBENCH_SPLAT_BACKEND=torch"
    else:
        try:
            from torch.utils.cpp_extension import load

            src = Path(__file__).parent / "csrc" / "composite_cpu.cpp"
            # the name carries a hash of the source, so checkouts with different sources never
            # overwrite each other's build in the shared cache, and identical ones share it
            digest = hashlib.sha256(src.read_bytes()).hexdigest()[:10]
            module = load(
                name=f"gdbench_splat_cpu_{digest}",
                sources=[str(src)],
                extra_cflags=["-O3", "-fopenmp"],
                extra_ldflags=["-fopenmp"],
                verbose=verbose,
            )
            _STATE["reason"] = "loaded"
        except Exception as e:  # compiler, ninja or headers missing
            _STATE["reason"] = f"build failed: {type(e).__name__}: {e}".splitlines()[0]
            warnings.warn(
                "renderers.splat: the C++ CPU compositor could not be built, using the slower pure-torch "
                f"path ({_STATE['reason']}). Install g++ and `pip install ninja` to build it.",
                stacklevel=2,
            )
    _STATE["module"] = module
    return module


def extension_status() -> str:
    load_extension()
    return str(_STATE["reason"])


if __name__ == "__main__":
    mod = load_extension(verbose=True)
    print("renderers.splat C++ compositor:", extension_status())
    raise SystemExit(0 if mod is not None else 1)
