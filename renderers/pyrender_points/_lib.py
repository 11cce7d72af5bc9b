"""Lazy import of pyrender for offscreen rendering (OSMesa, or EGL), with the three known fixes.

- ``PYOPENGL_PLATFORM`` defaults to ``osmesa`` when no display is set (needs Debian's
  ``libosmesa6``; ``egl`` renders on a GPU through its driver's EGL);
- numpy 2 removed ``np.infty``, which pyrender 0.1.45 still uses: it is aliased to ``np.inf``;
- pyrender imports its interactive viewer, whose pyglet needs X11's libraries: on a machine
  without them (a GPU server) the import is retried with the viewer stubbed out, which offscreen
  rendering never uses.
"""

from __future__ import annotations

import os
import sys
from types import ModuleType

_INSTALL = (
    "pyrender is not installed or cannot start: run `make setup` (it installs pyrender==0.1.45 with --no-deps, "
    "PyOpenGL==3.1.10 and Debian's libosmesa6), or `pip install --no-deps pyrender==0.1.45 && "
    "pip install PyOpenGL==3.1.10 pyglet trimesh networkx freetype-py six` and `apt-get install libosmesa6`"
)


def import_pyrender() -> ModuleType:
    if "PYOPENGL_PLATFORM" not in os.environ and not os.environ.get("DISPLAY"):
        os.environ["PYOPENGL_PLATFORM"] = "osmesa"
    import numpy as np

    if not hasattr(np, "infty"):
        np.infty = np.inf  # type: ignore[attr-defined]
    try:
        import pyrender
    except Exception as e:  # ImportError, or OpenGL failing to find libOSMesa
        if not _raised_by_the_viewer(e):
            raise ImportError(f"{_INSTALL} ({type(e).__name__}: {e})") from e
        try:
            pyrender = _import_without_viewer(f"{type(e).__name__}: {e}")
        except Exception as e2:
            raise ImportError(f"{_INSTALL} ({type(e2).__name__}: {e2})") from e2
    return pyrender


def _raised_by_the_viewer(e: BaseException) -> bool:
    """Whether the import failed inside pyrender's viewer module or the pyglet it imports."""
    tb = e.__traceback__
    while tb is not None:
        name = tb.tb_frame.f_code.co_filename.replace(os.sep, "/")
        if name.endswith("pyrender/viewer.py") or "/pyglet/" in name:
            return True
        tb = tb.tb_next
    return False


def _import_without_viewer(why: str) -> ModuleType:
    """pyrender imported with ``pyrender.viewer`` stubbed: the offscreen renderer does not use it,
    and its ``Viewer`` raises ImportError with ``why`` (the viewer's own import error)."""
    for name in [m for m in sys.modules if m == "pyrender" or m.startswith("pyrender.")]:
        del sys.modules[name]

    class Viewer:
        def __init__(self, *args, **kwargs):
            raise ImportError(f"pyrender's interactive Viewer cannot start here: pyglet failed to import ({why})")

    stub = ModuleType("pyrender.viewer")
    stub.Viewer = Viewer  # type: ignore[attr-defined]
    sys.modules["pyrender.viewer"] = stub
    import pyrender

    return pyrender


def available() -> tuple[bool, str]:
    """(True, '') when an offscreen pyrender context can be created, else (False, reason)."""
    try:
        pr = import_pyrender()
        r = pr.OffscreenRenderer(4, 4)
        r.delete()
        return True, ""
    except Exception as e:
        return False, str(e).splitlines()[0]
