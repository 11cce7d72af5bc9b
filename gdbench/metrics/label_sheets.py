"""Blinded sheets for labelling results by eye (docs/scoring.md, "The Janus classes against
labels"): every run folder under the given sweep folders, grouped by prompt and shuffled within
it, drawn as one row of six turntable frames (azimuth 0, 60, ..., 300) under the asset's own
views at the same azimuths, each row named only by a number. The key from number to run id (and
arm) is written apart, to be read after labelling.

    python -m gdbench.metrics.label_sheets --runs SWEEP_DIR [...] --out DIR [--per-sheet 10] [--seed 0]
        [--key KEY.json]
    python -m gdbench.metrics.label_sheets --unblind LABELS.csv --key KEY.json --to FILE.csv

Writes DIR/sheet_<prompt>_<k>.png, the key (number -> run id, run folder; DIR/key.json unless
``--key`` puts it out of the raters' folder) and DIR/labels_template.csv (number, label) to fill
in. ``--unblind`` turns a rater's numbered labels (number, label, ...) into labels by run id
(run_id, label, caption, sheet_number and the rater's other columns), the form
``gdbench.metrics.agreement`` and the experiments read. (``scripts/label_sheets.py`` runs the
same, for the command lines recorded before.)
"""

from __future__ import annotations

import argparse
import csv
import json
import random
from pathlib import Path

import numpy as np

FRAMES = (0, 6, 12, 18, 24, 30)
"""Turntable frames (10 degrees apart) shown per result: azimuths 0, 60, ..., 300."""


def asset_row(caption: str, size: int) -> np.ndarray:
    """The asset's views at the sheet's azimuths, as the run turntables show them."""
    from gdbench.core.camera import SphericalPoses
    from gdbench.core.turntable import RUN_TURNTABLE, render_views_alpha
    from gdbench.metrics.failures3d import asset_scene

    # the run turntable's orbit at six of its 36 frames (azimuths 0, 60, ..., 300)
    sub = SphericalPoses.orbit(len(FRAMES), **RUN_TURNTABLE).cameras(size, size)
    rgb, _ = render_views_alpha(asset_scene(caption), sub, (1.0, 1.0, 1.0))
    return (rgb.clamp(0, 1).numpy() * 255).astype(np.uint8)


def main(argv=None) -> int:
    import imageio.v3 as iio
    from PIL import Image, ImageDraw

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, nargs="+")
    ap.add_argument("--out", type=Path)
    ap.add_argument("--per-sheet", type=int, default=10)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--key", type=Path, help="where the key goes (default: OUT/key.json), or is read (--unblind)")
    ap.add_argument("--unblind", type=Path, help="a rater's labels by sheet number, to turn into labels by run id")
    ap.add_argument("--to", type=Path, help="--unblind: the labels by run id go here")
    args = ap.parse_args(argv)
    if args.unblind is not None:
        if args.key is None or args.to is None:
            ap.error("--unblind needs --key (the sheets' key) and --to (the file to write)")
        print(f"{len(unblind(args.unblind, args.key, args.to))} labels by run id -> {args.to}")
        return 0
    if not args.runs or args.out is None or args.per_sheet < 1:
        ap.error("--runs and --out are required (and --per-sheet >= 1) to draw sheets")
    runs = []
    for root in args.runs:
        for p in sorted(root.rglob("run.json")):
            if (p.parent / "turntable.gif").is_file():
                info = json.loads(p.read_text())
                runs.append({"run_id": info["run_id"], "run": str(p.parent), "caption": info.get("caption") or ""})
    random.Random(args.seed).shuffle(runs)
    args.out.mkdir(parents=True, exist_ok=True)
    key, number = {}, 0
    for caption in sorted({r["caption"] for r in runs}):
        mine = [r for r in runs if r["caption"] == caption]
        for k in range(0, len(mine), args.per_sheet):
            rows = []
            first = iio.imread(Path(mine[0]["run"]) / "turntable.gif")
            size = first.shape[1]
            rows.append(("asset", np.concatenate(list(asset_row(caption, size)), axis=1)))
            for r in mine[k : k + args.per_sheet]:
                number += 1
                key[number] = r
                frames = iio.imread(Path(r["run"]) / "turntable.gif")
                rows.append((str(number), np.concatenate([frames[i][..., :3] for i in FRAMES], axis=1)))
            pad = 70
            h, w = rows[0][1].shape[:2]
            sheet = Image.new("RGB", (w + pad, h * len(rows)), "white")
            draw = ImageDraw.Draw(sheet)
            for i, (name, img) in enumerate(rows):
                sheet.paste(Image.fromarray(img), (pad, i * h))
                draw.text((5, i * h + h // 2 - 5), name, fill="black")
            sheet.save(args.out / f"sheet_{caption.replace(' ', '_')}_{k // args.per_sheet}.png")
    key_path = args.key or args.out / "key.json"
    key_path.parent.mkdir(parents=True, exist_ok=True)
    key_path.write_text(json.dumps(key, indent=1))
    with open(args.out / "labels_template.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(["number", "label"])
        for n in key:
            w.writerow([n, ""])
    print(f"{number} results on sheets in {args.out}")
    return 0


def unblind(labels: Path, key: Path, to: Path) -> list[dict]:
    """A rater's labels by sheet number (``number``, ``label`` and any other columns) as labels by
    run id, through the sheets' ``key``; every number must be in the key, none twice, and every
    number of the key labelled."""
    from gdbench.core.io import write_csv
    from gdbench.metrics.agreement import LABELS

    keys = json.loads(Path(key).read_text())
    rows, seen = [], set()
    for r in csv.DictReader(open(labels)):
        n = str(r.get("number", "")).strip()
        if n not in keys or n in seen:
            raise ValueError(f"labels: number {n!r} of {labels} is {'twice' if n in seen else 'not in the key'}")
        if r.get("label", "").strip() not in LABELS:
            raise ValueError(f"labels: number {n} of {labels} has label {r.get('label')!r}; expected one of {LABELS}")
        seen.add(n)
        k = keys[n]
        rest = {c: v for c, v in r.items() if c not in ("number", "label")}
        rows.append(rest | {"run_id": k["run_id"], "label": r["label"].strip(), "caption": k["caption"],
                            "sheet_number": n})  # fmt: skip
    missing = sorted(set(keys) - seen, key=int)
    if missing:
        raise ValueError(f"labels: {labels} labels no result numbered {', '.join(missing[:10])}"
                         f"{' ...' * (len(missing) > 10)} ({len(missing)} of the key's {len(keys)})")  # fmt: skip
    write_csv(rows, to)
    return rows


if __name__ == "__main__":
    raise SystemExit(main())
