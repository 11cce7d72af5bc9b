"""The system under test: a PyTorch 3D Gaussian splatting renderer.

Stages, one file each: ``project`` (EWA projection), ``bin_tiles`` (tile lists sorted by
depth), ``composite`` (front-to-back blending with a hand-written backward, wrapped in
``autograd``), ``rasterize`` (the entry point); ``settings`` holds the constants in one
object. ``reference`` is the slow dense float64 twin used as the test oracle and benchmark
baseline.
"""

from .rasterize import OUTPUTS, Prepared, RenderOutput, composite_features, normalised_features, prepare, rasterize
from .settings import RasterSettings

__all__ = [
    "OUTPUTS",
    "Prepared",
    "RasterSettings",
    "RenderOutput",
    "composite_features",
    "normalised_features",
    "prepare",
    "rasterize",
]
