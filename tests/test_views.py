"""Ground-truth view metrics (multi-face rate, instance consistency, floaters), calibrated on
fixtures whose answer is known: the asset, a two-faced asset, a chimera of two variants,
per-view jitter and added floaters (docs/scoring.md)."""

import pytest
import torch

from renderers.pyrender_points._lib import available

pytestmark = pytest.mark.skipif(not available()[0], reason=f"pyrender unavailable: {available()[1]}")

CAPTION = "a yellow duck"


@pytest.fixture(scope="module")
def scores():
    from gdbench.metrics.views import fixture_views, reference, score_views

    ref = reference(CAPTION, variants=2)
    modes = ("asset", "two-faced", "chimera", "jittered", "floaters", "spun")
    return {m: score_views(*fixture_views(CAPTION, m), ref) for m in modes}


def test_the_asset_itself_scores_perfect(scores):
    s = scores["asset"]
    assert s.multi_face_rate == 0 and s.instance_consistency == 1 and s.majority_variant == 0
    assert s.offset_deg == 0 and s.floaters < 0.01
    assert s.front_share == pytest.approx(9 / 36)  # azimuths -40..40 of 0, 10, ..., 350


def test_multi_face_rate_separates_a_two_faced_asset(scores):
    s = scores["two-faced"]
    assert s.multi_face_rate > 0.4 and s.front_share > 0.45  # the back half sees a front
    assert scores["jittered"].multi_face_rate == 0  # +-30 degrees is not a second face


def test_featureless_rate_separates_a_solid_of_revolution_and_is_no_second_face(scores):
    assert scores["spun"].featureless_rate == 1 and scores["spun"].multi_face_rate == 0
    for mode in ("asset", "two-faced", "chimera", "jittered", "floaters"):
        assert scores[mode].featureless_rate == 0, mode
    assert scores["two-faced"].multi_face_rate > 0.4  # a second face stays one


def test_instance_consistency_separates_a_chimera(scores):
    s = scores["chimera"]
    assert 0.4 < s.instance_consistency < 0.65 and s.multi_face_rate == 0
    assert set(s.matched_variant) == {0, 1}


def test_floaters_separate_added_blobs(scores):
    assert scores["floaters"].floaters > 0.05 > 5 * max(scores["asset"].floaters, 0.002)
    # a second face or another variant is shape error, not floaters
    assert max(scores["two-faced"].floaters, scores["chimera"].floaters) < 0.01


def test_a_trained_like_scene_is_matched_to_its_azimuth():
    """A Gaussian scene fitted to nothing but placed like the asset's bank: its own turntable
    views are matched one for one when the reference is built from the same images."""
    from gdbench.metrics.views import Reference, score_views, turntable_poses

    g = torch.Generator().manual_seed(0)
    imgs = torch.rand(1, 72, 8, 8, 3, generator=g)
    ref = Reference(imgs, torch.ones(1, 72, 8, 8), torch.arange(72, dtype=torch.float32) * 5 - 180)
    # turntable azimuth a (0, 10, ...) is reference index (a + 180) / 5, turned by 40 degrees
    az = turntable_poses(36).azimuth
    idx = (((az + 40 + 180) % 360) / 5).round().long()
    s = score_views(imgs[0, idx], torch.ones(36, 8, 8), ref)
    assert s.offset_deg == 40 and s.multi_face_rate == 0 and s.instance_consistency == 1
    assert s.turned_deg == -40  # its view from t is the asset's from t + 40 = t - (-40)


@pytest.mark.parametrize("turn", [0.0, 90.0, -60.0, 180.0, 135.0])
def test_turned_deg_reads_the_turn_of_a_result(turn):
    """Views whose image from azimuth t is the asset's view from t - turn (a result turned by
    ``turn`` about +Z) read turned_deg = turn, in (-180, 180]."""
    from gdbench.metrics.views import Reference, score_views, turntable_poses

    g = torch.Generator().manual_seed(1)
    imgs = torch.rand(1, 72, 8, 8, 3, generator=g)
    ref = Reference(imgs, torch.ones(1, 72, 8, 8), torch.arange(72, dtype=torch.float32) * 5 - 180)
    az = turntable_poses(36).azimuth
    idx = (((az - turn + 180) % 360) / 5).round().long()
    s = score_views(imgs[0, idx], torch.ones(36, 8, 8), ref)
    assert s.turned_deg == turn and s.multi_face_rate == 0


