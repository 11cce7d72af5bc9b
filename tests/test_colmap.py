"""COLMAP consistency (gdbench/metrics/colmap_consistency.py): the alignment in closed form, and
its calibration on 3D failure fixtures: what it sees (flicker, per-view jitter) and what it
cannot (a second face, floaters)."""

import math
import subprocess
import sys

import numpy as np
import pytest

from gdbench.metrics.colmap_consistency import asset_circle_images, circle_poses, score_images, umeyama

pycolmap = pytest.importorskip("pycolmap")


def test_umeyama_recovers_a_similarity():
    rng = np.random.default_rng(0)
    src = rng.normal(size=(20, 3))
    a = 0.7
    R = np.array([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    dst = 2.5 * src @ R.T + np.array([0.3, -1.0, 2.0])
    s, Rh, t = umeyama(src, dst)
    assert s == pytest.approx(2.5) and np.allclose(Rh, R) and np.allclose(t, [0.3, -1.0, 2.0])


@pytest.fixture(scope="module")
def calibration():
    """COLMAP on the 3D failure fixtures of the duck (Gaussian scenes rendered on the circle),
    and on per-view jitter (each view turned by up to +-12 degrees, which no scene renders)."""
    from gdbench.metrics.colmap_consistency import fixture_circle_images
    from renderers.pyrender_points._lib import available

    if not available()[0]:
        pytest.skip(f"pyrender unavailable: {available()[1]}")
    cams = circle_poses(100).cameras(256, 256)
    out = {k: score_images(fixture_circle_images("a yellow duck", cams, k, flicker=0.2), cams)
           for k in ("asset", "flicker", "floaters", "two-faced")}  # fmt: skip
    out["jittered"] = score_images(asset_circle_images("a yellow duck", cams, mode="jittered"), cams)
    return out


def test_the_asset_scene_registers_with_the_true_step(calibration):
    s = calibration["asset"]
    assert s.registration_rate >= 0.95
    assert s.mean_theta_deg == pytest.approx(3.6, abs=0.1)  # 100 views on a circle
    assert s.var_theta_deg2 < 0.5 and s.translation_dir_err_deg < 5
    assert s.failure_rate <= 0.05  # pairs unregistered or off by > 5 degrees


def test_view_to_view_inconsistency_fails_colmap(calibration):
    """Colour flicker (+-0.2 per channel, anew per view; +-0.15 already fails 63% of pairs) and
    per-view jitter break the circle:
    what COLMAP measures is view-to-view inconsistency."""
    ok = calibration["asset"]
    for kind in ("flicker", "jittered"):
        bad = calibration[kind]
        assert bad.failure_rate >= ok.failure_rate + 0.2, (kind, bad.failure_rate, ok.failure_rate)


def test_colmap_cannot_see_a_3d_second_face_and_barely_sees_floaters(calibration):
    """A two-faced object is one consistent 3D scene: COLMAP registers it like the asset (the
    view metrics' multi-face rate is the instrument for it). Floaters are consistent 3D points
    too: they stay registered."""
    ok = calibration["asset"]
    for kind in ("two-faced", "floaters"):
        s = calibration[kind]
        assert s.registration_rate >= 0.95 and s.failure_rate <= ok.failure_rate + 0.05, (kind, s)
        assert s.var_theta_deg2 < 0.5


def test_a_scene_scores_the_same_every_time(calibration):
    """Same images, same seed, same score (the oracle: the calibration's own run of the floaters
    fixture, which registers). COLMAP threaded in any stage (SIFT, matching, mapping) moved the same scene's
    Var(theta) between runs, and so did two matchers in one process; THREADS = 1 and one share per
    process (SHARES) make every field equal."""
    from gdbench.metrics.colmap_consistency import fixture_circle_images

    cams = circle_poses(100).cameras(256, 256)
    again = score_images(fixture_circle_images("a yellow duck", cams, "floaters", flicker=0.2), cams).as_dict()
    first = calibration["floaters"].as_dict()
    assert first["registered"] > 50, first  # a reconstruction whose poses depend on every stage
    assert {k: v for k, v in again.items() if k != "seconds"} == {k: v for k, v in first.items() if k != "seconds"}


def test_bad_mode():
    with pytest.raises(ValueError, match="mode: expected 'consistent'"):
        asset_circle_images("a yellow duck", circle_poses(2).cameras(16, 16), mode="two-faced")
    from gdbench.metrics.colmap_consistency import fixture_circle_images

    with pytest.raises(ValueError, match="kind: expected one of"):
        fixture_circle_images("a yellow duck", circle_poses(2).cameras(16, 16), "spun")


def test_colmap_output_goes_to_the_log_not_the_console(tmp_path, capfd):
    """COLMAP's own lines (glog, written by C++ to file descriptor 2) land in the log file that
    ``score_run`` keeps in the run folder; the console sees none. Twelve 128 px views of the duck
    have too few matches, so COLMAP warns: a line it must write somewhere."""
    import re

    from gdbench.metrics.colmap_consistency import _import_pycolmap

    _import_pycolmap()
    cams = circle_poses(12).cameras(128, 128)
    log = tmp_path / "colmap.log"
    score_images(asset_circle_images("a yellow duck", cams), cams, log=log)
    glog = re.compile(r"^[IWEF]\d{8} ", re.M)
    assert glog.search(log.read_text()), log.read_text()
    out, err = capfd.readouterr()
    assert not glog.search(err) and not glog.search(out), err


def test_scoring_survives_pycolmap_imported_first():
    """A process that imported pycolmap before Pillow's zlib encoder was first used died in it
    (double free in deflateEnd) when the views were written as PNG; they are BMP now. Oracle: the
    process exits 0 and prints its registration (COLMAP ran on the written views)."""
    code = (
        "import pycolmap\n"
        "from gdbench.metrics.colmap_consistency import asset_circle_images, circle_poses, score_images\n"
        "cams = circle_poses(12).cameras(64, 64)\n"
        "print('views', score_images(asset_circle_images('a yellow duck', cams), cams).views)\n"
    )
    p = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0 and "views 12" in p.stdout, p.stderr[-2000:]


def _tables(db, skip=()):
    import sqlite3

    con = sqlite3.connect(db)
    try:
        names = [n for (n,) in con.execute("SELECT name FROM sqlite_master WHERE type='table'") if n not in skip]
        return {n: con.execute(f"SELECT * FROM {n} ORDER BY rowid").fetchall() for n in names}
    finally:
        con.close()


def test_the_shares_write_one_threads_features_and_match_every_pair_once(tmp_path):
    """Extraction and matching run as two shares, this process and a helper (SHARES). Oracle:
    pycolmap on one thread over all views (extract_features, then match_exhaustive): the
    database's every table but the matches' is the same, row for row, and every view pair has the
    same set of matches."""
    import shutil

    from gdbench.metrics.colmap_consistency import SHARES, _extraction_shares, fixture_circle_images

    assert SHARES == 2
    K = 16
    cams = circle_poses(K).cameras(192, 192)
    score_images(fixture_circle_images("a yellow duck", cams, "asset"), cams, tmp_path / "split")
    db = tmp_path / "split" / "database.db"
    fx, fy, cx, cy = (float(v) for v in cams.Ks[0, [0, 1, 0, 1], [0, 1, 2, 2]])
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model, reader.camera_params = "PINHOLE", f"{fx},{fy},{cx},{cy}"
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.max_image_size, extraction.num_threads = 512, 1
    one = tmp_path / "one.db"
    names = [f"{i:04d}.bmp" for i in range(K)]
    pycolmap.extract_features(one, tmp_path / "split" / "images", image_names=names,
                              camera_mode=pycolmap.CameraMode.SINGLE, reader_options=reader,
                              extraction_options=extraction, device=pycolmap.Device.cpu)  # fmt: skip
    matches = ("matches", "two_view_geometries")
    split_tables, one_tables = _tables(db, skip=matches), _tables(one, skip=matches)
    assert len(one_tables["keypoints"]) == K and all(r[1] > 0 for r in one_tables["keypoints"])
    assert split_tables == one_tables
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = 1
    matched = tmp_path / "matched.db"
    shutil.copyfile(one, matched)
    pycolmap.match_exhaustive(matched, matching_options=matching, device=pycolmap.Device.cpu)

    def match_sets(path):
        rows = _tables(path)["matches"]
        return {r[0]: set(map(tuple, np.frombuffer(r[3] or b"", np.uint32).reshape(-1, 2).tolist())) for r in rows}

    split, truth = match_sets(db), match_sets(matched)
    assert len(truth) == K * (K - 1) // 2 and sum(bool(m) for m in truth.values()) >= K // 2  # neighbours match
    assert split == truth
    # shares=1 is the metric as it was: one thread's database, verified geometries included
    score_images(fixture_circle_images("a yellow duck", cams, "asset"), cams, tmp_path / "one", shares=1)
    assert _tables(tmp_path / "one" / "database.db") == _tables(matched)
    for bad in (0, 17, True, 2.0):
        with pytest.raises(ValueError, match="shares: expected an integer from 1 to 16, got "):
            score_images(fixture_circle_images("a yellow duck", cams, "asset"), cams, shares=bad)
    # the views went to the shares alternately (the database above is the proof that it does not
    # matter which share extracts a view); no share is empty
    assert _extraction_shares(names, 2) == [names[0::2], names[1::2]]
    assert _extraction_shares(names[:1], 2) == [names[:1]]


def test_a_failing_share_process_raises_its_error(tmp_path):
    """A share's process reports its job's error, and the caller raises it with COLMAP's words
    (oracle: pycolmap's own refusal of a pairs list in a folder that does not exist)."""
    from gdbench.metrics._colmap_share import match
    from gdbench.metrics.colmap_consistency import _Helpers

    job = {"job": "match", "database": str(tmp_path / "none" / "db.db"), "pairs": str(tmp_path / "none" / "p"),
           "threads": 1}  # fmt: skip
    with pytest.raises(Exception) as here:
        match(job)
    with (
        _Helpers(1, tmp_path / "log") as helpers,
        pytest.raises(RuntimeError, match="COLMAP share process: error: ") as e,
    ):
        helpers.run([{"job": "match", "database": str(tmp_path / "ok.db"), "pairs": str(tmp_path / "x")}, job],
                    lambda job: None)  # fmt: skip
    assert str(here.value).splitlines()[0][:40] in str(e.value)
    assert all(p.poll() is not None for p in helpers.procs)  # ended with the block, killed on the error


def test_a_share_process_without_pycolmap_says_so(tmp_path, monkeypatch):
    """The helper imports pycolmap before its first job; if that fails, the job's answer carries
    the import's error (a pycolmap that raises on import shadows the real one in the helper)."""
    from gdbench.metrics.colmap_consistency import _Helpers

    (tmp_path / "shadow").mkdir()
    (tmp_path / "shadow" / "pycolmap.py").write_text("raise ImportError('no pycolmap in this test')\n")
    monkeypatch.setenv("PYTHONPATH", str(tmp_path / "shadow"))
    with (
        _Helpers(1, tmp_path / "log") as helpers,
        pytest.raises(RuntimeError, match="COLMAP share process: error: ImportError: no pycolmap in this test"),
    ):
        helpers.run([{"job": "match"}, {"job": "match"}], lambda job: None)


def test_score_scene_is_score_images_of_its_views(tmp_path):
    """score_scene passes its shares on; oracle: score_images of the same views, rendered apart,
    with one share and with two (every field but the seconds)."""
    from gdbench.core.turntable import render_views, to_uint8
    from gdbench.metrics.colmap_consistency import score_scene
    from gdbench.metrics.failures3d import failure_scene

    scene = failure_scene("a yellow duck", "asset")
    cams = circle_poses(40).cameras(192, 192)
    images = to_uint8(render_views(scene, cams, background=(1.0, 1.0, 1.0)))
    for shares in (1, 2):
        whole = score_scene(scene, views=40, size=192, shares=shares).as_dict()
        apart = score_images(images, cams, shares=shares).as_dict()
        whole.pop("seconds"), apart.pop("seconds")
        assert whole == apart and whole["registered"] >= 20, (shares, whole)
    with pytest.raises(ValueError, match="shares: expected an integer from 1 to 16"):
        score_scene(scene, views=16, size=192, shares=0)
