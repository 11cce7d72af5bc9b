"""COLMAP consistency (gdbench/metrics/colmap_consistency.py): the alignment in closed form, and
the calibration fixtures it must separate (consistent, two-faced, per-view jittered)."""

import math

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
    from renderers.pyrender_points._lib import available

    if not available()[0]:
        pytest.skip(f"pyrender unavailable: {available()[1]}")
    cams = circle_poses(100).cameras(256, 256)
    return {m: score_images(asset_circle_images("a yellow duck", cams, mode=m), cams)
            for m in ("consistent", "two-faced", "jittered")}  # fmt: skip


def test_consistent_asset_registers_with_the_true_step(calibration):
    s = calibration["consistent"]
    assert s.registration_rate >= 0.95
    assert s.mean_theta_deg == pytest.approx(3.6, abs=0.1)  # 100 views on a circle
    assert s.var_theta_deg2 < 0.5 and s.translation_dir_err_deg < 5
    assert s.failure_rate <= 0.05  # pairs unregistered or off by > 5 degrees


def test_metric_separates_inconsistent_fixtures(calibration):
    ok = calibration["consistent"]
    for mode in ("two-faced", "jittered"):
        bad = calibration[mode]
        # variance jumps by orders of magnitude, or views fail to register
        assert bad.var_theta_deg2 > 100 * ok.var_theta_deg2 or bad.registration_rate < 0.8, (mode, bad)
        assert bad.translation_dir_err_deg > 5 * ok.translation_dir_err_deg or bad.registration_rate < 0.8
        # failure rate: the two-faced circle flips at +-90 degrees (2 of 100 pairs, measured 0.02),
        # jitter breaks many adjacent steps
        assert bad.failure_rate >= ok.failure_rate + 0.02, (mode, bad.failure_rate, ok.failure_rate)


def test_bad_mode():
    with pytest.raises(ValueError, match="mode: expected 'consistent'"):
        asset_circle_images("a yellow duck", circle_poses(2).cameras(16, 16), mode="four-faced")
