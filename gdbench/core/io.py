"""Files a run writes and reads: atomic writes with the user's umask, strict JSON (null for a
missing number) that names the file when it is broken, CSV with empty cells for missing
numbers, content hashes, and a lock that keeps two writers out of one run folder."""

from __future__ import annotations

import contextlib
import csv
import errno
import hashlib
import io
import json
import math
import numbers
import os
import re
import socket
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import IO


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


DISK_ERRORS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EFBIG, errno.EIO, errno.EROFS})
"""OS errors of the file being written (a full disk or quota, a file too large, an I/O error, a
read-only file system), as opposed to errors of other files a writer reads."""


def disk_error(e: BaseException, path: str | Path) -> OSError | None:
    """The disk error behind ``e`` (itself, or one in its chain of causes: torch.save reports a
    full disk as a RuntimeError whose context is the OSError, imageio as a ValueError), as an
    OSError naming ``path``; None when there is none."""
    seen: set[int] = set()
    x: BaseException | None = e
    while x is not None and id(x) not in seen:
        if isinstance(x, OSError) and x.errno in DISK_ERRORS:
            return OSError(x.errno, x.strerror or os.strerror(x.errno), str(path))
        seen.add(id(x))
        x = x.__cause__ or x.__context__
    return None


def _reraise(e: BaseException, path: Path):
    """Re-raise ``e``, or the disk error behind it as an OSError naming ``path`` (so the command
    line prints one line, not torch's or imageio's traceback)."""
    err = disk_error(e, path) if isinstance(e, Exception) else None
    if err is None:
        raise e
    raise err from None  # the file the user asked for, not a writer's temporary name


def atomic_write(path: str | Path, write: Callable[[IO[bytes]], None]) -> Path:
    """Write ``path`` through ``write(f)`` into a temporary file in the same folder, then rename
    it over ``path``: readers see the old file or the new one, never a part. The file gets the
    mode a plain ``open()`` would give it (0666 & ~umask), not mkstemp's 0600. A full disk raises
    an OSError naming ``path`` whatever the writer made of it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    except OSError as e:
        _reraise(e, path)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException as e:
        Path(tmp).unlink(missing_ok=True)
        _reraise(e, path)
    return path


@contextlib.contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """For writers that take a file name (imageio, matplotlib, pyav): a temporary name beside
    ``path`` with its suffix (writers choose the format by it). When the block ends without
    error the file is fsynced, given the user's umask and renamed over ``path``; otherwise it is
    removed, and a full disk raises an OSError naming ``path``. A reader sees the old file or
    the new one, never a part."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        fd, name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=path.suffix)
    except OSError as e:
        _reraise(e, path)
    os.close(fd)
    tmp = Path(name)
    try:
        yield tmp
        fd = os.open(tmp, os.O_RDONLY)
        try:
            os.fsync(fd)
        finally:
            os.close(fd)
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException as e:
        tmp.unlink(missing_ok=True)
        _drop_writer(e)
        _reraise(e, path)


def _drop_writer(e: BaseException) -> None:
    """Free now what the failed writer left (imageio's half-closed plugin, whose ``__del__``
    would retry the write at exit and print a second traceback after the error line): clear the
    finished frames of ``e``'s traceback and collect them, quietly."""
    import gc
    import sys
    import traceback

    hook = sys.unraisablehook
    sys.unraisablehook = lambda _unraisable: None  # before the frames go: their locals die with them
    try:
        seen: set[int] = set()
        x: BaseException | None = e
        while x is not None and id(x) not in seen:  # the error and those it arose from
            traceback.clear_frames(x.__traceback__)
            seen.add(id(x))
            x = x.__cause__ or x.__context__
        gc.collect()
    finally:
        sys.unraisablehook = hook


