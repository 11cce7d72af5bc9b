"""The janus setting's description on the 64 px model (gdbench/experiments/world64_janus.py): the
shares by arm and reader, the prompts' table and the sheets chosen by rule, against counts made by
hand on made-up rows; and the committed labels read back with their sheets."""

from pathlib import Path

import pytest

from gdbench.experiments.world64_janus import by_arm, by_prompt, sheets_by_rule

ROOT = Path(__file__).resolve().parents[1]


def _row(caption, arm, seed, consensus, judge, psnr, gaussians=1000):
    return {"caption": caption, "block": arm, "seed": f"seed{seed}", "rater1": consensus or "blob",
            "rater2": consensus or "fine", "consensus": consensus, "six_views": judge, "run_folder": judge,
            "gt_psnr": str(psnr), "gaussians": str(gaussians), "judge": "j", "commit": "c"}  # fmt: skip


def test_shares_by_arm_and_the_sheets_by_rule():
    rows = [
        _row("a corgi", "gd", 0, "fine", "fine", 20.0), _row("a corgi", "gd", 1, "", "blob", 18.0),
        _row("a corgi", "gd-no-sn", 0, "front_everywhere", "front_everywhere", 16.0, 3000),
        _row("a corgi", "gd-no-sn", 1, "second_face", "blob", 14.0, 5000),
        _row("a sofa", "gd", 0, "blob", "blob", 10.0), _row("a sofa", "gd", 1, "blob", "blob", 12.0),
        _row("a sofa", "gd-no-sn", 0, "blob", "fine", 11.0), _row("a sofa", "gd-no-sn", 1, "blob", "blob", 13.0),
        _row("a duck", "gd", 0, "fine", "fine", 30.0), _row("a duck", "gd", 1, "fine", "fine", 30.0),
        _row("a duck", "gd-no-sn", 0, "fine", "fine", 30.0), _row("a duck", "gd-no-sn", 1, "fine", "fine", 30.0),
    ]  # fmt: skip
    arms = {(r["arm"], r["reader"]): r for r in by_arm(rows)}
    gd = arms[("gd", "consensus")]  # 5 of gd's 6 have a consensus: fine, blob, blob, fine, fine
    assert gd["results"] == 5 and gd["fine"] == pytest.approx(3 / 5) and gd["blob"] == pytest.approx(2 / 5)
    assert arms[("gd", "rater2")]["fine"] == pytest.approx(4 / 6)  # the one without consensus: rater2 said fine
    ns = arms[("gd-no-sn", "consensus")]
    assert ns["janus"] == pytest.approx(2 / 6) and ns["second_face"] == pytest.approx(1 / 6)
    assert ns["gt_psnr"] == pytest.approx((16 + 14 + 11 + 13 + 30 + 30) / 6)
    assert ns["gaussians"] == pytest.approx((3000 + 5000 + 4000) / 6)
    assert arms[("gd-no-sn", "run_folder")]["blob"] == pytest.approx(2 / 6)
    prompts = {p["prompt"]: p for p in by_prompt(rows)}
    assert prompts["a corgi"]["gt_psnr"] == pytest.approx(17.0) and prompts["a corgi"]["consensus_gd"] == "fine -"
    assert sheets_by_rule(list(prompts.values())) == {"highest": "a duck", "median": "a corgi", "lowest": "a sofa"}


def test_without_run_folders_the_six_views_are_read_alone():
    """No --runs: the run-folder reader has no rows, the prompts' table names the six views' labels,
    and no sheet is chosen by a GT PSNR that was never read."""
    cells = (("gd", 0, "fine"), ("gd", 1, "blob"), ("gd-no-sn", 0, "front_everywhere"), ("gd-no-sn", 1, "fine"))
    rows = [_row("a corgi", arm, k, "fine", lab, "") for arm, k, lab in cells]
    for r in rows:
        r["run_folder"], r["gaussians"] = "", ""
    arms = {(r["arm"], r["reader"]): r for r in by_arm(rows)}
    assert ("gd", "run_folder") not in arms and arms[("gd", "six_views")]["blob"] == pytest.approx(1 / 2)
    assert arms[("gd-no-sn", "six_views")]["janus"] == pytest.approx(1 / 2)
    assert arms[("gd", "six_views")]["gt_psnr"] is None
    prompts = by_prompt(rows)
    assert prompts[0]["judge_gd"] == "fine blob" and prompts[0]["judge_gd-no-sn"] == "front_everywhere fine"
    assert sheets_by_rule(prompts) == {}


def test_the_committed_labels_read_back_with_their_sheets():
    """Every labelled number is a row on a committed sheet, both passes label all 124, and the
    consensus is where they agree."""
    from gdbench.experiments.world64_janus import labelled_results

    results = labelled_results(ROOT)
    assert len(results) == 124 and len({r.caption for r in results}) == 31
    assert all(set(r.labels) == {"rater1", "rater2"} for r in results)
    agree = [r for r in results if r.labels["rater1"] == r.labels["rater2"]]
    assert [r.consensus for r in agree] == [r.labels["rater1"] for r in agree]
    assert all(r.consensus is None for r in results if r not in agree)
    assert all(r.views.shape[0] == 6 and r.views.std() > 5 for r in results)  # six drawn views, not blank