def test_a_run_is_scored_on_its_own_background(tmp_path):
    """A scene of the duck (its bank's surface points, coloured by the bank) scored as a run on a
    black background: the GT PSNR that score_run reports is the PSNR against pyrender's asset on
    black at the reported offset (the oracle, rendered here), not against the asset on white
    (which the run's own black background would fail by many dB)."""
    import json
    import math

    from gdbench.assets.bank import BankConfig, load_bank
    from gdbench.camera import SphericalPoses
    from gdbench.metrics.gt import asset_views, heldout_poses, psnr
    from gdbench.metrics.run_scores import score_run
    from gdbench.scene import GaussianScene
    from gdbench.train.init import from_bank_depth
    from gdbench.turntable import render_views

    bank = load_bank(CAPTION, BankConfig(resolution=64, azimuths=24, elevations=(0.0,)), verbose=False)
    s = from_bank_depth(bank, 20000, 0.95, generator=torch.Generator().manual_seed(0), views=24)
    scene = GaussianScene(s.means, s.quats, s.log_scales - math.log(2), s.opacity_logits, s.sh)  # surface-tight
    black = (0.0, 0.0, 0.0)
    run = tmp_path / "run"
    run.mkdir()
    scene.save_ply(run / "scene.ply")
    (run / "run.json").write_text(json.dumps({"caption": CAPTION, "config": {"background": list(black)}}))
    gt = score_run(run, colmap=False)["gt"]
    assert gt["background"] == list(black)
    p = heldout_poses(12)
    poses = SphericalPoses(p.azimuth + gt["offset_deg"], p.elevation, p.radius, p.fovy)
    img = render_views(scene, poses.cameras(64, 64), background=black)
    on_black = float(psnr(img, asset_views(CAPTION, poses, 64, background=black)).mean())
    on_white = float(psnr(img, asset_views(CAPTION, poses, 64)).mean())
    assert gt["psnr"] == pytest.approx(on_black, abs=1e-3) and on_black > 13
    assert on_white < on_black - 5, (on_black, on_white)


def test_gt_ssim_is_the_standard_one_and_held_out_views_are_not_bank_views():
    """SSIM against pytorch-msssim's (11x11 Gaussian window, sigma 1.5, valid region), on
    images related as a trained scene's are to the asset (blur, noise, a shift); the held-out
    poses lie off the bank's azimuth and elevation grid (half its step away in azimuth)."""
    import pytorch_msssim

    from gdbench.assets.bank import BankConfig
    from gdbench.metrics.gt import heldout_poses, ssim

    g = torch.Generator().manual_seed(0)
    ref = torch.rand(4, 48, 56, 3, generator=g, dtype=torch.float64)
    ref = torch.nn.functional.avg_pool2d(ref.permute(0, 3, 1, 2), 5, 1, 2).permute(0, 2, 3, 1)  # some structure
    noisy = (ref + 0.1 * torch.randn(ref.shape, generator=g, dtype=torch.float64)).clamp(0, 1)
    shifted = ref.roll(2, dims=2)
    for img in (ref, noisy, shifted):
        want = pytorch_msssim.ssim(
            img.permute(0, 3, 1, 2), ref.permute(0, 3, 1, 2), data_range=1.0, size_average=False, win_size=11
        )
        assert torch.allclose(ssim(img, ref).double(), want.double(), atol=1e-5), (ssim(img, ref), want)
    assert ssim(ref, ref).min() > 0.9999 and ssim(noisy, ref).max() < 0.95
    bank = BankConfig()
    step = 360.0 / bank.azimuths
    az = heldout_poses(12).azimuth
    gap = torch.remainder(az, step)
    assert torch.allclose(torch.minimum(gap, step - gap), torch.full_like(az, step / 2))
    assert all(float(e) not in bank.elevations for e in heldout_poses(12).elevation)
