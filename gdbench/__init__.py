"""gdbench: a reference testbed for text-to-3D with 3D Gaussian splatting.

Importing this package is cheap: it loads torch and nothing heavy. Renderer backends,
priors and scoring tools are imported where they are used.
"""

from gdbench.core.camera import Cameras, SphericalPoses, look_at
from gdbench.core.scene import GaussianScene

__version__ = "0.1.0"
__all__ = ["Cameras", "GaussianScene", "SphericalPoses", "__version__", "look_at"]
