"""Turntable sheets of a sweep over the world set, one figure per family (kind), and the per-object
table of docs/training.md ("Text to 3D on the world set").

    python scripts/world_turntables.py --sweep runs/sweep_world_empirical --name empirical \
        --figures docs/figures --out docs/results/world

Reads each cell's turntable_sheet.png and scores (the sweep's cells.csv); writes
world_turntables_<name>_<kind>.png (each object's sheet under its caption, PSNR and failure
classes beside it) and text_to_3d_<name>.md (the table, with the cells' commits).
"""

from __future__ import annotations

import argparse
import csv
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def cells(sweep: Path) -> list[dict]:
    """The sweep's cells.csv rows with the folder of each cell's turntable."""
    rows = list(csv.DictReader(open(sweep / "cells.csv")))
    from gdbench.experiments.sweep import cell_name

    for r in rows:
        r["folder"] = sweep / "cells" / r["setting"] / cell_name(r["prompt"]) / r["preset"] / f"seed{r['seed']}"
    return rows


def label(r: dict) -> str:
    def f(k):
        return float(r[k]) if r.get(k) not in (None, "") else float("nan")

    return (f"GT PSNR {f('gt_psnr'):.1f} dB; second faces {f('multi_face_rate'):.2f}, featureless "
            f"{f('featureless_rate'):.2f}, floaters {f('floaters'):.3f}, turned {f('turned_deg'):.0f} deg")  # fmt: skip


def family_sheets(rows: list[dict], name: str, figures: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from gdbench.assets.library import PARTS

    out = []
    kinds = sorted({PARTS[r["prompt"]][0] for r in rows}, key=lambda k: [PARTS[r["prompt"]][0] for r in rows].index(k))
    for kind in kinds:
        mine = [r for r in rows if PARTS[r["prompt"]][0] == kind]
        fig, axes = plt.subplots(len(mine), 1, figsize=(7.7, 1.75 * len(mine)), squeeze=False)
        for ax, r in zip(axes[:, 0], mine):
            ax.imshow(plt.imread(r["folder"] / "turntable_sheet.png"))
            ax.set_title(f"{r['prompt']}: {label(r)}", fontsize=7)
            ax.axis("off")
        fig.tight_layout()
        path = figures / f"world_turntables_{name}_{kind.replace(' ', '_')}.png"
        fig.savefig(path, dpi=110)
        plt.close(fig)
        out.append(path)
    return out


def table(rows: list[dict], labels: dict[str, str] | None = None) -> str:
    """The per-object table; with ``labels`` (caption -> what a person saw) a last column "by eye"."""
    eye = " by eye |" if labels else ""
    lines = ["| object | GT PSNR dB | SSIM | second faces | featureless | floaters | turned deg | Gaussians |" + eye,
             "|---|---|---|---|---|---|---|---|" + "---|" * bool(labels)]  # fmt: skip

    def g(r, k, fmt):
        return format(float(r[k]), fmt) if r.get(k) not in (None, "") else "n/a"

    cols = (("gt_psnr", ".2f"), ("gt_ssim", ".3f"), ("multi_face_rate", ".2f"), ("featureless_rate", ".2f"),
            ("floaters", ".3f"), ("turned_deg", ".0f"), ("gaussians", ".0f"))  # fmt: skip
    for r in rows:
        tail = f" {labels.get(r['prompt'], 'n/a')} |" if labels else ""
        lines.append(f"| {r['prompt']} | " + " | ".join(g(r, k, fmt) for k, fmt in cols) + " |" + tail)
    return "\n".join(lines)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--sweep", type=Path, required=True, help="a sweep folder (its cells.csv)")
    p.add_argument("--name", required=True, help="the prior's name in the file names (empirical, learned)")
    p.add_argument("--figures", type=Path, default=Path("docs/figures"))
    p.add_argument("--out", type=Path, default=Path("docs/results/world"))
    p.add_argument("--labels", type=Path, help="a TSV of caption and what a person saw (labelled before the metrics)")
    a = p.parse_args(argv)
    if not (a.sweep / "cells.csv").is_file():
        p.error(f"--sweep: expected a finished sweep folder with cells.csv, got {a.sweep}")
    rows = cells(a.sweep)
    labels = None
    if a.labels is not None:
        if not a.labels.is_file():
            p.error(f"--labels: expected a TSV file of caption and label, got {a.labels}")
        labels = dict(line.split("\t", 1) for line in a.labels.read_text().splitlines() if "\t" in line)
        labels = {k: v.strip() for k, v in labels.items() if k != "caption"}
    a.figures.mkdir(parents=True, exist_ok=True)
    a.out.mkdir(parents=True, exist_ok=True)
    paths = family_sheets(rows, a.name, a.figures)
    commits = sorted({r["train_commit"] for r in rows} | {r["score_commit"] for r in rows})
    head = f"Cells trained and scored at {', '.join(commits)} ({len(rows)} cells, {a.sweep})."
    text = f"{head}\n\n{table(rows, labels)}\n"
    (a.out / f"text_to_3d_{a.name}.md").write_text(text)
    print(text)
    print("\n".join(str(q) for q in paths))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
