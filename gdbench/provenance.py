"""Which code made a result, and when: every result file records ``code_commit()`` and a UTC
time, and a score is reused only under the same code (``same_code``)."""

from __future__ import annotations

import functools
import hashlib
import subprocess
import time
from pathlib import Path


def _git(root: Path, *args: str) -> subprocess.CompletedProcess:
    return subprocess.run(["git", *args], cwd=root, capture_output=True, timeout=30)


@functools.cache
def code_commit() -> str:
    """The commit of the checkout this package runs from (12 hex digits); when tracked files
    differ from it or new source files exist, ``<commit>-dirty-<hash of the changes>``, so
    the same edits give the same name and other edits another; ``gdbench <version>`` for an
    installed (non-checkout) copy."""
    root = Path(__file__).resolve().parents[1]
    if (root / ".git").exists():
        try:
            head = _git(root, "rev-parse", "--short=12", "HEAD")
            if head.returncode == 0:
                h = hashlib.sha256(_git(root, "diff", "HEAD", "--binary").stdout)
                new = _git(root, "ls-files", "--others", "--exclude-standard", "-z", "--", "gdbench", "renderers")
                names = sorted(n for n in new.stdout.decode().split("\0") if n.endswith((".py", ".cpp", ".h")))
                for name in names:
                    h.update(name.encode() + b"\0" + (root / name).read_bytes())
                dirty = h.hexdigest() != hashlib.sha256(b"").hexdigest() or bool(names)
                return head.stdout.decode().strip() + (f"-dirty-{h.hexdigest()[:8]}" if dirty else "")
        except (OSError, subprocess.SubprocessError):
            pass
    from importlib import metadata

    try:
        return f"gdbench {metadata.version('gdbench')}"
    except metadata.PackageNotFoundError:
        return "unknown"


def same_code(commit: str | None) -> bool:
    """Whether a result recorded under ``commit`` was made by this code: the same commit (for a
    dirty tree, the same changes to it)."""
    now = code_commit()
    return commit == now and now != "unknown"


def utc_now() -> str:
    return time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())


def made(params: dict, seconds: float) -> dict:
    """The provenance of one result block: its parameters, the commit, the time, its cost."""
    return {"params": params, "commit": code_commit(), "utc": utc_now(), "seconds": seconds}
