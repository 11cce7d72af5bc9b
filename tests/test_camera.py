"""Cameras: look_at, intrinsics, samplers, and the convention converters (OpenGL/pyrender,
Mitsuba, COLMAP), each checked against an independent projection."""

import math

import numpy as np
import pytest
import torch

from gdbench.core.camera import Cameras, SphericalPoses, intrinsics, look_at, rotmat_to_quat


def _cams(n=5, W=64, H=48, seed=0):
    g = torch.Generator().manual_seed(seed)
    poses = SphericalPoses.sample(n, generator=g, radius=(1.0, 2.0))
    return poses, poses.cameras(W, H)


def test_look_at_is_a_proper_rotation_and_sees_the_target():
    poses, cams = _cams()
    R = cams.viewmats[:, :3, :3].double()
    torch.testing.assert_close(
        R @ R.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(5, 3, 3), atol=1e-6, rtol=0
    )
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(5, dtype=torch.float64), atol=1e-6, rtol=0)
    uv, z = cams.project(torch.zeros(1, 3))
    torch.testing.assert_close(uv[:, 0], torch.tensor([32.0, 24.0]).expand(5, 2), atol=1e-4, rtol=0)
    torch.testing.assert_close(z[:, 0], poses.radius.float(), atol=1e-5, rtol=0)


def test_opencv_axes_world_up_is_image_up_and_right_is_right():
    cams = Cameras.from_look_at(torch.tensor([[2.0, 0.0, 0.0]]), 50.0, 64, 64)  # on +X, looking at -X
    uv, _ = cams.project(torch.tensor([[0.0, 0.0, 0.3], [0.0, 0.3, 0.0]]))
    assert float(uv[0, 0, 1]) < 32 - 5  # +Z (up) appears above the centre (smaller v)
    # looking along -X with +Z up, the camera's right is world +Y (right-handed)
    assert float(uv[0, 1, 0]) > 32 + 5
    torch.testing.assert_close(cams.centers, torch.tensor([[2.0, 0.0, 0.0]]))


def test_spherical_angles():
    p = SphericalPoses(
        torch.tensor([0.0, 90.0, 0.0]), torch.tensor([0.0, 0.0, 89.0]), torch.ones(3), torch.full((3,), 50.0)
    )
    c = p.cameras(32, 32).centers.double()
    torch.testing.assert_close(c[0], torch.tensor([1.0, 0.0, 0.0], dtype=torch.float64), atol=1e-6, rtol=0)
    torch.testing.assert_close(c[1], torch.tensor([0.0, 1.0, 0.0], dtype=torch.float64), atol=1e-6, rtol=0)
    assert float(c[2, 2]) == pytest.approx(math.sin(math.radians(89)), abs=1e-6)


def test_spherical_cameras_in_closed_form_equal_look_at():
    """Oracle: look_at of the eyes in float64. Poses below 89 degrees of elevation take the
    closed form; a batch holding one at 89.5 takes look_at itself (same bits)."""
    from gdbench.core.camera import spherical_to_eye

    g = torch.Generator().manual_seed(11)
    p = SphericalPoses.sample(500, generator=g, radius=(0.3, 4.0), elevation_range=(-88.9, 88.9))
    want = look_at(spherical_to_eye(p.azimuth, p.elevation, p.radius))
    torch.testing.assert_close(p.cameras(48, 32).viewmats.double(), want, atol=1e-6, rtol=0)
    steep = SphericalPoses(
        torch.tensor([10.0, 30.0]), torch.tensor([20.0, 89.5]), torch.tensor([1.0, 2.0]), torch.full((2,), 50.0)
    )
    want = look_at(spherical_to_eye(steep.azimuth, steep.elevation, steep.radius)).float()
    assert torch.equal(steep.cameras(32, 32).viewmats, want)


def test_straight_down_uses_a_fallback_up():
    v = look_at(torch.tensor([[0.0, 0.0, 2.0]]))
    R = v[0, :3, :3]
    torch.testing.assert_close(R @ R.T, torch.eye(3), atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="eye: coincides with target"):
        look_at(torch.zeros(1, 3))