def jsonable(obj):
    """``obj`` with every value JSON can hold strictly: NaN and infinities become None (null),
    tuples lists, numpy scalars and arrays Python numbers and lists, paths strings."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if hasattr(obj, "tolist"):  # numpy scalars and arrays, torch tensors
        return jsonable(obj.tolist())
    if isinstance(obj, Path):
        return str(obj)
    return str(obj)


def json_bytes(obj) -> bytes:
    """Strict JSON (RFC 8259: no NaN or Infinity; a missing number is null), indent 2."""
    return json.dumps(jsonable(obj), indent=2, allow_nan=False).encode()


def write_json(obj, path: str | Path) -> Path:
    """Atomic strict JSON (``json_bytes``): a missing number is written as null, so browsers
    and strict readers load every file the project writes; ``num`` reads it back as NaN."""
    data = json_bytes(obj)
    return atomic_write(path, lambda f: f.write(data))


def num(x) -> float:
    """A number read back from a file: null (None) or an empty CSV cell is NaN."""
    return math.nan if x is None or x == "" else float(x)


def nulls_to_nan(obj):
    """``obj`` read from strict JSON with every null turned back into NaN (for code that formats
    the numbers it reads)."""
    if isinstance(obj, dict):
        return {k: nulls_to_nan(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [nulls_to_nan(v) for v in obj]
    return math.nan if obj is None else obj


def write_csv(rows: list[dict], path: str | Path) -> Path:
    """Atomic CSV of ``rows`` (columns in order of first appearance). A missing number (None,
    NaN, infinity) is an empty cell, so numeric columns hold numbers only."""

    def cell(v):
        if v is None:
            return ""
        if isinstance(v, numbers.Real) and not isinstance(v, bool) and not math.isfinite(float(v)):
            return ""  # NaN and infinities, numpy's included
        return v

    keys: list[str] = []
    for r in rows:
        keys += [k for k in r if k not in keys]
    buf = io.StringIO(newline="")
    w = csv.DictWriter(buf, fieldnames=keys)
    w.writeheader()
    w.writerows({k: cell(v) for k, v in r.items()} for r in rows)
    data = buf.getvalue().encode()
    return atomic_write(path, lambda f: f.write(data))


def read_csv(path: str | Path) -> list[dict]:
    """Rows of a CSV written by ``write_csv``, with numbers, booleans and empty cells converted
    (empty cells become None)."""

    def convert(v: str):
        if v == "":
            return None
        if v in ("True", "False"):
            return v == "True"
        try:
            return int(v)
        except ValueError:
            pass
        try:
            return float(v)
        except ValueError:
            return v

    with open(path, newline="") as f:
        return [{k: convert(v) for k, v in r.items()} for r in csv.DictReader(f)]


def read_json(path: str | Path, *, what: str | None = None) -> dict:
    """A JSON object from ``path``; a broken or non-object file raises ValueError naming it."""
    path = Path(path)
    name = what or path.name
    try:
        obj = json.loads(path.read_text())
    except json.JSONDecodeError as e:
        raise ValueError(f"{name}: {path} is not valid JSON ({e.msg} at line {e.lineno}); fix or delete it") from None
    except UnicodeDecodeError:
        raise ValueError(f"{name}: {path} is not a text file; fix or delete it") from None
    if not isinstance(obj, dict):
        raise ValueError(f"{name}: {path} holds a JSON {type(obj).__name__}, expected an object; fix or delete it")
    return obj


def sha256_file(path: str | Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def run_json_of(ply: str | Path) -> tuple[Path, dict] | None:
    """(path, content) of the run.json beside ``ply`` when ``ply`` is that run's scene.ply (its
    ``scene_sha256`` names this file); None for any other scene file, or one edited since."""
    ply = Path(ply)
    beside = ply.parent / "run.json"
    if ply.name != "scene.ply" or not beside.is_file():
        return None
    info = read_json(beside, what="run.json")
    return (beside, info) if info.get("scene_sha256") == sha256_file(ply) else None


def sha256_json(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()


def check_folder(folder: str | Path, what: str = "out") -> Path:
    """``folder`` as a place to write: a folder or a path that does not exist yet. A file, or a
    symbolic link that leads nowhere (dangling, or a loop), is a ValueError naming ``what``."""
    folder = Path(folder)
    if folder.is_symlink() and not folder.exists():
        raise ValueError(
            f"{what}: {folder} is a symbolic link to {os.readlink(folder)!r}, which does not exist or loops; "
            "expected a folder"
        )
    if folder.exists() and not folder.is_dir():
        raise ValueError(f"{what}: {folder} is a file; expected a folder (or a path that does not exist)")
    return folder


def probe_writable(folder: str | Path, what: str = "out") -> Path:
    """``folder`` (a path that may not exist yet) where files can be made: a probe file is made
    and removed in it, or in its nearest existing parent, so nothing is left behind and nothing is
    created for a command that fails later (a bad prompt). A place that refuses (read-only, /sys,
    /proc, full) is a ValueError naming ``what``, before any work."""
    folder = Path(folder)
    place = folder
    while not place.exists() and place != place.parent:
        place = place.parent
    try:
        fd, probe = tempfile.mkstemp(dir=place, prefix=".gdbench-probe.")
        os.close(fd)
        os.unlink(probe)
    except OSError as e:
        raise ValueError(f"{what}: cannot write into {folder} ({e.strerror or e} at {place})") from None
    return folder


def writable_folder(folder: str | Path, what: str = "out") -> Path:
    """``check_folder``, then make it and write and remove a probe file there: a read-only or
    full place fails now, naming the folder, not after minutes of work."""
    folder = check_folder(folder, what)
    folder.mkdir(parents=True, exist_ok=True)
    return probe_writable(folder, what)


class FolderBusy(RuntimeError):
    """Another process holds the folder's lock."""


