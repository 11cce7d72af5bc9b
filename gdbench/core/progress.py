"""Progress reports that read well on a terminal and in a log file.

``progress(total, desc)`` gives tqdm's bar when standard error is a terminal, and otherwise a
``PlainProgress``: one flushed line at most every ``every_s`` seconds (and at least every tenth
of the work), plus one at the end, each with the count, the rate and the time left. A bar piped
to a file writes a carriage-return update per refresh (about 170 per 200 steps); these lines are
what ``tail -f`` and CI logs want. ``GDBENCH_PROGRESS=plain|bar`` forces one or the other.
"""

from __future__ import annotations

import os
import sys
import time
from typing import TextIO


def _fmt_s(s: float) -> str:
    s = max(0.0, s)
    if s < 60:
        return f"{s:.0f}s"
    if s < 3600:
        return f"{int(s // 60)}m{int(s % 60):02d}s"
    return f"{int(s // 3600)}h{int(s % 3600 // 60):02d}m"


class PlainProgress:
    """tqdm's subset the project uses (update, set_postfix, close, context manager), as lines."""

    def __init__(
        self,
        total: int,
        desc: str = "",
        unit: str = "it",
        initial: int = 0,
        every_s: float = 10.0,
        file: TextIO | None = None,
        clock=time.monotonic,
    ):
        self.total, self.desc, self.unit, self.n = int(total), desc, unit, int(initial)
        self.start_n, self.every_s, self.file, self.clock = self.n, every_s, file, clock
        self.t0 = self.last_t = clock()
        self.last_n = self.n
        self.postfix = ""
        self.closed = False
        self.step_n = max(1, self.total // 10)  # at least a line per tenth of the work

    def _line(self) -> str:
        done = self.n - self.start_n
        dt = self.clock() - self.t0
        rate = done / dt if dt > 0 and done else 0.0
        left = (self.total - self.n) / rate if rate else float("nan")
        pct = 100.0 * self.n / self.total if self.total else 100.0
        eta = f", {_fmt_s(left)} left" if rate and self.n < self.total else ""
        post = f" [{self.postfix}]" if self.postfix else ""
        speed = f"{rate:.2f} {self.unit}/s" if rate >= 1 or not rate else f"{1 / rate:.1f} s/{self.unit}"
        return f"{self.desc}: {self.n}/{self.total} {self.unit} ({pct:.0f}%), {_fmt_s(dt)} elapsed, {speed}{eta}{post}"

    def _emit(self) -> None:
        print(self._line(), file=self.file or sys.stderr, flush=True)
        self.last_t, self.last_n = self.clock(), self.n

    def update(self, n: int = 1) -> None:
        self.n += n
        if self.n >= self.total or self.clock() - self.last_t >= self.every_s or self.n - self.last_n >= self.step_n:
            if self.n < self.total:  # the end line comes from close()
                self._emit()

    def set_postfix(self, **kw) -> None:
        self.postfix = ", ".join(f"{k}={v}" for k, v in kw.items())

    def write(self, s: str) -> None:
        """A line of results (standard output, as ``tqdm.write``)."""
        print(s, flush=True)

    def close(self) -> None:
        if not self.closed:
            self.closed = True
            if self.n != self.last_n or self.n == self.start_n:
                self._emit()

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def is_terminal(stream: TextIO | None = None) -> bool:
    mode = os.environ.get("GDBENCH_PROGRESS", "")
    if mode in ("plain", "bar"):
        return mode == "bar"
    s = stream or sys.stderr
    return bool(getattr(s, "isatty", lambda: False)())


def progress(total: int, desc: str = "", unit: str = "it", initial: int = 0, *, disable: bool = False):
    """A progress reporter: tqdm on a terminal, ``PlainProgress`` lines otherwise; None when
    ``disable``."""
    if disable or total <= 0:  # nothing to report on
        return None
    if is_terminal():
        from tqdm import tqdm

        return tqdm(total=total, initial=initial, desc=desc, unit=unit, dynamic_ncols=True)
    return PlainProgress(total, desc, unit, initial)


def track(items, desc: str = "", unit: str = "it", *, disable: bool = False):
    """Iterate over ``items`` (a sized collection) with a ``progress`` report."""
    items = list(items)
    bar = progress(len(items), desc, unit, disable=disable)
    if bar is None:
        yield from items
        return
    try:
        for x in items:
            yield x
            bar.update(1)
    finally:
        bar.close()


class Phases:
    """Progress over named stages of known count (a score: view metrics, COLMAP's features,
    matching, mapping): ``start(name)`` ends the stage before it; a line per stage in a log, a bar
    whose label is the stage on a terminal. ``disable``: silent."""

    def __init__(self, total: int, desc: str, *, disable: bool = False, clock=time.monotonic):
        self.total, self.desc, self.clock = total, desc, clock
        self.done, self.t0, self.current = 0, clock(), None
        self.bar = None
        self.plain = not is_terminal()
        if not disable and total > 0 and not self.plain:
            from tqdm import tqdm

            self.bar = tqdm(total=total, desc=desc, unit="stage", dynamic_ncols=True)
        self.silent = disable or total <= 0

    @property
    def total(self) -> int:
        return self._total

    @total.setter
    def total(self, n: int) -> None:  # stages found to have nothing to do (a reused score)
        self._total = n
        if getattr(self, "bar", None) is not None:
            self.bar.total = n
            self.bar.refresh()

    def start(self, name: str) -> None:
        if self.current is not None:
            self._finish()
        self.current = name
        if self.silent:
            return
        if self.bar is not None:
            self.bar.set_postfix_str(name)
        else:
            msg = f"{self.desc}: {name} ({self.done + 1}/{self.total}), {_fmt_s(self.clock() - self.t0)} elapsed"
            print(msg, file=sys.stderr, flush=True)

    def _finish(self) -> None:
        self.done += 1
        if self.bar is not None:
            self.bar.update(1)

    def close(self) -> None:
        if self.current is not None:
            self._finish()
            self.current = None
        if self.bar is not None:
            self.bar.close()
            self.bar = None
        elif not self.silent and self.done:
            print(f"{self.desc}: done in {_fmt_s(self.clock() - self.t0)}", file=sys.stderr, flush=True)
            self.silent = True

    def __enter__(self):
        return self

    def __exit__(self, *exc) -> None:
        self.close()