def test_intrinsics_and_fov():
    K = intrinsics(60.0, 100, 80)
    assert float(K[1, 1]) == pytest.approx(40 / math.tan(math.radians(30)))
    assert (float(K[0, 2]), float(K[1, 2])) == (50.0, 40.0)
    cams = Cameras(torch.eye(4)[None], K[None], 100, 80)
    assert float(cams.fovy_deg()[0]) == pytest.approx(60.0, abs=1e-4)
    r = cams.resized(50, 40)
    assert float(r.fovy_deg()[0]) == pytest.approx(60.0, abs=1e-4) and float(r.Ks[0, 0, 2]) == 25.0
    with pytest.raises(ValueError, match="fovy_deg"):
        intrinsics(180.0, 10, 10)


def test_random_pose_sampler_ranges_uniformity_and_seed():
    from scipy import stats

    g = torch.Generator().manual_seed(1)
    p = SphericalPoses.sample(4000, generator=g, fovy_range=(40, 70), elevation_range=(-45, 45))
    assert float(p.azimuth.min()) >= -180 and float(p.azimuth.max()) <= 180
    assert float(p.elevation.abs().max()) <= 45 and float(p.fovy.min()) >= 40 and float(p.fovy.max()) <= 70
    assert stats.kstest(p.azimuth.numpy(), stats.uniform(-180, 360).cdf).pvalue > 1e-3
    assert stats.kstest(p.fovy.numpy(), stats.uniform(40, 30).cdf).pvalue > 1e-3
    a = SphericalPoses.sample(8, generator=torch.Generator().manual_seed(5))
    b = SphericalPoses.sample(8, generator=torch.Generator().manual_seed(5))
    c = SphericalPoses.sample(8, generator=torch.Generator().manual_seed(6))
    assert torch.equal(a.azimuth, b.azimuth) and not torch.equal(a.azimuth, c.azimuth)
    with pytest.raises(ValueError, match="elevation_range"):
        SphericalPoses.sample(2, generator=g, elevation_range=(-95, 0))
    with pytest.raises(ValueError, match="fovy_range: expected \\(low, high\\)"):
        SphericalPoses.sample(2, generator=g, fovy_range=(70, 40))


def test_nearby_pose_batches_stay_within_the_spread_and_keep_uniform_marginals():
    """spread_deg: poses after the first lie within +-spread of it in azimuth (circularly) and
    elevation, fold back into the ranges without piling at their ends (a uniform anchor plus a
    symmetric offset, reflected, is uniform again: KS test), and the first pose, radii and fovs
    are the independent sampler's draws from the same seed."""
    from scipy import stats

    s, n = 20.0, 4
    batches = [SphericalPoses.sample(n, generator=torch.Generator().manual_seed(k), spread_deg=s) for k in range(1500)]
    free = [SphericalPoses.sample(n, generator=torch.Generator().manual_seed(k)) for k in range(3)]
    for b, f in zip(batches, free):
        assert float(b.azimuth[0]) == float(f.azimuth[0]) and float(b.elevation[0]) == float(f.elevation[0])
        assert torch.equal(b.fovy, f.fovy) and torch.equal(b.radius, f.radius)
    az = torch.stack([b.azimuth for b in batches])
    el = torch.stack([b.elevation for b in batches])
    daz = (az[:, 1:] - az[:, :1] + 180.0) % 360.0 - 180.0
    assert float(daz.abs().max()) <= s + 1e-9 and float((el[:, 1:] - el[:, :1]).abs().max()) <= s + 1e-9
    assert float(daz.abs().max()) > 0.9 * s  # the offsets fill the spread
    assert float(az.min()) >= -180 and float(az.max()) <= 180 and float(el.abs().max()) <= 45
    assert stats.kstest(el[:, 1:].flatten().numpy(), stats.uniform(-45, 90).cdf).pvalue > 1e-3
    assert stats.kstest(az[:, 1:].flatten().numpy(), stats.uniform(-180, 360).cdf).pvalue > 1e-3
    # a part-circle azimuth range folds back too
    p = SphericalPoses.sample(6, generator=torch.Generator().manual_seed(0), azimuth_range=(-10, 10), spread_deg=90)
    assert float(p.azimuth.abs().max()) <= 10
    with pytest.raises(ValueError, match="spread_deg"):
        SphericalPoses.sample(2, generator=torch.Generator(), spread_deg=0.0)


