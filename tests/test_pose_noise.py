"""Pose-locked noise (the gd-pose-locked control): its weights against their closed form, its
marginals against N(0, 1), its persistence and its spectrum against structured noise's, and that
it is locked to the image, not to the object."""

import math

import pytest
import torch

from gdbench.core.camera import SphericalPoses
from gdbench.mechanisms.noise import NoiseConfig, NoiseRenderer, autocorrelation_length, make_noise_cloud
from gdbench.mechanisms.pose_noise import POSE_WIDTH_DEG, PoseLockedNoise, anchor_weights


def _pose_corr(p, q) -> float:
    a1, w1 = anchor_weights(*p)
    a2, w2 = anchor_weights(*q)
    other = dict(zip(a2, w2.tolist()))
    return sum(w * other.get(k, 0.0) for k, w in zip(a1, w1.tolist()))


@pytest.mark.parametrize(("az", "el"), [(0.0, 0.0), (13.7, 8.2), (179.9, -44.0), (-91.0, 60.0)])
def test_anchor_weights_have_unit_norm_and_the_gaussian_kernels_correlation(az, el):
    """sum a_k^2 = 1 (unit variance for any pose); two poses Delta apart correlate as the
    continuous Gaussian kernel's closed form exp(-Delta^2 / (4 w^2)) up to the grid's error, along
    azimuth (on the sphere: Delta / cos(elevation) of azimuth) and elevation, across the wrap."""
    _, a = anchor_weights(az, el)
    assert abs(float((a**2).sum()) - 1) < 1e-12
    w = POSE_WIDTH_DEG
    for delta in (2.5, 5.0, 10.0):
        want = math.exp(-(delta**2) / (4 * w * w))
        got_az = _pose_corr((az, el), (az + delta / math.cos(math.radians(el)), el))
        got_el = _pose_corr((az, el), (az, el + delta))
        assert abs(got_az - want) < 0.04 and abs(got_el - want) < 0.04, (delta, want, got_az, got_el)
    assert _pose_corr((az, el), (az + 360.0, el)) == pytest.approx(1.0)  # a function of the pose
    assert abs(_pose_corr((az, el), (az + 30.0 / math.cos(math.radians(el)), el))) < 1e-3  # 30 degrees apart


def test_anchor_weights_refuse_bad_input():
    with pytest.raises(ValueError, match="pose: expected finite"):
        anchor_weights(float("nan"), 0.0)
    with pytest.raises(ValueError, match="width: expected > 0"):
        anchor_weights(0.0, 0.0, 0.0)


def _setup(seed=0, size=24):
    cloud = make_noise_cloud(NoiseConfig(), 3, generator=torch.Generator().manual_seed(seed))
    return cloud, PoseLockedNoise(cloud, seed=100 + seed)


def _poses(az, el=10.0, fovy=55.0):
    az = torch.as_tensor(az, dtype=torch.float64).reshape(-1)
    n = len(az)
    return SphericalPoses(az, torch.full((n,), el, dtype=torch.float64), torch.ones(n, dtype=torch.float64),
                          torch.full((n,), fovy, dtype=torch.float64))  # fmt: skip


def test_pose_locked_fields_are_standard_normal_per_pixel():
    """Over 48 poses 7.5 degrees apart (whose colours are independent: 0.03 correlation), each
    pixel's values have mean 0 and variance 1 (within 5 standard errors of the pooled estimate)."""
    _, noise = _setup()
    az = torch.arange(48) * 7.5
    poses = _poses(az)
    n = noise.render(poses, poses.cameras(16, 16), generator=torch.Generator().manual_seed(1)).noise
    per_pixel_var = n.double().var(0)  # [16, 16, 3] over the poses
    k = n.shape[0]
    assert abs(float(per_pixel_var.mean()) - 1) < 5 * math.sqrt(2 / (k - 1)) / math.sqrt(16 * 3)
    assert abs(float(n.double().mean())) < 5 / math.sqrt(k * 3)


