"""Lazy import of Mitsuba 3 with the LLVM variant.

Dr.Jit's LLVM backend needs a libLLVM it can load; Debian's ``libllvm19`` works (the LLVM 15
of Debian 12 crashes a render). When ``DRJIT_LIBLLVM_PATH`` is unset, known locations of
libLLVM 19 are tried. Note that ``mi.set_variant`` is process-global in Mitsuba; this module
is the only place gdbench sets it.
"""

from __future__ import annotations

import os
from pathlib import Path
from types import ModuleType

VARIANT = "llvm_ad_rgb"
_LLVM_CANDIDATES = (
    "/usr/lib/x86_64-linux-gnu/libLLVM-19.so",
    "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1",
    "/usr/lib/aarch64-linux-gnu/libLLVM-19.so",
    "/usr/lib/llvm-19/lib/libLLVM.so",
)
_HELP = (
    "Mitsuba's LLVM backend needs libLLVM 19: run `make setup` (as root it installs Debian's libllvm19) or "
    "`sudo apt-get install libllvm19`, and `pip install mitsuba==3.9.1 drjit==1.5.0`; set DRJIT_LIBLLVM_PATH "
    "to the library if it lives elsewhere"
)


def import_mitsuba() -> tuple[ModuleType, ModuleType]:
    """(mitsuba, drjit) with the ``llvm_ad_rgb`` variant set; ImportError naming what to install."""
    if "DRJIT_LIBLLVM_PATH" not in os.environ:
        for cand in _LLVM_CANDIDATES:
            if Path(cand).exists():
                os.environ["DRJIT_LIBLLVM_PATH"] = cand
                break
    try:
        import drjit as dr
        import mitsuba as mi

        if mi.variant() != VARIANT:
            mi.set_variant(VARIANT)
    except (ImportError, AttributeError, RuntimeError) as e:
        raise ImportError(f"{_HELP} ({type(e).__name__}: {str(e).splitlines()[0]})") from e
    return mi, dr


def available() -> tuple[bool, str]:
    try:
        import_mitsuba()
        return True, ""
    except ImportError as e:
        return False, str(e).splitlines()[0]


def mitsuba_cameras(viewmats, Ks, width: int, height: int) -> list[dict]:
    """Per camera of OpenCV world-to-camera ``viewmats`` [C, 4, 4] and ``Ks`` [C, 3, 3]:
    ``to_world`` [4, 4] (Mitsuba axes: x left, y up, z forward), the horizontal ``fov`` in degrees
    and the principal point offsets as fractions of the image size (Mitsuba's
    ``principal_point_offset_x/y``). ``gdbench.core.camera.Cameras.to_mitsuba`` is this function."""
    import torch

    cv_to_mi = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=torch.float64))
    c2w = torch.linalg.inv(viewmats.double()) @ cv_to_mi
    out = []
    for i in range(viewmats.shape[0]):
        K = Ks[i].double()
        out.append(
            {
                "to_world": c2w[i],
                "fov": float(torch.rad2deg(2 * torch.atan(0.5 * width / K[0, 0]))),
                "fov_axis": "x",
                "principal_point_offset_x": float((K[0, 2] - width / 2) / width),
                "principal_point_offset_y": float((K[1, 2] - height / 2) / height),
                "width": width,
                "height": height,
            }
        )
    return out


def sensor_dict(mi, cam: dict, spp: int) -> dict:
    """A Mitsuba perspective sensor from ``mitsuba_cameras`` entries (box filter)."""
    return {
        "type": "perspective",
        "fov": cam["fov"],
        "fov_axis": "x",
        "principal_point_offset_x": cam["principal_point_offset_x"],
        "principal_point_offset_y": cam["principal_point_offset_y"],
        "to_world": mi.ScalarTransform4f(cam["to_world"].double().numpy()),
        "near_clip": 0.01,
        "far_clip": 1000.0,
        "film": {"type": "hdrfilm", "width": cam["width"], "height": cam["height"], "pixel_format": "rgb",
                 "rfilter": {"type": "box"}},
        "sampler": {"type": "independent", "sample_count": spp},
    }  # fmt: skip
