"""The 64 px model's text-to-3D table (gdbench/experiments/prior64.py) read from two sweeps'
cells.csv: the gains are the rows' differences, the median gain against the 1 dB target is the
median of those (checked against statistics.median on hand-made rows), held-out captions are
marked, and a sweep without cells.csv is named."""

import csv
import statistics

import pytest

from gdbench.experiments.prior64 import main, read_cells, summary, table_rows


def _sweep(folder, rows):
    folder.mkdir(parents=True)
    with open(folder / "cells.csv", "w", newline="") as f:
        w = csv.DictWriter(f, ["prompt", "seed", "gt_psnr", "gaussians", "judge_label", "run_id", "train_commit"])
        w.writeheader()
        for prompt, seed, psnr in rows:
            w.writerow({"prompt": prompt, "seed": seed, "gt_psnr": psnr, "gaussians": 1000, "judge_label": "fine",
                        "run_id": f"{prompt}-{seed}", "train_commit": "abc"})  # fmt: skip


def test_the_table_reads_both_sweeps_and_the_median_gain(tmp_path):
    old = [("a corgi", 0, 22.0), ("a blue duck", 0, 20.0), ("a sofa", 0, 24.0), ("a penguin", 0, "")]
    new = [("a corgi", 0, 23.5), ("a blue duck", 0, 20.5), ("a sofa", 0, 23.0), ("a penguin", 0, 21.0),
           ("a hamburger", 0, 25.0)]  # fmt: skip
    _sweep(tmp_path / "runs" / "shipped", old)
    _sweep(tmp_path / "runs" / "world64", new)
    _sweep(tmp_path / "runs" / "duck", [("a yellow duck", s, 24.0 + s) for s in range(4)])
    rows = table_rows(read_cells(tmp_path / "runs" / "shipped"), read_cells(tmp_path / "runs" / "world64"),
                      ("a blue duck",))  # fmt: skip
    assert [r["prompt"] for r in rows] == ["a blue duck", "a corgi", "a penguin", "a sofa"]  # both sweeps, sorted
    gains = {r["prompt"]: r["psnr_gain"] for r in rows}
    assert gains == {"a blue duck": 0.5, "a corgi": 1.5, "a penguin": None, "a sofa": -1.0}
    assert [r["held_out"] for r in rows] == [True, False, False, False]
    s = summary(rows)
    # the target is a difference of medians over the captions both sweeps scored
    assert s["median_gain"] == statistics.median([23.5, 20.5, 23.0]) - statistics.median([22.0, 20.0, 24.0])
    assert s["median_of_gains"] == statistics.median([0.5, 1.5, -1.0]) and s["captions"] == 3
    assert s["missing"] == 35 and not s["gain_meets_target"] and s["captions_gaining"] == 2
    assert main(["--runs", str(tmp_path / "runs"), "--to", str(tmp_path / "out"), "--held-out", "a blue duck",
                 "--model", "uniform"]) == 0  # fmt: skip
    import hashlib
    import json

    from gdbench.priors.learned.prior import model_path

    ident = json.loads((tmp_path / "out" / "model.json").read_text())
    assert ident["sha256"] == hashlib.sha256(model_path("uniform").read_bytes()).hexdigest()
    md = (tmp_path / "out" / "table.md").read_text()
    assert "+1.00 dB (target +1.0 over all 38: not met, 35 captions missing)" in md and "a blue duck (held out)" in md
    assert len(list(csv.DictReader(open(tmp_path / "out" / "duck.csv")))) == 4
    with pytest.raises(FileNotFoundError, match=r"no cells\.csv in"):
        read_cells(tmp_path / "nothing")
