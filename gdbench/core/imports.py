"""Objects of the user's named on a command line: ``pkg.module:name`` (a module on the path) or
``path/to/file.py:name`` (a Python file), as renderers and methods enter gdbench."""

from __future__ import annotations

import importlib
from pathlib import Path


def import_module(module: str):
    """A module by its dotted name, or a Python file by its path (``.py``)."""
    if not module.endswith(".py"):
        return importlib.import_module(module)
    import hashlib
    import sys
    from importlib.util import module_from_spec, spec_from_file_location

    path = Path(module).resolve()
    if not path.is_file():
        raise FileNotFoundError(f"no file {module}")
    stat = path.stat()
    key = (str(path), stat.st_mtime_ns, stat.st_size)
    if key in _FILES:  # once per version of the file: its top level runs once, its state is shared
        return _FILES[key]
    name = f"gdbench_user_{path.stem}_{hashlib.sha256(str(path).encode()).hexdigest()[:8]}"
    spec = spec_from_file_location(name, path)
    mod = module_from_spec(spec)
    sys.modules[name] = mod  # dataclasses and pickling look their module up by name
    try:
        spec.loader.exec_module(mod)
    except BaseException:
        sys.modules.pop(name, None)
        raise
    _FILES[key] = mod
    return mod


_FILES: dict[tuple, object] = {}
"""Python files imported by path in this process, by (path, modification time, size)."""


def is_ref(text: str) -> bool:
    """Whether ``text`` has the shape of a reference (something:name)."""
    module, sep, attr = text.rpartition(":")
    return bool(sep and module and attr)


def import_ref(ref: str, what: str) -> object:
    """The object ``ref`` names (``module:name``, ``file.py:name``, dotted names after the colon
    reach attributes); anything that fails is a one-line ValueError starting with ``what``."""
    module, sep, attr = ref.rpartition(":")
    if not sep or not module or not attr:
        raise ValueError(f"{what} {ref!r}: expected module:function (pkg.mod:fn) or path/to/file.py:function")
    try:
        obj = import_module(module)
    except Exception as e:  # any failure to import is the user's module's: one line
        msg = str(e).splitlines()[0] if str(e) else ""
        raise ValueError(f"{what} {ref!r}: cannot import {module!r}: {type(e).__name__}: {msg}") from None
    for part in attr.split("."):
        if not hasattr(obj, part):
            raise ValueError(f"{what} {ref!r}: {module!r} has no {attr!r}")
        obj = getattr(obj, part)
    return obj
