"""Which code made a result, and when: every result file records ``code_commit()`` and a UTC
time, and a score is reused only under the same code (``same_code``)."""

from __future__ import annotations

import functools
import hashlib
import subprocess
import time
from pathlib import Path

CODE = ("gdbench", "renderers", "pyproject.toml")
"""What counts as the code: edits elsewhere (docs, results, the README) do not change it."""

SOURCES = (".py", ".cpp", ".h")
"""Suffixes of the source files a new, untracked file or a non-checkout copy is hashed by."""


def _git(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=root, capture_output=True, timeout=30)


def _source_hash(root: Path) -> str:
    """SHA-256 (12 hex digits) of the package's source files, for a copy git cannot describe."""
    h = hashlib.sha256()
    for top in (root / c for c in CODE if (root / c).is_dir()):
        for path in sorted(top.rglob("*")):
            if path.suffix in SOURCES and "__pycache__" not in path.parts:
                h.update(str(path.relative_to(root)).encode() + b"\0" + path.read_bytes())
    return h.hexdigest()[:12]


@functools.cache
def code_commit() -> str:
    """The code this package runs: ``checkout_code`` of its own checkout."""
    return checkout_code(Path(__file__).resolve().parents[2])


def checkout_code(root: Path) -> str:
    """The code of the checkout at ``root``: its commit (12 hex digits); when the code (``CODE``)
    differs from it, ``<commit>-dirty-<hash of the changes>``, so the same edits give the same
    name and other edits another. Where git cannot say (an installed copy, git missing or refusing
    the folder): ``src-<hash of the source files>``. What a run made there records as its commit."""
    if (root / ".git").exists():
        try:
            head = _git(root, "rev-parse", "--short=12", "HEAD")
            diff = _git(root, "diff", "HEAD", "--binary", "--no-ext-diff", "--no-color", "--", *CODE)
            new = _git(root, "ls-files", "--others", "--exclude-standard", "-z", "--", *CODE)
            if head.returncode == 0 and diff.returncode == 0 and new.returncode == 0:
                h = hashlib.sha256(diff.stdout)
                names = sorted(n for n in new.stdout.decode().split("\0") if n.endswith(SOURCES))
                for name in names:
                    h.update(name.encode() + b"\0" + (root / name).read_bytes())
                dirty = bool(diff.stdout) or bool(names)
                return head.stdout.decode().strip() + (f"-dirty-{h.hexdigest()[:8]}" if dirty else "")
        except (OSError, subprocess.SubprocessError):
            pass
    return f"src-{_source_hash(root)}"


def same_code(commit: str | None) -> bool:
    """Whether a result recorded under ``commit`` was made by this code: the same commit (for a
    dirty tree, the same changes to it)."""
    return commit is not None and commit == code_commit()


def utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def made(params: dict, seconds: float, device: str | None = None) -> dict:
    """The provenance of one result block: its parameters, the commit, the time, its cost (and
    where it was computed, outside the parameters: a block is reused across devices)."""
    out = {"params": params, "commit": code_commit(), "utc": utc_now(), "seconds": seconds}
    return out | ({"device": device} if device is not None else {})