def test_one_pose_sees_one_field_where_the_cloud_covers_it():
    """Persistence: the same pose renders the same values on covered pixels whatever the generator
    (which fills only the uncovered ones); another run seed gives an independent field."""
    cloud, noise = _setup()
    poses = _poses([33.0])
    cams = poses.cameras(24, 24)
    a = noise.render(poses, cams, generator=torch.Generator().manual_seed(1))
    b = noise.render(poses, cams, generator=torch.Generator().manual_seed(2))
    cov = a.coverage[..., 0].bool()
    assert 0.3 < float(cov.float().mean()) and torch.equal(a.coverage, b.coverage)
    assert torch.equal(a.noise[cov], b.noise[cov])
    if bool((~cov).any()):
        assert not torch.equal(a.noise[~cov], b.noise[~cov])
    other = PoseLockedNoise(cloud, seed=999).render(poses, cams, generator=torch.Generator().manual_seed(1))
    r = torch.corrcoef(torch.stack([a.noise[cov].flatten(), other.noise[cov].flatten()]))[0, 1]
    assert abs(float(r)) < 0.2


def test_nearby_poses_share_noise_at_the_same_pixel_as_their_weights_say():
    """Image-locked sharing: the pixel-for-pixel correlation of two poses' fields on covered
    pixels, over 24 run seeds, matches sum_k a_k a'_k (the weights' own overlap, the oracle)."""
    for delta in (5.0, 10.0):
        poses = _poses([20.0, 20.0 + delta])
        cams = poses.cameras(16, 16)
        xs, ys = [], []
        for s in range(24):
            r = _setup(s)[1].render(poses, cams, generator=torch.Generator().manual_seed(s))
            cov = r.coverage[0, ..., 0].bool() & r.coverage[1, ..., 0].bool()
            xs.append(r.noise[0][cov].flatten())
            ys.append(r.noise[1][cov].flatten())
        x, y = torch.cat(xs).double(), torch.cat(ys).double()
        got = float((x * y).mean() / (x.std() * y.std()))
        want = _pose_corr((20.0, 10.0), (20.0 + delta, 10.0))
        assert abs(got - want) < 0.08, (delta, got, want)


def test_pose_locked_noise_has_the_spectrum_of_structured_noise():
    """The same correlation length (pixels) as the cloud rendered from the view's own camera:
    the canonical camera keeps the view's radius and field of view."""
    poses = _poses([70.0], el=20.0, fovy=45.0)
    cams = poses.cameras(48, 48)
    locked, structured, cover = [], [], []
    for s in range(6):
        cloud, noise = _setup(s)
        g = torch.Generator().manual_seed(s)
        r = noise.render(poses, cams, generator=g)
        locked.append(r.noise[0])
        colors = torch.randn(len(cloud), 3, generator=g)
        q = NoiseRenderer(cloud).render(colors, cams, generator=g)
        structured.append(q.noise[0])
        cover.append(r.coverage[0] * q.coverage[0])
    both = torch.stack(cover).prod(0)
    a = autocorrelation_length(torch.cat(locked, -1), both)
    b = autocorrelation_length(torch.cat(structured, -1), both)
    assert a > 1.0 and abs(a / b - 1) < 0.2, (a, b)


def test_a_pose_locked_source_persists_by_construction():
    with pytest.raises(ValueError, match=r"noise.redraw \(--noise-redraw\).*expected 'run', got 'step'"):
        NoiseConfig(source="pose", redraw="step")
    with pytest.raises(ValueError, match=r"noise\.source"):
        NoiseConfig(source="image")


def test_the_controls_measure_what_each_arm_keeps():
    """experiments.controls through the trainer's own noise path, one draw: structured noise
    (r = 1) persists at one pose and shares noise at one surface point 5 degrees away; redrawn
    every step it does neither across steps; pose-locked persists and shares more at the pixel
    than at the surface point."""
    from gdbench.experiments.controls import measure_arm
    from gdbench.priors.factory import make_prior
    from gdbench.train.config import preset

    prior = make_prior(preset("gd", prior="learned"))
    gd = measure_arm(prior, "gd", {}, 1.0, draws=1)
    step = measure_arm(prior, "gd-redraw-step", {}, 1.0, draws=1)
    locked = measure_arm(prior, "gd-pose-locked", {}, 1.0, draws=1)
    for row in (gd, step, locked):
        assert abs(row["variance"] - 1) < 0.25 and row["corr_length_px"] > 1.0
    assert gd["persist_lag100"] > 0.8 and gd["surface_5_next"] > 0.6
    assert abs(step["persist_lag1"]) < 0.15 and abs(step["surface_5_next"]) < 0.15
    assert locked["persist_lag100"] > 0.95 and locked["pixel_5_next"] > locked["surface_5_next"] + 0.1
