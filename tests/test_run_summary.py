"""What a finished run says about itself (issue: a failed run must not look like a finished one):
the turn in one convention for the GT score and the view metrics, checked on fixtures turned by
a known angle, and a warning exactly when the result is of a failure class."""

import json

import pytest
import torch

from renderers.pyrender_points._lib import available

CAPTION = "a yellow duck"


@pytest.mark.parametrize(("offset", "turn"), [(0, 0), (90, 90), (345, -15), (180, 180), (-180, 180), (540, 180)])
def test_turned_deg_wraps_the_gt_offset_into_the_view_metrics_range(offset, turn):
    from gdbench.metrics.gt import turned_deg

    assert turned_deg(offset) == turn


def _run(tmp_path, kind):
    from gdbench.metrics.failures3d import failure_scene

    run = tmp_path / kind
    run.mkdir()
    failure_scene(CAPTION, kind).save_ply(run / "scene.ply")
    (run / "run.json").write_text(json.dumps({"caption": CAPTION, "config": {"background": [1.0, 1.0, 1.0]}}))
    return run


@pytest.mark.skipif(not available()[0], reason=f"pyrender unavailable: {available()[1]}")
def test_a_turned_result_reads_one_turn_and_a_failed_one_warns(tmp_path):
    """The duck turned by 90 degrees (a 3D fixture): the GT score's turn and the view metrics'
    turned_deg are both 90, the judge calls it fine, and the summary says so and warns of nothing;
    the faceless blob fixture's summary warns once, on the judge's label (a failure), naming its
    confidence (the view classes are shown as superseded, and warn no more)."""
    from gdbench.metrics.gt import turned_deg
    from gdbench.metrics.run_scores import JUDGE_WORDS, report, result_lines, score_run

    s = score_run(_run(tmp_path, "turned-90"), colmap=False)
    assert turned_deg(s["gt"]["offset_deg"]) == 90 == s["views"]["turned_deg"]
    lines = result_lines(s["gt"], s["views"], s["judge"])
    assert "turned 90 deg" in lines[0] and "turned 90 deg" in report(s)
    assert f"{s['gt']['psnr_unaligned']:.2f} dB as it stands" in lines[0]
    assert s["gt"]["psnr"] > s["gt"]["psnr_unaligned"] + 3  # the headline is after the turn
    assert lines[1].startswith("  judge: fine (confidence") and not any("warning" in x for x in lines)
    assert lines[2].startswith("  view classes (superseded by the judge): fine;")
    b = score_run(_run(tmp_path, "blob"), colmap=False)
    warn = [x for x in result_lines(b["gt"], b["views"], b["judge"]) if "warning" in x]
    # a failure either way (the eighth judge calls this blob a front everywhere: test_judge.py's
    # strict expected failure); the one warning names the judge's own label and confidence
    assert b["judge"]["judge_failure"] == 1 and b["judge"]["label"] != "fine"
    assert len(warn) == 1 and f"the judge calls this result {JUDGE_WORDS[b['judge']['label']]}" in warn[0]
    assert f"confidence {b['judge']['confidence']:.2f}" in warn[0]
    assert not [x for x in result_lines(b["gt"], b["views"]) if "warning" in x]  # no judge, no warning
    assert torch.isfinite(torch.tensor(b["gt"]["psnr"]))


@pytest.mark.skipif(not available()[0], reason=f"pyrender unavailable: {available()[1]}")
def test_scores_json_records_the_gt_turn_in_the_view_metrics_convention(tmp_path):
    """The duck turned by 180 degrees: scores.json's gt block has turned_deg 180 beside its
    offset_deg, and the views block reads the same turn."""
    from gdbench.metrics.run_scores import score_run

    s = score_run(_run(tmp_path, "turned-180"), colmap=False)
    stored = json.loads((tmp_path / "turned-180" / "scores.json").read_text())
    assert stored["gt"]["turned_deg"] == 180 == stored["views"]["turned_deg"] == s["gt"]["turned_deg"]
