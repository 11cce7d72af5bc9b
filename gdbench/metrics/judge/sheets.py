"""The committed label sheets read back as results: each numbered row's six views, the asset's row
and the raters' labels, so that the judge can be judged on every labelled result whose images
survive (docs/results/v3/sheets: batches C-F, 620 results).

A sheet (``gdbench.metrics.label_sheets``) is a column of rows of height h: the asset's views at
azimuths 0, 60, ..., 300 on top, then one result a row at the same azimuths, behind a 70 px margin
with the row's name. A batch's key (``<batch>_key.json``: number -> run id, run folder, caption)
numbers the results caption by caption in sorted order, sheet by sheet, row by row, which is how
the rows are matched to their numbers here (checked against each sheet's row count).
"""

from __future__ import annotations

import csv
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

MARGIN = 70
"""Pixels left of the views, where the row's name is written."""
SHEET_AZIMUTHS = (0.0, 60.0, 120.0, 180.0, 240.0, 300.0)
"""The camera azimuths of a sheet's six columns (the run turntable's frames 0, 6, ..., 30)."""
SHEET_ELEVATION = 15.0
"""The sheets' (and the run turntables') camera elevation, degrees."""


@dataclass
class SheetResult:
    """One labelled result as its sheet shows it."""

    batch: str
    number: int
    run_id: str
    run: str
    """The run folder the key names (it says arm and seed: read after judging, never by the judge)."""
    caption: str
    views: np.ndarray
    """[6, h, h, 3] uint8: the result at ``SHEET_AZIMUTHS``."""
    labels: dict[str, str] = field(default_factory=dict)
    """Rater name -> label."""

    @property
    def consensus(self) -> str | None:
        """The label every rater gives, or None where they differ (or none labelled it)."""
        got = set(self.labels.values())
        return got.pop() if len(got) == 1 else None


