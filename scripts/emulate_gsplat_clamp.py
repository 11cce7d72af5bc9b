"""gdbench's command line with every render emulating the gsplat backend's clamp on the CPU: the
C++ compositor at alpha_max 0.999 on opacities capped at 0.99 with a straight-through gradient
(renderers/splat/gsplat_backend.py's cap_opacities), as the backend renders on CUDA. Used for the
paired check in docs/renderer.md ("On a GPU"):

    python scripts/emulate_gsplat_clamp.py generate "a yellow duck" --seed 0 --out runs/cap_0
"""

import sys

import renderers.splat as splat
from renderers.splat.gsplat_backend import cap_opacities

_rasterize = splat.rasterize


def capped(means, quats, scales, opacities, *args, **kwargs):
    if "settings" not in kwargs and kwargs.get("alpha_max", 0.99) == 0.99:
        opacities = cap_opacities(opacities, 0.99)
        kwargs["alpha_max"] = 0.999
    return _rasterize(means, quats, scales, opacities, *args, **kwargs)


if __name__ == "__main__":
    splat.rasterize = capped  # gdbench imports rasterize inside its functions: every render sees this
    from gdbench.app.cli import program

    sys.argv = ["gdbench", *sys.argv[1:]]
    program()
