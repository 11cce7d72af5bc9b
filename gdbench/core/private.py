"""The private APIs of torch and Python that gdbench calls, each in one guarded place.

Each is the only way to a result that a public API gives at a much higher cost, and each may
change or vanish in a release: a missing one raises one line naming it, the version found and
what it was for, instead of an AttributeError deep in a training step.

- ``fused_adam_`` and ``foreach_add_``: torch.optim.Adam(fused=True)'s kernel and its step count,
  without torch.optim's import of torch._dynamo (seconds of a training process; train/adam.py).
- ``non_finite_check_``: one kernel over all gradients for non-finite values (torch's GradScaler
  check; train/update.py).
- ``shutdown_threads`` and ``run_exit_functions``: Python's own first exit steps, for a process
  that then ends with ``os._exit`` (app/cli.py's ``program``).
"""

from __future__ import annotations

import atexit
import sys
import threading

import torch


def _guarded(owner, name: str, what: str):
    """``owner.name`` if it exists, else a function raising one line that says what is missing."""
    fn = getattr(owner, name, None)
    if fn is not None:
        return fn
    version = f"torch {torch.__version__}" if owner is torch else f"Python {sys.version.split()[0]}"

    def missing(*_args, **_kwargs):
        raise RuntimeError(f"{owner.__name__}.{name} is missing in {version} ({what}); gdbench is tested with "
                           "the versions in constraints.txt")  # fmt: skip

    return missing


fused_adam_ = _guarded(torch, "_fused_adam_", "the trainer's Adam step")
foreach_add_ = _guarded(torch, "_foreach_add_", "Adam's step count")
non_finite_check_ = _guarded(torch, "_amp_foreach_non_finite_check_and_unscale_", "the gradients' finite check")
shutdown_threads = _guarded(threading, "_shutdown", "joining threads before a fast exit")
run_exit_functions = _guarded(atexit, "_run_exitfuncs", "exit handlers before a fast exit")
