"""The Janus judge (gdbench/metrics/judge/): the crop, the readings along a turntable, the head,
the committed sheets read back, and the shipped judge against the raters' labels."""

from __future__ import annotations

import csv
import json
from collections import Counter
from pathlib import Path

import numpy as np
import pytest
import torch

from gdbench.metrics.judge.net import BINS, SIZE, crop_views
from gdbench.metrics.judge.reading import FEATURES, turntable_features
from gdbench.metrics.judge.train import azimuth_targets

ROOT = Path(__file__).resolve().parents[1]
SIX = torch.tensor([0.0, 60, 120, 180, 240, 300])


def test_crop_finds_the_object_whatever_its_size_and_place():
    """A dark rectangle of aspect 2:1 anywhere in a white frame, at any size, comes out as the same
    crop: centred, its long side the crop's width less the margins, its aspect kept."""
    crops = []
    for y, x, h in ((10, 20, 12), (60, 5, 40), (30, 30, 20)):
        img = torch.full((1, 128, 128, 3), 255, dtype=torch.uint8)
        img[0, y : y + h, x : x + 2 * h] = 40
        crops.append(crop_views(img)[0])
    for c in crops:
        ink = (1 - c.min(0).values) > 0.5
        rows, cols = ink.any(1).nonzero().flatten(), ink.any(0).nonzero().flatten()
        width, height = int(cols[-1] - cols[0] + 1), int(rows[-1] - rows[0] + 1)
        assert abs(width - SIZE / 1.16) <= 2 and abs(height - width / 2) <= 2, (width, height)
        assert (
            abs(float(cols.float().mean()) - (SIZE - 1) / 2) < 1
            and abs(float(rows.float().mean()) - (SIZE - 1) / 2) < 1
        )
    assert (crops[0] - crops[1]).abs().mean() < 0.03 and (crops[1] - crops[2]).abs().mean() < 0.03
    empty = crop_views(torch.full((1, 16, 16, 3), 255, dtype=torch.uint8))
    assert torch.allclose(empty, torch.ones_like(empty))  # no object: the whole (white) frame


