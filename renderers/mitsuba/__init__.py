"""Mitsuba 3 / Dr.Jit references, built from the same Gaussians and cameras:

- ``ellipsoids``: the ``ellipsoids`` shape with the ``volprim_rf_basic`` integrator (ray-traced
  peak response per Gaussian, in ray-hit order), rgb and alpha, gradients through Dr.Jit's
  torch interop;
- ``volume``: exact emission-absorption rendering of the Gaussian mixture as a density field
  (grid or analytic), with a Python ray-marching integrator.

Mitsuba is imported lazily (``_lib.import_mitsuba``) and needs Dr.Jit's LLVM backend.
"""