def test_orbit_spacing():
    cams = SphericalPoses.orbit(100, radius=1.5, elevation=10.0).cameras(32, 32)
    c = cams.centers.double()
    torch.testing.assert_close(c.norm(dim=-1), torch.full((100,), 1.5, dtype=torch.float64), atol=1e-5, rtol=0)
    torch.testing.assert_close(
        c[:, 2], torch.full((100,), 1.5 * math.sin(math.radians(10)), dtype=torch.float64), atol=1e-5, rtol=0
    )
    az = torch.rad2deg(torch.atan2(c[:, 1], c[:, 0]))
    step = (az.roll(-1) - az + 180) % 360 - 180
    torch.testing.assert_close(step, torch.full((100,), 3.6, dtype=torch.float64), atol=1e-4, rtol=0)


def _points(n=20, seed=0):
    return torch.randn(n, 3, generator=torch.Generator().manual_seed(seed)) * 0.3


def test_opengl_converter_matches_pyrender_projection():
    """pyrender's IntrinsicsCamera projection matrix (written out here) with our GL pose."""
    _, cams = _cams(3, W=80, H=60)
    pose, K = cams.to_opengl()
    X = torch.cat([_points(), torch.ones(20, 1)], 1).double()
    uv, _ = cams.project(X[:, :3].float())
    W, H, n, f = 80, 60, 0.05, 100.0
    for i in range(3):
        fx, fy, cx, cy = K[i, 0, 0], K[i, 1, 1], K[i, 0, 2], K[i, 1, 2]
        P = torch.tensor(
            [
                [2 * fx / W, 0, 1 - 2 * cx / W, 0],
                [0, 2 * fy / H, 2 * cy / H - 1, 0],
                [0, 0, (f + n) / (n - f), 2 * f * n / (n - f)],
                [0, 0, -1, 0],
            ],
            dtype=torch.float64,
        )
        clip = (P @ torch.linalg.inv(pose[i].double()) @ X.T).T
        ndc = clip[:, :3] / clip[:, 3:]
        px = torch.stack([(ndc[:, 0] + 1) / 2 * W, (1 - ndc[:, 1]) / 2 * H], -1)
        torch.testing.assert_close(px.float(), uv[i], atol=1e-3, rtol=0)


def test_mitsuba_converter_axes_and_fov():
    _, cams = _cams(2)
    for i, m in enumerate(cams.to_mitsuba()):
        T = m["to_world"]
        c2w = torch.linalg.inv(cams.viewmats[i].double())
        torch.testing.assert_close(T[:3, 2], c2w[:3, 2])  # Mitsuba looks along its +Z = our forward
        torch.testing.assert_close(T[:3, 0], -c2w[:3, 0])  # Mitsuba +X is left
        torch.testing.assert_close(T[:3, 1], -c2w[:3, 1])  # Mitsuba +Y is up (ours is down)
        torch.testing.assert_close(T[:3, 3], c2w[:3, 3])
        assert m["fov"] == pytest.approx(float(cams.fovx_deg()[i]), abs=1e-4)
        assert m["principal_point_offset_x"] == pytest.approx(0.0, abs=1e-7)


def test_colmap_converter_with_pycolmap():
    pycolmap = pytest.importorskip("pycolmap")
    _, cams = _cams(3, W=80, H=60)
    X = _points().double()
    uv, _ = cams.project(X.float())
    for i, c in enumerate(cams.to_colmap()):
        q = c["qvec"].numpy()  # wxyz
        rig = pycolmap.Rigid3d(pycolmap.Rotation3d(np.array([q[1], q[2], q[3], q[0]])), c["tvec"].numpy())
        cam = pycolmap.Camera(model="PINHOLE", width=c["width"], height=c["height"], params=c["params"].numpy())
        pc = (rig.rotation.matrix() @ X.numpy().T).T + c["tvec"].numpy()
        px = cam.img_from_cam(pc)
        np.testing.assert_allclose(px, uv[i].numpy(), atol=2e-3)


def test_rotmat_to_quat_roundtrip():
    from renderers.splat.project import quat_to_rotmat

    q = torch.nn.functional.normalize(
        torch.randn(50, 4, generator=torch.Generator().manual_seed(0), dtype=torch.float64), dim=-1
    )
    R = quat_to_rotmat(q)
    back = torch.stack([rotmat_to_quat(r) for r in R])
    torch.testing.assert_close(back, q * torch.sign(q[:, :1]))


def test_cameras_validation():
    with pytest.raises(ValueError, match=r"Ks: expected shape \[2, 3, 3\]"):
        Cameras(torch.eye(4).expand(2, 4, 4), torch.eye(3)[None], 10, 10)
    with pytest.raises(ValueError, match="width: expected a positive int"):
        Cameras(torch.eye(4)[None], torch.eye(3)[None], 0, 10)