class FolderLock:
    """An exclusive lock on a folder for the lifetime of a run (``fcntl.flock`` on
    ``<folder>/.gdbench.lock``). The kernel drops it when the holder exits, however it exits,
    so a lock left by a killed run never blocks the next one. The file names its holder."""

    NAME = ".gdbench.lock"

    def __init__(self, folder: str | Path, what: str = "out"):
        self.folder = Path(folder)
        self.what = what
        self._fd: int | None = None

    def __enter__(self) -> FolderLock:
        import fcntl

        check_folder(self.folder, self.what)
        self.folder.mkdir(parents=True, exist_ok=True)
        path = self.folder / self.NAME
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o666)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 512, 0).decode(errors="replace").strip() or "unknown process"
            os.close(fd)
            raise FolderBusy(
                f"{self.what}: {self.folder} is in use by another gdbench run ({holder}); "
                "wait for it to finish or use another folder"
            ) from None
        os.ftruncate(fd, 0)
        stamp = time.strftime("%Y-%m-%d %H:%M:%S")
        os.pwrite(fd, f"pid {os.getpid()} on {socket.gethostname()}, since {stamp}\n".encode(), 0)
        self._fd = fd
        return self

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            os.close(self._fd)  # closing releases the flock
            self._fd = None


@contextlib.contextmanager
def captured_output(log: str | Path | None):
    """Send everything written to file descriptors 1 and 2 while the block runs to ``log``
    (appended; None: discarded): native code's lines (COLMAP's glog warnings) and Python's own
    prints alike, so the block should hold the native calls only. Python's streams are flushed
    before and after, so nothing printed earlier lands in the log."""
    import sys

    for s in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            s.flush()
    target = os.open(os.fspath(log) if log is not None else os.devnull, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
    saved = []
    try:
        for fd in (1, 2):
            try:
                saved.append((fd, os.dup(fd)))
            except OSError:  # no such descriptor (a daemon): nothing to capture there
                continue
            os.dup2(target, fd)
        yield
    finally:
        for s in (sys.stdout, sys.stderr):
            with contextlib.suppress(Exception):
                s.flush()
        for fd, copy in saved:
            os.dup2(copy, fd)
            os.close(copy)
        os.close(target)


def prompt_slug(prompt: str, what: str = "prompt") -> str:
    """A prompt as a folder name: lower-case letters, digits and '_' only, so no prompt can
    reach outside its parent folder ('../../a duck' -> 'a_duck')."""
    name = re.sub(r"[^a-z0-9]+", "_", prompt.lower()).strip("_")
    if not name:
        raise ValueError(f"{what}: {prompt!r} has no letters or digits to name a folder by")
    if len(name) > 200:  # a folder name has at most 255 bytes on common file systems
        raise ValueError(f"{what}: {prompt[:40]!r}... names a folder of {len(name)} characters; expected at most 200")
    return name


def load_torch_safely(path: str | Path, remedy: str, error: type[Exception] = ValueError):
    """What ``torch.save`` wrote to ``path``, loaded with ``weights_only`` (tensors and plain data
    only, so a crafted file cannot run code). A file that is not a whole torch archive, or that
    holds other objects, raises ``error`` in one line naming it and ending with ``remedy``."""
    import pickle
    import zipfile

    import torch

    path = Path(path)
    with open(path, "rb") as f:
        magic = f.read(4)
    if magic != b"PK\x03\x04":  # torch.save writes a zip archive
        raise error(f"checkpoint: {path} is unreadable (empty, truncated or not a checkpoint); {remedy}")
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except pickle.UnpicklingError:
        raise error(
            f"checkpoint: {path} holds objects other than tensors and plain data; refusing to load it "
            f"(it may run code). {remedy[:1].upper()}{remedy[1:]}"
        ) from None
    except (RuntimeError, EOFError, zipfile.BadZipFile, OSError) as e:
        raise error(
            f"checkpoint: {path} is unreadable (truncated or not a checkpoint: {type(e).__name__}); {remedy}"
        ) from None
