"""Agreement of the metric's result classes with labels made by eye (gdbench/metrics/agreement.py):
Cohen's kappa against its textbook examples, the confusion matrix against a count by hand, and
bad labels files as one-line errors."""

import json

import pytest

from gdbench.metrics.agreement import LABELS, agreement, cohen_kappa, confusion, main, read_labels


def test_cohen_kappa_matches_the_textbook_example():
    """50 items rated yes/no: 20 both yes, 15 both no, 5 and 10 disagreeing: p_o = 0.7,
    p_e = 0.5 * 0.6 + 0.5 * 0.4 = 0.5, kappa = 0.4 (Cohen 1960's form, as on Wikipedia)."""
    a = ["yes"] * 25 + ["no"] * 25
    b = ["yes"] * 20 + ["no"] * 5 + ["yes"] * 10 + ["no"] * 15
    assert cohen_kappa(a, b, ("yes", "no")) == pytest.approx(0.4)
    assert cohen_kappa(a, a, ("yes", "no")) == 1.0
    assert cohen_kappa(["fine"] * 4, ["fine"] * 4) == 1.0  # one class on both sides: perfect agreement
    with pytest.raises(ValueError, match="same results"):
        cohen_kappa(["fine"], [])


def test_confusion_counts_each_pair():
    truth = ["fine", "blob", "blob", "second_face"]
    pred = ["fine", "fine", "blob", "front_everywhere"]
    c = confusion(truth, pred)
    assert c["blob"]["fine"] == 1 and c["blob"]["blob"] == 1 and c["second_face"]["front_everywhere"] == 1
    assert sum(sum(r.values()) for r in c.values()) == 4 and set(c) == set(LABELS)


def _run(root, rid, views):
    d = root / rid
    d.mkdir(parents=True)
    (d / "run.json").write_text(json.dumps({"run_id": rid}))
    (d / "scores.json").write_text(json.dumps({"views": views}))
    return d


