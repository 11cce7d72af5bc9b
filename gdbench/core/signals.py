"""Stop signals, in one place: what ends a run cleanly (``STOP_SIGNALS``), the error a run raises
after saving its checkpoint (``RunInterrupted``), a training loop's deferral of the signals to the
end of its step (``defer_stop_signals``), and the handlers a command installs outside training
loops (``install_stop_handlers``: SIGTERM and SIGHUP stop it as Ctrl-C does)."""

from __future__ import annotations

import contextlib
import signal
import threading
from pathlib import Path

STOP_SIGNALS = tuple(getattr(signal, n) for n in ("SIGINT", "SIGTERM", "SIGHUP") if hasattr(signal, n))
"""What ends a run cleanly: Ctrl-C (SIGINT), ``timeout``/``kill``/Slurm (SIGTERM) and a closed
terminal or SSH session (SIGHUP)."""


class RunInterrupted(RuntimeError):
    """A stop signal (``STOP_SIGNALS``) during training: the checkpoint was saved first.
    ``exit_code`` is the shell's 128 + the signal's number (130 for Ctrl-C, 143 for SIGTERM,
    129 for SIGHUP)."""

    def __init__(self, message: str, signum: int = signal.SIGINT):
        super().__init__(message)
        self.signum = int(signum)

    @property
    def exit_code(self) -> int:
        return 128 + self.signum

    @classmethod
    def at(cls, signum: int, step: int, steps: int, ckpt: Path) -> RunInterrupted:
        return cls(
            f"interrupted by {signal.Signals(signum).name} at step {step} of {steps}; checkpoint saved to {ckpt}; "
            "run the same command again to resume",
            signum,
        )


@contextlib.contextmanager
def defer_stop_signals(flag: list):
    """While active, each of ``STOP_SIGNALS`` appends its number to ``flag`` instead of stopping
    the process (main thread only; elsewhere signals cannot be caught and nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = {}
    for s in STOP_SIGNALS:
        if signal.getsignal(s) is not signal.SIG_IGN:  # nohup's ignored SIGHUP stays ignored
            previous[s] = signal.signal(s, lambda signum, _frame: flag.append(signum))
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


class Stopped(KeyboardInterrupt):
    """SIGTERM or SIGHUP outside a training loop: raised like Ctrl-C's KeyboardInterrupt, so files
    being written are removed (``io.atomic_write``) and the command ends with one line."""

    def __init__(self, signum: int):
        super().__init__(signum)
        self.signum = int(signum)


def _stop(signum, _frame):
    raise Stopped(signum)


def install_stop_handlers() -> None:
    """SIGTERM and SIGHUP raise ``Stopped`` (as Ctrl-C raises KeyboardInterrupt); a training loop
    defers all three to the end of its step (``defer_stop_signals``)."""
    for s in (getattr(signal, n) for n in ("SIGTERM", "SIGHUP") if hasattr(signal, n)):
        if signal.getsignal(s) is not signal.SIG_IGN:  # nohup's ignored SIGHUP stays ignored
            signal.signal(s, _stop)
