"""Golden renders of the fixture scenes: the float64 twin's images at full quality, stored as
compressed .npz in ``fixtures/golden/``. Regenerate them all with

    python -m gdbench.refcheck.golden --regen

Regression tests compare the splat renderer with them using each scene's tolerances.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from gdbench.refcheck.scenes import FIXTURE_DIR, fixture_names, load_fixture

GOLDEN_DIR = FIXTURE_DIR.parent / "golden"


def golden_path(name: str) -> Path:
    return GOLDEN_DIR / f"{name}.npz"


GOLDEN_SPP = 256
"""Samples per pixel of the stored Mitsuba renders."""


def render_golden(name: str) -> dict[str, np.ndarray]:
    """The twin's rgb/alpha and, where the scene declares it, the high-setting Mitsuba render."""
    from renderers.splat.reference import rasterize_reference

    fx = load_fixture(name)
    c = fx.cameras
    args = dict(
        **fx.scene.render_args(), viewmats=c.viewmats, Ks=c.Ks, width=c.width, height=c.height, background=fx.background
    )
    out = rasterize_reference(**args, outputs=("rgb", "alpha"))
    gold = {"rgb": out.rgb.float().numpy(), "alpha": out.alpha.float().numpy()}
    if fx.skip_reason("mitsuba_ellipsoids") is None:
        from renderers.mitsuba.ellipsoids import rasterize as mi_rasterize

        gold["mitsuba_ellipsoids"] = mi_rasterize(**args, spp=GOLDEN_SPP).rgb.float().numpy()
    from gdbench.refcheck.compare import VOLUME_LADDERS

    for mode in ("analytic", "grid"):  # the exact volume at the harness's high setting
        if fx.skip_reason(f"mitsuba_volume_{mode}") is None:
            from renderers.mitsuba.volume import rasterize as vol_rasterize

            gold[f"mitsuba_volume_{mode}"] = (
                vol_rasterize(**args, mode=mode, **VOLUME_LADDERS[mode][0]).rgb.float().numpy()
            )
    return gold


def load_golden(name: str) -> dict[str, torch.Tensor]:
    path = golden_path(name)
    if not path.is_file():
        raise FileNotFoundError(
            f"no golden data for scene {name!r} at {path}; run `python -m gdbench.refcheck.golden --regen`"
        )
    with np.load(path) as z:
        return {k: torch.from_numpy(z[k]) for k in z.files}


def regen(names: list[str] | None = None) -> list[Path]:
    GOLDEN_DIR.mkdir(parents=True, exist_ok=True)
    paths = []
    for n in names or fixture_names():
        np.savez_compressed(golden_path(n), **render_golden(n))
        paths.append(golden_path(n))
        print(f"wrote {golden_path(n)}")
    return paths


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--regen", action="store_true", help="re-render and overwrite the golden files")
    ap.add_argument("--scene", nargs="*", help="only these scenes")
    args = ap.parse_args(argv)
    if not args.regen:
        ap.error("nothing to do: pass --regen")
    regen(args.scene)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