def test_agreement_reads_the_runs_scores_and_names_an_unknown_run_in_one_line(tmp_path, capsys):
    fe = {"front_everywhere_rate": 0.45, "multi_face_rate": 0.0, "blob_rate": 0.0, "janus_rate": 0.45}
    blob = {"front_everywhere_rate": 0.0, "multi_face_rate": 0.0, "blob_rate": 0.9, "janus_rate": 0.0}
    burger = {"front_everywhere_rate": None, "multi_face_rate": None, "blob_rate": 1.0, "janus_rate": None}
    _run(tmp_path / "runs", "aaa", fe)
    _run(tmp_path / "runs", "bbb", blob)
    _run(tmp_path / "runs", "ccc", burger)
    labels = tmp_path / "labels.csv"
    labels.write_text("run_id,label\naaa,front_everywhere\nbbb,fine\nccc,fine\n")
    from gdbench.metrics.agreement import runs_by_id

    res = agreement(read_labels(labels), runs_by_id([tmp_path / "runs"]))
    assert [r["metric"] for r in res["rows"]] == ["front_everywhere", "blob"]
    assert res["recall"]["front_everywhere"] == 1 and res["recall"]["fine"] == 0 and res["recall"]["blob"] is None
    assert res["kappa_janus_split"] == 1.0  # both say Janus for aaa, not for bbb
    assert res["results"] == 2 and res["left_out_no_front"] == 1  # the frontless asset: no Janus class
    assert main(["--labels", str(labels), "--runs", str(tmp_path / "runs"), "--out", str(tmp_path / "o")]) == 0
    assert json.loads((tmp_path / "o" / "agreement.json").read_text())["results"] == 2
    labels.write_text("run_id,label\nzzz,fine\n")
    assert main(["--labels", str(labels), "--runs", str(tmp_path / "runs")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["agreement: error: labels: run id zzz names no run folder under --runs"]
    labels.write_text("run_id,label\naaa,janus\n")
    with pytest.raises(ValueError, match=r"labels: .* line 2: expected a run_id and a label of"):
        read_labels(labels)


def test_the_committed_label_files_are_valid_and_the_second_rater_labelled_the_same_results():
    """Every labels file under fixtures/labels reads (a run id and a class of LABELS per row), a
    hamburger is labelled blob or fine only (the rule: it has no front), and the second rater's
    file names exactly the results of the three sets it rated again, each with the same asset; the
    fourth and fifth sets are new results, the fifth of captions labelled nowhere else."""
    from pathlib import Path

    root = Path(__file__).resolve().parent.parent / "fixtures" / "labels"
    files = sorted(root.glob("janus_labels*.csv"))
    assert len(files) >= 4
    rows = {f.name: read_labels(f) for f in files}
    for name, rs in rows.items():
        assert all(r["label"] in ("blob", "fine") for r in rs if r["caption"] == "a hamburger"), name
        assert len({r["run_id"] for r in rs}) == len(rs), name  # one label per result
    rated_twice = ("janus_labels.csv", "janus_labels_heldout.csv", "janus_labels_fresh.csv")
    first = {r["run_id"]: r["caption"] for n in rated_twice for r in rows[n]}
    second = {r["run_id"]: r["caption"] for r in rows["janus_labels_rater2.csv"]}
    assert second == first and len(first) == 192
    # the fourth and fifth sets (one rater) name results of none of the others
    fourth = {r["run_id"] for r in rows["janus_labels_set4.csv"]}
    fifth = {r["run_id"] for r in rows["janus_labels_set5.csv"]}
    assert len(fourth) == len(fifth) == 72 and not (fourth | fifth) & set(first) and not fourth & fifth
    assert {r["caption"] for r in rows["janus_labels_set5.csv"]}.isdisjoint(
        r["caption"] for n in (*rated_twice, "janus_labels_set4.csv") for r in rows[n]
    )  # its twelve captions were never labelled before


def test_the_v3_label_files_pair_up_by_batch():
    """The v3 raters' files (fixtures/labels/v3_rater{1,2}_<batch>.csv): both passes of a batch label
    the same results, every caption of the 31 with four arms per seed of the batch; batch C (seeds
    3-4) names no result of the seeds 0-2 batches; batches D, E and F (seeds 0, 1 and 2 trained
    again in the second sitting) name the results A and B named (the same configs: docs/decisive_v3.md, deviation 5)."""
    from collections import Counter
    from pathlib import Path

    seeds = {"A": 2, "B": 1, "C": 2, "D": 1, "E": 1, "F": 1}
    root = Path(__file__).resolve().parent.parent / "fixtures" / "labels"
    ids = {}
    for batch, n in seeds.items():
        files = [root / f"v3_rater{p}_{batch}.csv" for p in (1, 2)]
        if not files[0].exists() and batch in ("E", "F"):
            continue  # not labelled yet
        a, b = ({r["run_id"]: r["caption"] for r in read_labels(f)} for f in files)
        assert a == b, batch
        per = Counter(a.values())
        assert len(per) == 31 and set(per.values()) == {4 * n}, (batch, per)
        ids[batch] = set(a)
    assert not ids["C"] & (ids["A"] | ids["B"]) and not ids["A"] & ids["B"]
    again = [ids[b] for b in ("D", "E", "F") if b in ids]  # seeds 0, 1, 2 trained again
    assert sum(map(len, again)) == len(set().union(*again))  # disjoint
    if len(again) == 3:
        assert set().union(*again) == ids["A"] | ids["B"]
    else:
        assert set().union(*again) < ids["A"] | ids["B"]
    # the files the report reads: each pass's batches C-F, every Janus result of the sweep once
    for p in (1, 2):
        whole = read_labels(root / f"v3_rater{p}.csv")
        parts = [r for b in "CDEF" for r in read_labels(root / f"v3_rater{p}_{b}.csv")]
        assert [(r["run_id"], r["label"]) for r in whole] == [(r["run_id"], r["label"]) for r in parts]
        assert len({r["run_id"] for r in whole}) == len(whole) == 620