def test_azimuth_targets_peak_at_their_bin():
    t = azimuth_targets(torch.tensor([0.0, 90.0, -165.0, 359.0]))
    assert torch.allclose(t.sum(1), torch.ones(4))
    assert t.argmax(1).tolist() == [0, 90 // (360 // BINS), (360 - 165) // (360 // BINS), 0]


def _features(shown, azimuths=SIX, mix=None):
    q = azimuth_targets(torch.as_tensor(shown, dtype=torch.float32))
    if mix is not None:  # a second reading mixed in: front and back undecided
        q = 0.5 * q + 0.5 * azimuth_targets(torch.as_tensor(mix, dtype=torch.float32))
    return dict(zip(FEATURES, turntable_features(q, azimuths).tolist()))


def test_the_traces_of_the_four_classes():
    """Readings built from what each class shows (the closed forms of the rule's four cases) give
    the features their definitions promise."""
    fine = _features(SIX - 40.0)  # a whole object, turned by 40 degrees
    front = _features(torch.zeros(6))  # the front from every camera
    # turned by 60 degrees (camera a shows the asset's a - 60), the front again where its back is (camera 240)
    second = _features(torch.tensor([-60.0, 0, 60, 120, 0, 240]))
    blob = _features(SIX, mix=SIX + 180)  # profiles at the sides, front and back undecided
    assert fine["follow"] > 0.95 and fine["constant"] < 0.4 and fine["back_reads_front"] < 0.01
    assert front["constant"] > 0.95 and front["follow"] < 0.4 and front["profile_max"] < 0.01
    assert second["back_reads_front"] > 0.95 and 0.7 < second["follow"] < 0.9 and second["profile_max"] > 0.95
    assert blob["follow_half"] > 0.95 and 0.4 < blob["follow"] < 0.6
    many = _features(torch.arange(36) * 10.0 - 40.0, azimuths=torch.arange(36) * 10.0)
    assert abs(many["follow"] - fine["follow"]) < 0.05  # six views and thirty-six read alike
    with pytest.raises(ValueError, match="q: expected"):
        turntable_features(torch.ones(5, BINS) / BINS, SIX)


def test_head_recovers_separable_classes():
    from gdbench.metrics.judge.head import decide, fit

    g = torch.Generator().manual_seed(0)
    centres = {"front_everywhere": 0.0, "blob": 3.0, "fine": 6.0}
    labels = [c for c in centres for _ in range(30)]
    x = torch.stack([torch.full((len(FEATURES),), centres[c]) for c in labels]) + torch.randn(
        90, len(FEATURES), generator=g
    )
    head = fit(x, labels)
    p = head.probabilities(x)
    got = [decide(p[i], x[i], True)[0] for i in range(90)]
    assert sum(a == b for a, b in zip(got, labels)) >= 85
    assert decide(torch.tensor([0.9, 0.05, 0.05]), x[0], False)[0] == "blob"  # no front: Janus reads as blob


def _sheet_labels(path: Path, batches: set[str]) -> dict[tuple[str, str], str]:
    return {(r["batch"], r["run_id"]): r["label"] for r in csv.DictReader(open(path)) if r["batch"] in batches}


def test_committed_sheets_read_back_with_their_labels():
    """Batch D's sheets give the key's 124 results, each six square views of the sheet's row height,
    with both passes' labels; the consensus counts match a direct count of the two CSVs."""
    from gdbench.metrics.judge.sheets import v3_results

    rs = v3_results(ROOT, batches=("D",))
    key = json.loads((ROOT / "docs/results/v3/sheets/D_key.json").read_text())
    assert len(rs) == len(key) == 124 and {r.run_id for r in rs} == {k["run_id"] for k in key.values()}
    assert all(r.views.shape == (6, 128, 128, 3) for r in rs)
    assert all(key[str(r.number)]["caption"] == r.caption for r in rs)
    a = _sheet_labels(ROOT / "fixtures/labels/v3_rater1.csv", {"D"})
    b = _sheet_labels(ROOT / "fixtures/labels/v3_rater2.csv", {"D"})
    direct = Counter(a[k] for k in a if a[k] == b[k])
    assert Counter(r.consensus for r in rs if r.consensus) == direct
    # a row is the result its number names: its views are not the asset's (the sheet's top row)
    assert all(r.views.std() > 10 for r in rs)


def _shipped():
    from gdbench.metrics.judge.judge import WEIGHTS, load_judge

    if not (WEIGHTS / "eye.safetensors").is_file():
        pytest.fail(f"the shipped judge is missing from {WEIGHTS}: run `gdbench train-judge`")
    return load_judge()


EIGHTH_READS_THE_SPUN_DUCK_AS_A_FRONT = pytest.mark.xfail(
    strict=True,
    reason="the eighth judge reads the duck's spun single-coloured solid as front_everywhere (0.62): "
    "featureless round lumps (the teapot's, the duck's) are its two largest kinds of leave-kind-out misses "
    "on v3 (docs/scoring.md)",
)


@pytest.mark.parametrize(
    ("which", "kind", "want"),
    [
        ("shipped", "turned-90", "fine"),
        ("shipped", "front-everywhere", "front_everywhere"),
        pytest.param("shipped", "blob", "blob", marks=EIGHTH_READS_THE_SPUN_DUCK_AS_A_FRONT),
        ("seventh", "blob", "blob"),
    ],
)
def test_judge_on_renderable_fixtures(which, kind, want, tmp_path):
    """The 3D fixtures (metrics/failures3d.py: Gaussian scenes built from the asset, never labels)
    as results: the duck turned by 90 degrees is fine, and turned by that much; its front wedge
    repeated around it is front_everywhere; its spun, single-coloured solid is a blob. Both modes
    agree: the 36 turntable frames and the six views a sheet shows. No head saw the duck's labels;
    the seventh judge (made again from its kept head) read its fixtures against themselves as
    references (reference.py) and calls the spun solid a blob; the eighth (shipped) reads no
    references and calls it a front everywhere, a known shortfall (strict: a judge that reads it
    right fails this mark, and the mark goes)."""
    from gdbench.metrics.failures3d import failure_scene
    from gdbench.metrics.judge.judge import SEVENTH_HEAD, Judge, turntable_frames, with_head

    judge = _shipped() if which == "shipped" else Judge(with_head(SEVENTH_HEAD, tmp_path / "seventh"))
    scene = failure_scene("a yellow duck", kind)
    run = judge.scene(scene, "a yellow duck")
    assert run["label"] == want, run
    assert 0 < run["confidence"] <= 1 and len(run["views"]) == 36 and run["version"] == judge.version
    six = judge.views(turntable_frames(scene)[::6], SIX, "a yellow duck")
    assert six["label"] == want, six
    if kind == "turned-90":
        assert abs(run["turn_deg"] - 90) <= 22.5 and abs(six["turn_deg"] - 90) <= 22.5


def test_judge_block_is_null_where_there_is_nothing_to_judge(tmp_path):
    """No caption, or a caption the judge does not know: the block is null with the reason, not a
    guess; a labels CSV naming a run id no judged run has is a one-line error."""
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import JudgeRuns
    from gdbench.core.builtin import demo_scene
    from gdbench.metrics.judge.judge import judge_block

    _shipped()
    scene = demo_scene(500)
    for caption, why in ((None, "no caption"), ("a purple giraffe", "knows no asset")):
        block = judge_block(scene, caption)
        assert block["label"] is None and why in block["reason"]
    run = tmp_path / "r"
    run.mkdir()
    scene.save_ply(run / "scene.ply")
    (run / "run.json").write_text(json.dumps({"run_id": "abc", "config": {}}))
    rows = main(JudgeRuns(paths=(tmp_path,)))
    assert rows[0]["label"] is None and (tmp_path / "judge.csv").is_file()
    stored = json.loads((run / "scores.json").read_text())["judge"]
    assert stored["label"] is None and "no caption" in stored["reason"]
    labels = tmp_path / "labels.csv"
    labels.write_text("run_id,label\nnot-a-run,blob\n")
    with pytest.raises(ValueError, match=r"labels: .* names run id 'not-a-run'"):
        main(JudgeRuns(paths=(tmp_path,), labels=labels))
    with pytest.raises(ValueError, match="paths: expected at least one"):
        main(JudgeRuns(paths=()))


def test_an_asset_without_a_front_takes_the_view_metrics_blob_or_fine():
    """The hamburger declares no front: the judge's eye has nothing to read there, so its label is
    the view metrics' blob or fine and says so; an asset with a front keeps the judge's own label;
    without a views block the judge's label stands, marked unvalidated."""
    from gdbench.metrics.run_scores import judge_text, no_front

    j = {"label": "blob", "confidence": 0.7, "judge_failure": 1, "version": "v"}
    blob_views = {"front_everywhere_rate": None, "multi_face_rate": None, "blob_rate": 1.0}
    fine_views = {"front_everywhere_rate": None, "multi_face_rate": None, "blob_rate": 0.0}
    got = no_front(j, "a hamburger", fine_views)
    assert got["label"] == "fine" and got["judge_failure"] == 0 and got["eye_label"] == "blob"
    assert got["confidence"] is None and "no front" in judge_text(got)
    assert no_front(j, "a hamburger", blob_views)["label"] == "blob"
    assert no_front(j, "a yellow duck", fine_views) == j
    assert "unvalidated" in no_front(j, "a hamburger", None)["decided_by"]


def test_a_sweeps_cell_line_names_the_judges_label():
    """A finished cell's line says the judge's class and confidence (not the view classes' rates,
    nor a Var(theta) of nan for a cell scored without COLMAP)."""
    from gdbench.experiments.sweep import cell_line

    row = {"setting": "janus", "group": "learned-v1", "prompt": "a corgi", "preset": "gd", "seed": 5,
           "gt_psnr": 15.75, "judge_label": "blob", "judge_confidence": 0.81, "floaters": 0.002,
           "colmap_failure_rate": float("nan"), "cell_s": 98.0}  # fmt: skip
    line = cell_line(row)
    assert "judge blob (0.81)" in line and "nan" not in line and "multi-face" not in line
    assert "COLMAP failure 0.10" in cell_line(row | {"colmap_failure_rate": 0.1})
    assert "judge not judged" in cell_line(row | {"judge_label": "", "judge_confidence": float("nan")})


def test_judging_again_reuses_only_the_same_judge_and_keeps_other_blocks(tmp_path, monkeypatch):
    """`gdbench judge` on a scored run: the judge's block is reused by the same judge on the same
    scene, judged again by another judge (its version is in the block's parameters), and every
    other block of scores.json, even one made by older code, stays as it was; views that are not
    images in [0, 1] or uint8 are refused naming the argument."""
    from gdbench.metrics.failures3d import failure_scene
    from gdbench.metrics.judge import judge as judge_module
    from gdbench.metrics.run_scores import judge_only

    judge = _shipped()
    run = tmp_path / "run"
    run.mkdir()
    failure_scene("a yellow duck", "turned-90").save_ply(run / "scene.ply")
    (run / "run.json").write_text(json.dumps({"caption": "a yellow duck", "config": {}}))
    first = judge_only(run)
    assert first["judge"]["label"] == "fine" and first["reused"] == []
    stored = json.loads((run / "scores.json").read_text())
    old_block = {"registration_rate": 1.0, "made": {"commit": "0000000old00", "params": {}}}
    (run / "scores.json").write_text(json.dumps(stored | {"colmap": old_block}))
    assert judge_only(run)["reused"] == ["judge"]
    monkeypatch.setattr(judge_module, "judge_version", lambda: "another-judge")
    again = judge_only(run)
    assert again["reused"] == [] and again["judge"]["made"]["params"]["judge"] == "another-judge"
    assert json.loads((run / "scores.json").read_text())["colmap"] == old_block
    with pytest.raises(ValueError, match="views: expected uint8 images or floats in"):
        judge.views(np.full((6, 8, 8, 3), 200.0), SIX, "a yellow duck")


def test_the_re_reading_recomputes_v3s_registered_rows(tmp_path):
    """``reread_v3`` on the committed labels gives, for the raters, v3's registered primary rows
    (docs/results/v3/verdict.csv, written by the v3 report's own code) to float precision: the
    pairing of arms, the prompt as the unit and Holm are v3's; the judge's rows are read the same way."""
    from gdbench.experiments.judge_build import reread_v3
    from gdbench.metrics.agreement import LABELS

    judged = tmp_path / "judged.csv"
    with open(judged, "w", newline="") as f:  # the raters' labels of every sheet result (the judge's columns unused)
        w = csv.writer(f)
        w.writerow(["batch", "run_id", "rater1", "rater2", "judge_loko", "judge_in_sample"])
        a = {
            (r["batch"], r["run_id"]): r["label"] for r in csv.DictReader(open(ROOT / "fixtures/labels/v3_rater1.csv"))
        }
        b = {
            (r["batch"], r["run_id"]): r["label"] for r in csv.DictReader(open(ROOT / "fixtures/labels/v3_rater2.csv"))
        }
        for k in a:
            if k[0] in "CDEF":
                w.writerow([*k, a[k], b[k], LABELS[0], LABELS[3]])
    rows = {r["comparison"]: r for r in reread_v3(judged, tmp_path, root=ROOT) if r["reader"] == "raters"}
    registered = [r for r in csv.DictReader(open(ROOT / "docs/results/v3/verdict.csv")) if r["metric"] == "label_janus"]
    assert len(registered) == 3
    for r in registered:
        mine = rows[f"{r['a']} vs {r['b']}"]
        for key in ("prompt_mean_diff", "prompt_ci_low", "prompt_ci_high", "p_prompts_holm"):
            assert mine[key] == pytest.approx(float(r[key]), rel=1e-9), (r["b"], key)


def test_eye_from_provenance_names_the_source_judge_not_a_path(tmp_path):
    """``train-judge --eye-from``'s provenance names the source by what it is (its judge version
    and its eye's SHA-256, recomputed here with hashlib over the file), the same for the shipped
    folder and a copy of it elsewhere; the shipped weights' own record names its source so, with
    the shipped eye's hash (the eye is taken byte for byte), not a machine path."""
    import hashlib
    import shutil

    from gdbench.experiments.judge_build import source_of
    from gdbench.metrics.judge.judge import WEIGHTS, Judge

    judge = _shipped()
    copy = tmp_path / "elsewhere"
    shutil.copytree(WEIGHTS, copy)
    here, there = source_of(judge, WEIGHTS), source_of(Judge(copy), copy)
    assert here == there
    assert here["judge"] == judge.version
    assert here["eye_sha256"] == hashlib.sha256((WEIGHTS / "eye.safetensors").read_bytes()).hexdigest()[:12]
    # the shipped record: its eye was copied byte for byte from the judge it names, so the hash it
    # keeps is the shipped eye's own
    shipped = json.loads((WEIGHTS / "provenance.json").read_text())["eye_from"]
    if shipped is not None:
        assert set(shipped) == {"judge", "eye_sha256"} and shipped["eye_sha256"] == here["eye_sha256"]
