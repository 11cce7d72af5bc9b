"""The judge's fresh set (gdbench/experiments/judge_fresh.py, docs/judge_fresh.md): the block and arm
read from a run folder, the agreement rows against hand-counted oracles, and the committed tables
recomputed from the committed sheets and labels."""

import csv
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def test_block_and_arm_from_the_run_folder():
    from gdbench.experiments.judge_fresh import block_and_arm

    run = "/work/runs/judge-fresh/learned-janus/cells/janus/a_corgi/gd-no-sn/seed5"
    assert block_and_arm(run) == ("learned-janus", "gd-no-sn")
    assert block_and_arm("/x/empirical-janus/cells/janus/a_sofa/gd/seed5") == ("empirical-janus", "gd")
    assert block_and_arm("/x/other/cells/easy/a_sofa/gd/seed5") == ("", "gd")


def _row(consensus, six, block="learned-janus"):
    return {"consensus": consensus, "rater1": consensus, "rater2": consensus, "six_views": six, "run_folder": "",
            "block": block, "commit": "c", "judge": "j"}  # fmt: skip


def test_agreement_rows_against_hand_counts():
    """Ten results, six agreeing over the four classes. Janus split: truth 4 of 10 Janus, judged 5;
    they agree on 9 (p_o 0.9, p_e = 0.4 * 0.5 + 0.6 * 0.5 = 0.5, kappa 0.8). Two of the five
    consensus-fine results are warned: 0.4 > 0.1, so fine_warned fails."""
    from gdbench.experiments.judge_fresh import agreement_rows

    truth = ["front_everywhere"] * 3 + ["second_face"] + ["blob"] + ["fine"] * 5
    judged = ["front_everywhere"] * 3 + ["front_everywhere"] + ["fine"] + ["fine"] * 3 + ["blob", "second_face"]
    rows = agreement_rows([_row(t, j) for t, j in zip(truth, judged)])
    top = next(r for r in rows if r["mode"] == "six views" and r["truth"] == "consensus" and r["block"] == "all")
    assert top["n"] == 10 and top["agree"] == pytest.approx(0.6)
    assert top["kappa_janus"] == pytest.approx(0.8)
    assert top["fine_warned"] == pytest.approx(0.4) and "fine_warned" in top["fails"].split(";")
    assert top["recall_front_everywhere"] == 1.0 and top["recall_blob"] == 0.0 and top["recall_fine"] == 0.6
    assert top["second_face_judged"] == 1
    assert not any(r["mode"] == "run folder" for r in rows)  # no run-folder labels: no rows
    assert rows[-1]["mode"] == "rater2 against rater1" and rows[-1]["kappa_four"] == pytest.approx(1.0)


def _read(path):
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


SETS = ("fresh", "fresh2", "fresh3", "fresh4", "fresh5", "fresh6", "fresh7", "fresh8", "fresh9")


def _judged_or_skip(name):
    folder = ROOT / "docs" / "results" / "judge" / name
    if not (folder / "judged.csv").is_file():
        pytest.skip(f"the fresh set {name} is not judged yet")
    return folder, _read(folder / "judged.csv")


@pytest.mark.parametrize("name", SETS)
def test_the_committed_agreement_recomputes_from_the_committed_judgements(name):
    """agreement.csv is what agreement_rows makes of judged.csv, and judged.csv's raters' columns
    are the committed labels of the key's results."""
    from gdbench.experiments.judge_fresh import agreement_rows

    folder, judged = _judged_or_skip(name)
    readings = [folder, *(d for d in sorted(folder.iterdir()) if (d / "judged.csv").is_file())]  # other judges'
    for where in readings:
        stored = _read(where / "agreement.csv")
        again = agreement_rows(_read(where / "judged.csv"))
        assert len(again) == len(stored)
        for a, s in zip(again, stored):
            assert (a["mode"], a["truth"], a["block"], a["n"]) == (s["mode"], s["truth"], s["block"], int(s["n"]))
            assert a["kappa_janus"] == pytest.approx(float(s["kappa_janus"]), abs=1e-9)
    key = json.loads((folder / f"{name}_key.json").read_text())
    assert len(judged) == len(key) >= 120
    labels = {p: {r["run_id"]: r["label"] for r in _read(ROOT / "fixtures" / "labels" / f"{name}_rater{p}.csv")}
              for p in (1, 2)}  # fmt: skip
    for r in judged:
        assert (r["rater1"], r["rater2"]) == (labels[1][r["run_id"]], labels[2][r["run_id"]])
        assert r["consensus"] == (r["rater1"] if r["rater1"] == r["rater2"] else "")


