"""The view metrics' calibration table of docs/scoring.md: every 3D failure fixture of every
asset (``gdbench/metrics/failures3d.py``) scored by ``score_views``, one row per (asset,
fixture), and a sheet of the first asset's fixtures.

    python scripts/calibrate_views.py --out docs/results/calibration \
        --sheet docs/figures/failure_fixtures.png

Every row records the commit of the code that scored it. About 15 s per asset once its banks
are cached (the first call renders each variant's bank: a minute per asset).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

METRICS = (
    "front_everywhere_rate", "multi_face_rate", "blob_rate", "janus_rate", "featureless_rate", "instance_consistency",
    "majority_variant", "floaters", "turned_deg", "outline_side", "back_share",
)  # fmt: skip


def main(argv: list[str] | None = None) -> int:
    from gdbench.assets.library import ASSETS
    from gdbench.metrics.failures3d import KINDS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, required=True, help="folder for views.csv")
    p.add_argument("--captions", nargs="+", default=sorted(ASSETS), help="assets (default: all six)")
    p.add_argument("--kinds", nargs="+", default=list(KINDS), choices=KINDS, help="fixtures (default: all)")
    p.add_argument("--sheet", type=Path, help="write a PNG of the first caption's fixtures here")
    a = p.parse_args(argv)
    unknown = sorted(set(a.captions) - set(ASSETS))
    if unknown:
        p.error(f"--captions: unknown {unknown}; known: {sorted(ASSETS)}")

    from gdbench.assets.library import has_front
    from gdbench.core.io import write_csv
    from gdbench.core.provenance import code_commit
    from gdbench.metrics.failures3d import failure_scene
    from gdbench.metrics.views import reference, render_turntable, result_class, score_views

    commit = code_commit()
    rows, sheet = [], {}
    for caption in a.captions:
        t0 = time.perf_counter()
        ref = reference(caption, variants=3)
        for kind in a.kinds:
            images, alpha = render_turntable(failure_scene(caption, kind))
            s = score_views(images, alpha, ref, front=has_front(caption)).as_dict()
            row = {"caption": caption, "fixture": kind, **{m: s[m] for m in METRICS}, "class": result_class(s)}
            rows.append(row | {"commit": commit})
            if caption == a.captions[0]:
                sheet[kind] = images
        print(f"{caption}: {len(a.kinds)} fixtures in {time.perf_counter() - t0:.0f} s", flush=True)
    path = write_csv(rows, a.out / "views.csv")
    print(f"wrote {path}")
    if a.sheet:
        _sheet(sheet, a.captions[0], a.sheet)
        print(f"wrote {a.sheet}")
    return 0


def _sheet(views: dict, caption: str, path: Path) -> None:
    from gdbench.core.plotting import pyplot, save

    plt = pyplot()
    frames = (0, 6, 9, 18, 27)  # azimuths 0, 60, 90, 180, 270
    fig, axs = plt.subplots(len(views), len(frames), figsize=(1.3 * len(frames), 1.35 * len(views)))
    for r, (kind, images) in enumerate(views.items()):
        for c, f in enumerate(frames):
            ax = axs[r, c]
            ax.imshow(images[f].clamp(0, 1).numpy())
            ax.set_xticks([])
            ax.set_yticks([])
            if r == 0:
                ax.set_title(f"azimuth {10 * f}", fontsize=7)
        axs[r, 0].set_ylabel(kind, fontsize=7)
    fig.suptitle(f"3D failure fixtures of '{caption}' (Gaussian scenes)", fontsize=8)
    save(fig, path)


if __name__ == "__main__":
    raise SystemExit(main())
