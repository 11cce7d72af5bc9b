"""Renderer backends for gdbench, one sub-package each, with the same call shape.

This package is the lowest layer: pure functions over tensors. It never imports
``gdbench``. Heavy backends (Mitsuba, pyrender, gsplat) import their library lazily.
"""
