"""Figures written by commands: a headless pyplot and one way to save (lazy matplotlib import)."""

from __future__ import annotations

from pathlib import Path


def pyplot():
    """matplotlib.pyplot on the Agg backend (no display needed); imported on first use."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save(fig, path: str | Path, *, dpi: int = 110) -> Path:
    """Lay out (tight, unless the figure has its own layout engine), write (creating the
    folder) and close ``fig``; returns the path."""
    path = Path(path)
    if fig.get_layout_engine() is None:
        fig.tight_layout()
    from gdbench.core.io import atomic_path

    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi, format=path.suffix[1:] or None)
    finally:
        pyplot().close(fig)
    return path