def split_sheet(image: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """(the asset's row [6, h, h, 3], the result rows [[6, h, h, 3], ...]) of one sheet image."""
    height, width = image.shape[:2]
    h = (width - MARGIN) // 6
    if h < 8 or (width - MARGIN) % 6 or height % h:
        raise ValueError(f"sheet: expected rows of six square views behind a {MARGIN} px margin, got {width}x{height}")
    rows = []
    for r in range(height // h):
        row = image[r * h : (r + 1) * h, MARGIN : MARGIN + 6 * h, :3]
        rows.append(np.stack([row[:, i * h : (i + 1) * h] for i in range(6)]))
    return rows[0], rows[1:]


def read_batch(folder: Path, key_path: Path, batch: str | None = None) -> list[SheetResult]:
    """Every result of one batch's sheets, in the key's numbering; the batch is named ``batch``
    (default: the folder's name, as v3's C-F)."""
    from PIL import Image

    folder, key = Path(folder), json.loads(Path(key_path).read_text())
    numbers = sorted(key, key=int)
    out: list[SheetResult] = []
    for caption in sorted({key[n]["caption"] for n in numbers}):
        mine = [n for n in numbers if key[n]["caption"] == caption]
        pattern = re.compile(rf"sheet_{re.escape(caption.replace(' ', '_'))}_(\d+)\.\w+")
        sheets = sorted((int(m.group(1)), p) for p in folder.iterdir() if (m := pattern.fullmatch(p.name)))
        rows = [row for _, p in sheets for row in split_sheet(np.asarray(Image.open(p).convert("RGB")))[1]]
        if len(rows) != len(mine):
            raise ValueError(f"sheets: {folder} shows {len(rows)} results of {caption!r}; its key numbers {len(mine)}")
        for n, views in zip(mine, rows):
            k = key[n]
            out.append(SheetResult(batch or folder.name, int(n), k["run_id"], k["run"], caption, views))
    return out


def attach_labels(results: list[SheetResult], labels: dict[str, Path]) -> list[SheetResult]:
    """Each rater's labels (name -> labels CSV by run id and batch, as fixtures/labels/v3_rater*.csv)
    on the results (rows of batches not read are passed over); a run id that a read batch does not
    hold is a one-line error."""
    from gdbench.metrics.agreement import LABELS

    index = {(r.batch, r.run_id): r for r in results}
    batches = {r.batch for r in results}
    for name, path in labels.items():
        reader = csv.DictReader(open(path))
        if not {"batch", "run_id", "label"} <= set(reader.fieldnames or ()):
            raise ValueError(f"labels: {path} needs the columns batch, run_id and label; it has {reader.fieldnames}")
        for i, row in enumerate(reader, start=2):
            if row["label"] not in LABELS:
                raise ValueError(f"labels: {path} line {i} has label {row['label']!r}; expected one of {LABELS}")
            key = (row["batch"], row["run_id"])
            if key[0] not in batches:
                continue  # a batch not read
            if key not in index:
                raise ValueError(
                    f"labels: {path} line {i} names run id {key[1]!r} of batch {key[0]!r}, which no sheet shows"
                )
            index[key].labels[name] = row["label"]
    return results


V3_SHEETS = Path("docs/results/v3/sheets")
V3_LABELS = {"rater1": Path("fixtures/labels/v3_rater1.csv"), "rater2": Path("fixtures/labels/v3_rater2.csv")}


def v3_results(root: Path = Path("."), batches: tuple[str, ...] = ("C", "D", "E", "F")) -> list[SheetResult]:
    """v3's 620 labelled results from the committed sheets, with both passes' labels."""
    root = Path(root)
    results = [r for b in batches for r in read_batch(root / V3_SHEETS / b, root / V3_SHEETS / f"{b}_key.json")]
    return attach_labels(results, {k: root / v for k, v in V3_LABELS.items()})


@dataclass(frozen=True)
class FreshSet:
    """A registered fresh set of the judge: its committed sheets (WebP), key and both passes' labels."""

    name: str
    """The labels' batch column, and the key's name (``<name>_key.json``)."""
    folder: Path
    """sheets/, the key and the set's tables."""
    registration: str
    """The document that registered it."""

    @property
    def labels(self) -> dict[str, Path]:
        return {f"rater{p}": Path(f"fixtures/labels/{self.name}_rater{p}.csv") for p in (1, 2)}

    @property
    def key(self) -> Path:
        return self.folder / f"{self.name}_key.json"


FRESH_SETS = {
    "fresh": FreshSet("fresh", Path("docs/results/judge/fresh"), "docs/judge_fresh.md"),
    "fresh2": FreshSet("fresh2", Path("docs/results/judge/fresh2"), "docs/judge_fresh2.md"),
    "fresh3": FreshSet("fresh3", Path("docs/results/judge/fresh3"), "docs/judge_fresh3.md"),
    "fresh4": FreshSet("fresh4", Path("docs/results/judge/fresh4"), "docs/judge_fresh4.md"),
    "fresh5": FreshSet("fresh5", Path("docs/results/judge/fresh5"), "docs/judge_fresh5.md"),
    "fresh6": FreshSet("fresh6", Path("docs/results/judge/fresh6"), "docs/judge_fresh6.md"),
    "fresh7": FreshSet("fresh7", Path("docs/results/judge/fresh7"), "docs/judge_fresh7.md"),
    "fresh8": FreshSet("fresh8", Path("docs/results/judge/fresh8"), "docs/judge_fresh8.md"),
    "fresh9": FreshSet("fresh9", Path("docs/results/judge/fresh9"), "docs/judge_fresh9.md"),
}
"""The judge's fresh sets: the first (spent: the second and third judges are fitted on it), the
second and the third (spent: read by the second and third judges; the fourth judge is fitted on all
three), the fourth and the fifth (spent: read by the fourth and fifth judges; the sixth is fitted on
all five), the sixth (spent: read by the sixth judge; the seventh is fitted on all six), the
seventh and the eighth (spent: read by the seventh judge; the eighth is fitted on all eight) and
the ninth (registered 2026-12-06, read by the eighth judge, the seventh beside it)."""


def fresh_results(root: Path = Path("."), which: str = "fresh") -> list[SheetResult]:
    """A fresh set's results (default: the first) from the committed sheets, with both passes' labels."""
    root, fs = Path(root), FRESH_SETS[which]
    results = read_batch(root / fs.folder / "sheets", root / fs.key, batch=fs.name)
    return attach_labels(results, {k: root / v for k, v in fs.labels.items()})


def labelled_results(root: Path = Path("."), sets: tuple[str, ...] = ()) -> tuple[list[SheetResult], list[str]]:
    """(results, their sources): v3's committed results (``v3_results``), then each fresh set of
    ``sets`` in order (``fresh_results``); a result's source is its fresh set's name, or "v3"."""
    results = v3_results(root) + [r for which in sets for r in fresh_results(root, which)]
    return results, [r.batch if r.batch in sets else "v3" for r in results]