@pytest.mark.slow
@pytest.mark.parametrize("name", SETS)
def test_the_six_view_labels_recompute_from_the_committed_sheets(name):
    """The shipped judge reads the committed sheets as judged.csv says, when it is the judge the
    table names (a retrained judge is read again, not compared)."""
    from gdbench.experiments.judge_fresh import judge_fresh
    from gdbench.metrics.judge.judge import judge_version

    _, judged = _judged_or_skip(name)
    if judged[0]["judge"] != judge_version():
        pytest.skip(f"judged.csv names the judge {judged[0]['judge']}, the shipped one is {judge_version()}")
    now = judge_fresh(ROOT, which=name)
    assert [r["six_views"] for r in now] == [r["six_views"] for r in judged]


def test_the_fresh_sets_read_back_whole_with_both_passes():
    """Every committed fresh set's sheets give one result per key entry, in the key's run ids, each
    labelled by both passes (the label files name exactly the key's results)."""
    from gdbench.metrics.judge.sheets import FRESH_SETS, fresh_results

    for name, fs in FRESH_SETS.items():
        if not (ROOT / fs.labels["rater2"]).is_file():
            continue
        key = json.loads((ROOT / fs.key).read_text())
        got = fresh_results(ROOT, name)
        assert sorted(r.run_id for r in got) == sorted(k["run_id"] for k in key.values())
        assert all(set(r.labels) == {"rater1", "rater2"} for r in got)
        assert all(r.batch == name and r.views.shape[0] == 6 and r.views.std() > 5 for r in got)


def test_the_pooled_diagnostic_refits_the_head_on_both_sets_labels():
    """``judge_fresh --pooled``: the head refitted over v3's and the fresh set's consensus results
    (counted here from the label files themselves), by source; in sample it cannot do worse than
    leave-kind-out on the results it was fitted on. The regression is refitted (the shipped trees
    take 22 fits of five forests over 200 numbers: minutes that the counts do not need)."""
    import csv

    from gdbench.experiments.judge_fresh import LABELS, pooled

    def consensus(paths):
        a, b = ({r["run_id"]: r["label"] for r in csv.DictReader(open(p))} for p in paths)
        return sum(a[k] == b[k] for k in a if k in b)

    fresh = consensus([LABELS["rater1"], LABELS["rater2"]])
    rows = {(r["fit"], r["source"]): r for r in pooled(head="linear")}
    n_all = rows[("in sample, pooled", "all")]["n"]
    assert n_all == rows[("in sample, pooled", "v3")]["n"] + fresh
    blocks = ("learned-janus", "learned-uniform", "empirical-janus")
    assert sum(rows[("in sample, pooled", b)]["n"] for b in blocks) == fresh
    assert rows[("in sample, pooled", "all")]["agree"] >= rows[("leave-kind-out, pooled", "all")]["agree"]


def test_the_reading_refuses_bad_arguments_in_one_line(tmp_path, monkeypatch, capsys):
    """Another judge without --out (it would replace the shipped judge's committed reading), a
    folder that holds no judge, and a registered set whose sheets are not committed yet are each a
    one-line error naming the argument; nothing is written."""
    from gdbench.experiments.judge_fresh import main
    from gdbench.metrics.judge.judge import WEIGHTS
    from gdbench.metrics.judge.sheets import FRESH_SETS, FreshSet

    cases = [
        (["--set", "fresh", "--judge", str(WEIGHTS)], "--judge: give --out too"),
        (["--set", "fresh", "--judge", str(tmp_path), "--out", str(tmp_path)], "missing eye.safetensors, head.json"),
    ]
    monkeypatch.setitem(FRESH_SETS, "later", FreshSet("later", tmp_path / "later", "docs/judge_later.md"))
    cases.append((["--set", "later"], "--set later: "))
    for argv, message in cases:
        with pytest.raises(SystemExit) as e:
            main(argv)
        assert e.value.code == 2 and message in capsys.readouterr().err
    assert not any(tmp_path.iterdir())
