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


def test_the_blind_readings_join_their_cells_through_the_key(tmp_path):
    """Sheet numbers become run ids through the key; each rater's counts are the rows' own (counted
    by hand here), and a number the key lacks is an error naming the file."""
    import json

    from gdbench.experiments.prior64 import eye_readings, eye_summary

    rows = [{"prompt": "a corgi", "held_out": False, "run_shipped": "c0", "run_world64": "c1"},
            {"prompt": "a blue duck", "held_out": True, "run_shipped": "d0", "run_world64": "d1"}]  # fmt: skip
    duck = [{"run_id": "y0"}, {"run_id": "y1"}]
    key = {"1": {"run_id": "c1"}, "2": {"run_id": "c0"}, "3": {"run_id": "d0"}, "4": {"run_id": "d1"},
           "5": {"run_id": "y0"}, "6": {"run_id": "y1"}}  # fmt: skip
    (tmp_path / "key.json").write_text(json.dumps(key))
    labels = {"rater1": ["yes,yes", "yes,no", "no,no", "yes,yes", "yes,no", "yes,yes"],
              "rater2": ["no,no", "yes,yes", "yes,no", "no,no", "yes,yes", "yes,yes"]}  # fmt: skip
    for rater, rs in labels.items():
        lines = ["number,reads_as_caption,features_drawn"] + [f"{i + 1},{v}" for i, v in enumerate(rs)]
        (tmp_path / f"{rater}.csv").write_text("\n".join(lines) + "\n")
    eye = eye_readings(tmp_path)
    assert eye["c1"] == {"rater1": ("yes", "yes"), "rater2": ("no", "no")}
    s = eye_summary(rows, duck, eye)
    assert s["rater1"] == {"reads_shipped": 1, "reads_world64": 2, "held_out_reads_shipped": 0,
                           "held_out_reads_world64": 1, "duck_features_drawn": 1, "duck_seeds": 2}  # fmt: skip
    assert s["rater2"] == {"reads_shipped": 2, "reads_world64": 0, "held_out_reads_shipped": 1,
                           "held_out_reads_world64": 0, "duck_features_drawn": 2, "duck_seeds": 2}  # fmt: skip
    (tmp_path / "rater3.csv").write_text("number,reads_as_caption,features_drawn\n9,yes,yes\n")
    with pytest.raises(ValueError, match=r"rater3\.csv labels sheet number 9"):
        eye_readings(tmp_path)
