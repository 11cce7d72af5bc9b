"""The on-disk cache: what gdbench builds once and reuses, under ``$GDBENCH_CACHE`` (default
``~/.cache/gdbench``). Everything in it is rebuilt on demand, so any part may be removed.

Kinds (sub-folders): ``banks`` (each prompt's image bank, rendered by pyrender: 10-45 s to build,
20-100 MB each), ``fixtures`` (the 3D calibration scenes of the metrics), ``learned_data`` (the
learned prior's training renders), ``clip_tokenizer`` (the tiny Stable Diffusion's tokenizer files)
and ``ext`` (the compiled C++ compositor; rebuilt in about a minute).
"""

from __future__ import annotations

import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

KINDS = {
    "banks": "image banks of the prompts (pyrender renders of the assets)",
    "fixtures": "3D calibration scenes of the metrics",
    "learned_data": "the learned prior's training renders",
    "clip_tokenizer": "the tiny Stable Diffusion's tokenizer files",
    "ext": "the compiled C++ compositor",
}
"""Sub-folder -> what it holds."""

FILES = {
    "prebuild.log": "the log of the background bank build (scripts/setup.sh: gdbench cache build)",
    "prebuild.pid": "the process id of the background bank build, while it runs",
}
"""gdbench's own files at the top of the cache -> what they are (``clear`` leaves them)."""


def root() -> Path:
    """The cache folder: ``$GDBENCH_CACHE`` (an empty value counts as unset), else
    ``~/.cache/gdbench``."""
    return Path(os.environ.get("GDBENCH_CACHE") or Path.home() / ".cache" / "gdbench")


@dataclass
class Entry:
    kind: str
    path: Path
    files: int
    bytes: int
    newest: float | None
    """Modification time of the newest file (seconds since the epoch), None when empty."""


def _walk(path: Path) -> tuple[int, int, float | None]:
    files, size, newest = 0, 0, None
    for dirpath, _dirs, names in os.walk(path):
        for n in names:
            try:
                st = os.lstat(os.path.join(dirpath, n))
            except OSError:  # removed while we looked
                continue
            files, size = files + 1, size + st.st_size
            newest = st.st_mtime if newest is None else max(newest, st.st_mtime)
    return files, size, newest


def entries() -> list[Entry]:
    """One entry per kind present in the cache, and one per unknown sub-folder or file."""
    base = root()
    if not base.is_dir():
        return []
    out = []
    for p in sorted(base.iterdir()):
        if p.is_dir() and not p.is_symlink():
            files, size, newest = _walk(p)
        else:
            st = p.lstat()
            files, size, newest = 1, st.st_size, st.st_mtime
        out.append(Entry(p.name, p, files, size, newest))
    return out


def human(n: float) -> str:
    for unit in ("B", "KB", "MB", "GB"):
        if abs(n) < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "B" else f"{n:.1f} {unit}"
        n /= 1000
    raise AssertionError  # pragma: no cover


def listing() -> str:
    """The table ``gdbench cache list`` prints."""
    es = entries()
    lines = [f"gdbench cache: {root()} ({human(sum(e.bytes for e in es))} in {sum(e.files for e in es)} files)"]
    for e in es:
        age = "" if e.newest is None else f", newest {(time.time() - e.newest) / 86400:.0f} days old"
        what = KINDS.get(e.kind) or FILES.get(e.kind) or "not gdbench's (left alone by clear)"
        lines.append(f"  {e.kind:15s} {human(e.bytes):>9s} {e.files:6d} files{age}  {what}")
    if not es:
        lines.append("  (empty)")
    return "\n".join(lines)


def clear(kinds: list[str] | None = None) -> tuple[int, int]:
    """Remove the given kinds (default: all of ``KINDS``); returns (files, bytes) removed. Only
    gdbench's own sub-folders are touched, whatever else the folder holds."""
    unknown = [k for k in kinds or [] if k not in KINDS]
    if unknown:
        raise ValueError(f"kinds: unknown {unknown}; expected some of {sorted(KINDS)}")
    base = root()
    if not base.is_absolute() or base.resolve() == Path.cwd().resolve():
        raise ValueError(
            f"GDBENCH_CACHE: {str(base)!r} is relative or the current folder; clear removes only an absolute "
            "cache folder (a project's own fixtures/ could sit here)"
        )
    files = size = 0
    for k in kinds or list(KINDS):
        p = root() / k
        if p.is_symlink() or p.is_file():
            raise ValueError(f"GDBENCH_CACHE: {p} is not a folder; remove it by hand if it is not needed")
        if p.is_dir():
            n, b, _ = _walk(p)
            shutil.rmtree(p)
            files, size = files + n, size + b
    return files, size
