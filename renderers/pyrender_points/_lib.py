"""Lazy import of pyrender for offscreen rendering (OSMesa), with the two known fixes.

- ``PYOPENGL_PLATFORM`` defaults to ``osmesa`` when no display is set (needs Debian's
  ``libosmesa6``);
- numpy 2 removed ``np.infty``, which pyrender 0.1.45 still uses: it is aliased to ``np.inf``.
"""

from __future__ import annotations

import os
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
        raise ImportError(f"{_INSTALL} ({type(e).__name__}: {e})") from e
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
