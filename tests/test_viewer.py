"""The browser viewer (gdbench/app/viewer.py, docs/viewer.md): what viser receives (covariances,
colours, turntable and training cameras) checked without a browser, and a slow end-to-end test
that drives Debian's headless Chromium and compares its screenshot with our own render."""

from __future__ import annotations

import math
import socket
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from gdbench.app.viewer import (
    NUDGE,
    import_viser,
    resolve_inputs,
    splat_arrays,
    training_cameras,
    turntable_cameras,
    up_rotation,
    viser_pose,
)
from gdbench.core.builtin import demo_scene
from gdbench.core.camera import SphericalPoses
from gdbench.core.scene import GaussianScene
from gdbench.core.turntable import RUN_TURNTABLE, render_views_alpha
from renderers.splat.sh import C0

CHROMIUM = Path("/usr/bin/chromium")


def _random_scene(n: int = 64, seed: int = 0, scale=(3e-4, 7e-2)) -> GaussianScene:
    g = torch.Generator().manual_seed(seed)
    quats = torch.randn(n, 4, generator=g, dtype=torch.float64) * 3
    quats[0] = 0.0  # a zero quaternion means the identity
    log_s = math.log(scale[0]) + (math.log(scale[1]) - math.log(scale[0])) * torch.rand(n, 3, generator=g)
    sh = torch.randn(n, 1, 3, generator=g, dtype=torch.float64) * 2.5  # some colours clip
    return GaussianScene(
        torch.randn(n, 3, generator=g, dtype=torch.float64) * 0.3,
        quats,
        log_s.double(),
        torch.randn(n, generator=g, dtype=torch.float64) * 2,
        sh,
    )


# ------------------------------------------------------------------ fast: what viser receives
def test_splats_are_the_closed_form_covariances_dc_colours_and_opacities():
    from scipy.spatial.transform import Rotation

    scene = _random_scene()
    s = splat_arrays(scene)
    q = scene.quats.numpy().copy()
    q[0] = (1.0, 0.0, 0.0, 0.0)
    R = Rotation.from_quat(q[:, [1, 2, 3, 0]]).as_matrix()  # scipy: xyzw, normalises
    S2 = np.exp(2 * scene.log_scales.numpy())
    sigma = np.einsum("nij,nj,nkj->nik", R, S2, R)  # R diag(s^2) R^T, float64
    v = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)
    nudged = sigma + NUDGE * (S2.sum(1) / 3)[:, None, None] * np.outer(v, v)
    assert s.covariances.dtype == s.centers.dtype == s.rgbs.dtype == s.opacities.dtype == np.float32
    assert s.covariances.shape == (64, 3, 3) and s.opacities.shape == (64, 1)
    np.testing.assert_allclose(s.world_covariances(), nudged, rtol=1e-6, atol=1e-6 * S2.max())
    assert (np.abs(s.world_covariances() - sigma).max(axis=(1, 2)) <= 1.01e-3 * S2.mean(1) * v.max() ** 2).all()
    np.testing.assert_allclose(s.centers * s.scale, scene.means.numpy(), rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(s.rgbs, np.clip(C0 * scene.sh[:, 0].numpy() + 0.5, 0, 1), atol=1e-6)
    assert (s.rgbs == 0).any() and (s.rgbs == 1).any()  # the clip is exercised
    np.testing.assert_allclose(s.opacities[:, 0], 1 / (1 + np.exp(-scene.opacity_logits.numpy())), atol=1e-6)
    # viser sends the covariances as float16: the node scale (a power of two near the median
    # standard deviation) keeps a trained scene's variances (std 3e-4 .. 7e-2) in float16's normal
    # range, where the world variances alone are mostly subnormal
    assert math.log2(s.scale) == round(math.log2(s.scale))
    diag = np.diagonal(s.covariances, axis1=1, axis2=2).astype(np.float64)
    rel = np.abs(diag.astype(np.float16).astype(np.float64) - diag) / diag
    assert rel.max() < 1e-3
    raw = np.diagonal(sigma, axis1=1, axis2=2)
    assert (raw < np.finfo(np.float16).tiny).mean() > 0.3


def test_nudge_makes_the_screen_covariance_of_a_centred_gaussian_non_diagonal():
    """viser drops a splat whose 2D covariance is exactly diagonal with the long axis horizontal
    (``NUDGE``): an isotropic Gaussian at the origin seen from turntable view 0 is one."""
    scene = GaussianScene.from_activated(
        torch.zeros(1, 3), torch.full((1, 3), 0.05), torch.full((1,), 0.9), torch.full((1, 3), 0.5)
    )
    cams = turntable_cameras(36, 64)
    nudged = splat_arrays(scene).world_covariances()[0]
    for k in (0, 9, 18):
        # at the image centre the projection's Jacobian is diag(f/z, f/z): the 2D covariance's
        # off-diagonal term is the camera-space covariance's
        Wr = cams.viewmats[k, :3, :3].double().numpy()
        assert abs((Wr @ (0.05**2 * np.eye(3)) @ Wr.T)[0, 1]) < 1e-15
        assert abs((Wr @ nudged @ Wr.T)[0, 1]) > 1e-1 * NUDGE * 0.05**2


def test_turntable_views_are_the_runs_turntable_cameras():
    """The slider's views are write_turntable's cameras with the run's orbit (radius 1.3,
    elevation 15, fovy 45: train.run), and viser's camera built from (position, look_at, up) is
    exactly that camera (viser's own look-at maths when viser is installed)."""
    assert RUN_TURNTABLE == {"radius": 1.3, "elevation": 15.0, "fovy": 45.0}
    cams = turntable_cameras(36, 64, 48)
    ref = SphericalPoses.orbit(36, radius=1.3, elevation=15.0, fovy=45.0).cameras(64, 48)
    torch.testing.assert_close(cams.viewmats, ref.viewmats, rtol=0, atol=0)
    torch.testing.assert_close(cams.Ks, ref.Ks, rtol=0, atol=0)
    for k in (0, 7, 20):
        p = viser_pose(cams, k)
        c2w = torch.linalg.inv(cams.viewmats[k].double()).numpy()
        np.testing.assert_allclose(p.position, c2w[:3, 3], atol=1e-6)
        az, el = math.radians(10.0 * k), math.radians(15.0)
        eye = 1.3 * np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
        np.testing.assert_allclose(p.position, eye, atol=1e-6)
        np.testing.assert_allclose(p.look_at, 0.0, atol=1e-6)
        np.testing.assert_allclose(p.up, [0, 0, 1])
        assert p.fov == pytest.approx(math.radians(45.0))
        _check_viser_orientation(p, c2w[:3, :3])


def _check_viser_orientation(p, R_expected: np.ndarray) -> None:
    """viser's camera orientation from (position, look_at, up) (its CameraHandle maths) and our
    wxyz both equal the expected camera-to-world rotation (OpenCV axes)."""
    from scipy.spatial.transform import Rotation

    R_ours = Rotation.from_quat(np.roll(p.wxyz, -1)).as_matrix()
    np.testing.assert_allclose(R_ours, R_expected, atol=1e-6)
    try:
        viser = import_viser()
    except ImportError:
        return
    from viser._viser import CameraHandle, _CameraHandleState

    handle = CameraHandle.__new__(CameraHandle)
    handle._state = _CameraHandleState(
        client=None,
        wxyz=np.array([1.0, 0, 0, 0]),
        position=np.asarray(p.position, dtype=np.float64),
        fov=p.fov,
        image_height=1,
        image_width=1,
        near=0.01,
        far=100.0,
        min_orbit_distance=0.01,
        max_orbit_distance=1e4,
        look_at=np.asarray(p.look_at, dtype=np.float64),
        up_direction=np.asarray(p.up, dtype=np.float64),
        update_timestamp=1.0,
        camera_cb=[],
    )
    handle._update_wxyz()
    R_viser = viser.transforms.SO3(handle._state.wxyz).as_matrix()
    np.testing.assert_allclose(R_viser, R_expected, atol=1e-6)


@pytest.mark.parametrize("up", ["+z", "-y", "+x", "-z", (1.0, 2.0, 2.0)])
def test_up_direction_turns_the_cameras(up):
    Rup = up_rotation(up)
    np.testing.assert_allclose(Rup @ Rup.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(Rup) == pytest.approx(1.0)
    cams = turntable_cameras(8, 32)
    p = viser_pose(cams, 3, Rup)
    u = {"+z": (0, 0, 1), "-y": (0, -1, 0), "+x": (1, 0, 0), "-z": (0, 0, -1)}.get(up, (1 / 3, 2 / 3, 2 / 3))
    np.testing.assert_allclose(Rup[:, 2], u, atol=1e-12)
    np.testing.assert_allclose(p.up, u, atol=1e-12)
    assert float(p.position @ np.asarray(u)) == pytest.approx(1.3 * math.sin(math.radians(15.0)))
    c2w = torch.linalg.inv(cams.viewmats[3].double()).numpy()
    _check_viser_orientation(p, Rup @ c2w[:3, :3])


def test_training_frustums_are_the_runs_own_views_within_its_ranges():
    """The frustums are the trainer's draws (train.views.sample_views on the run's ``views``
    stream), step by step, and lie in the run's radius, fov, azimuth and elevation ranges."""
    from gdbench.train.config import TrainConfig
    from gdbench.train.outputs import config_dict
    from gdbench.train.streams import make_streams
    from gdbench.train.views import ViewsConfig, sample_views

    cfg = TrainConfig(
        seed=3,
        steps=40,
        resolution=32,
        views=ViewsConfig(per_step=2),
        camera_radius=1.2,
        fovy_range=(42.0, 55.0),
        azimuth_range=(-90.0, 60.0),
        elevation_range=(-5.0, 30.0),
    )
    config = config_dict(cfg)
    cams, steps = training_cameras(config, 40, max_views=10)
    assert steps == list(range(0, 40, 4)) and len(cams) == 10
    ctx = SimpleNamespace(cfg=cfg, factor=1, mode="rgb", sigmas=torch.tensor([0.1, 1.0]), sigma_values=[0.1, 1.0],
                          device=torch.device("cpu"))  # fmt: skip
    state = SimpleNamespace(streams=make_streams(3), step=0)
    trainer = []
    for step in range(40):
        state.step = step
        trainer.append(sample_views(ctx, state).cams.viewmats[0])
    torch.testing.assert_close(cams.viewmats, torch.stack(trainer)[steps], rtol=0, atol=0)
    for i in range(len(cams)):
        p = viser_pose(cams, i)
        r = float(np.linalg.norm(p.position))
        assert r == pytest.approx(1.2, abs=1e-5)
        el = math.degrees(math.asin(p.position[2] / r))
        az = math.degrees(math.atan2(p.position[1], p.position[0]))
        assert -5.0 - 1e-4 <= el <= 30.0 + 1e-4 and -90.0 - 1e-4 <= az <= 60.0 + 1e-4
        assert 42.0 - 1e-4 <= math.degrees(p.fov) <= 55.0 + 1e-4
        np.testing.assert_allclose(p.look_at, 0.0, atol=1e-5)
        _check_viser_orientation(p, torch.linalg.inv(cams.viewmats[i].double()).numpy()[:3, :3])


def test_inputs_run_folder_ply_and_errors(tmp_path):
    from gdbench.core.io import sha256_file, write_json

    scene = _random_scene(8).to(dtype=torch.float32)
    ply = scene.save_ply(tmp_path / "scene.ply")
    write_json({"config": {"seed": 0}, "steps": 3, "scene_sha256": sha256_file(ply)}, tmp_path / "run.json")
    for src in (tmp_path, ply):  # the folder, or its scene.ply: the run.json of the same scene
        s, name, run = resolve_inputs(src, None)
        assert len(s) == 8 and name.endswith("scene.ply") and run["steps"] == 3
    write_json({"config": {"seed": 0}, "steps": 3, "scene_sha256": "0" * 64}, tmp_path / "run.json")
    assert resolve_inputs(tmp_path, None)[2] is None  # a run.json of another scene
    with pytest.raises(FileNotFoundError, match="run folder"):
        resolve_inputs(tmp_path / "missing", None)
    write_json({"steps": 3}, tmp_path / "bad.json")
    with pytest.raises(ValueError, match="no 'config'"):
        resolve_inputs(scene, tmp_path / "bad.json")
    with pytest.raises(ValueError, match="config has no 'camera_radius'"):
        training_cameras({"seed": 0}, 3)


def test_a_ply_from_elsewhere_is_framed():
    """A scene off the origin and larger than a run's: the turntable orbits its bounds' centre at
    the distance that shows it whole (``framing``), and every view looks at that centre."""
    from gdbench.app.viewer import framed_orbit
    from gdbench.core.framing import bounds, orbit_radius

    scene = _random_scene(200, scale=(0.01, 0.05))
    scene = GaussianScene(
        scene.means * 10 + torch.tensor([5.0, -3.0, 2.0], dtype=torch.float64),
        *[getattr(scene, k) for k in ("quats", "log_scales", "opacity_logits", "sh")],
    )
    centre, radius = framed_orbit(scene)
    c, r = bounds(scene)
    np.testing.assert_allclose(centre, c.numpy())
    assert radius == pytest.approx(orbit_radius(r, 45.0))
    cams = turntable_cameras(12, 64, radius=radius)
    Rup = up_rotation("-y")
    for k in (0, 4):
        p = viser_pose(cams, k, Rup, centre)
        np.testing.assert_allclose(p.look_at, centre, atol=1e-6 * radius)  # float32 viewmats
        assert np.linalg.norm(p.position - centre) == pytest.approx(radius)
        assert float((p.position - centre) @ np.array([0, -1.0, 0])) == pytest.approx(
            radius * math.sin(math.radians(15))
        )
        _check_viser_orientation(p, Rup @ torch.linalg.inv(cams.viewmats[k].double()).numpy()[:3, :3])


def test_serve_without_a_browser(tmp_path):
    """The server side: a run folder gives the run's turntable frame count and its frustums; the
    slider and the checkbox drive them; a lone scene has the checkbox disabled."""
    pytest.importorskip("viser", reason="the viewer needs viser: pip install -e '.[view]' (or make setup)")
    from gdbench.app.viewer import serve
    from gdbench.core.io import sha256_file, write_json
    from gdbench.train.config import TrainConfig
    from gdbench.train.outputs import config_dict

    scene = demo_scene(50)
    ply = scene.save_ply(tmp_path / "scene.ply")
    config = config_dict(TrainConfig(steps=30, turntable_frames=12))
    write_json({"config": config, "steps": 30, "scene_sha256": sha256_file(ply)}, tmp_path / "run.json")
    viewer = serve(tmp_path, port=_free_port(), block=False, view=3, verbose=False)
    try:
        assert len(viewer.poses) == 12 and viewer.frustum_steps == list(range(30)) and viewer.radius == 1.3
        assert viewer.slider.value == 3 and not viewer.checkbox.value and not viewer.frustums.visible
        np.testing.assert_allclose(viewer.server.initial_camera.position, viewer.poses[3].position)
        viewer.show_frustums(True)
        assert viewer.frustums.visible
        viewer.show_view(-1)
        assert viewer.slider.value == 11 and "azimuth -30°" in viewer._info.content
    finally:
        viewer.stop()
    viewer = serve(scene, port=_free_port(), block=False, frustums=True, verbose=False)
    try:
        assert len(viewer.poses) == 36 and viewer.frustum_steps == [] and viewer.frustums is None
        assert viewer.checkbox.disabled and not viewer.checkbox.value and viewer.radius == 1.3
    finally:
        viewer.stop()
    (tmp_path / "run.json").unlink()  # now a PLY from elsewhere: framed from its bounds
    viewer = serve(ply, port=_free_port(), block=False, verbose=False)
    try:
        assert viewer.radius != 1.3 and viewer.frustum_steps == []
    finally:
        viewer.stop()
    with pytest.raises(ValueError, match="turntable view"):
        serve(scene, view=36, block=False, verbose=False)


def test_missing_viser_says_what_to_install(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "viser", None)
    with pytest.raises(ImportError, match=r"pip install -e '\.\[view\]'.*make setup"):
        import_viser()


# ------------------------------------------------------------ slow: the browser's pixels
W, H = 480, 360
"""Browser viewport (CSS pixels, device pixel ratio fixed at 1): 4:3, so the horizontal fov is
the browser's, as in our render of the same vertical fov."""

CHROME_ARGS = [
    "--headless",
    "--no-sandbox",
    "--disable-gpu",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--no-first-run",
    "--use-angle=swiftshader",  # WebGL2 on the CPU
    "--enable-unsafe-swiftshader",
]
HIDE_OVERLAYS = "body * { visibility: hidden !important; } canvas { visibility: visible !important; }"
"""Leaves the WebGL canvas alone on the page (the GUI panel and notifications float over it)."""


def _test_scene() -> GaussianScene:
    """The demo torus and ball (flat, rotated, opaque, hue-striped) with three thin coloured
    arms along +X (red), +Y (green) and +Z (blue): 420 Gaussians, no symmetry left, anisotropic
    Gaussians whose variances are float16-subnormal in world units."""
    base = demo_scene(300)
    t = torch.linspace(0.25, 0.55, 40)
    arms = []
    for axis, colour in ((0, (0.9, 0.1, 0.1)), (1, (0.1, 0.8, 0.1)), (2, (0.1, 0.2, 0.9))):
        means = torch.zeros(40, 3)
        means[:, axis] = t
        scales = torch.full((40, 3), 0.005)
        scales[:, axis] = 0.012  # elongated along the arm
        arms.append(
            GaussianScene.from_activated(means, scales, torch.full((40,), 0.9), torch.tensor(colour).expand(40, 3))
        )
    return GaussianScene.cat([base, *arms])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _settled(page, previous: np.ndarray | None, deadline: float) -> np.ndarray:
    """Screenshots every 0.25 s until splats are drawn (over 1% of the pixels off the white
    background) and two consecutive ones agree (viser fades splats in and eases its camera)."""
    import io

    from PIL import Image

    last = None
    while time.monotonic() < deadline:
        img = np.asarray(Image.open(io.BytesIO(page.screenshot())).convert("RGB"), dtype=np.float64) / 255
        drawn = (np.abs(img - 1).max(-1) > 0.1).mean() > 0.01
        moved = previous is None or np.abs(img - previous).mean() > 0.01
        if drawn and moved and last is not None and np.abs(img - last).mean() < 2e-4:
            return img
        last = img
        time.sleep(0.25)
    raise AssertionError("the viewer drew no (settled) splats before the timeout")


def _agreement(shot: np.ndarray, render: np.ndarray) -> dict:
    mse = float(((shot - render) ** 2).mean())
    a, b = np.abs(shot - 1).max(-1) > 0.1, np.abs(render - 1).max(-1) > 0.1
    return {
        "psnr": -10 * math.log10(max(mse, 1e-12)),
        "mae": float(np.abs(shot - render).mean()),
        "iou": float((a & b).sum() / max((a | b).sum(), 1)),
    }


@pytest.mark.slow
def test_browser_screenshot_matches_our_render(tmp_path):
    """Headless Chromium (SwiftShader WebGL2) shows turntable view 0, then view 5 after the GUI's
    slider moves; each screenshot is compared with ``rasterize`` of the same camera (480 x 360,
    vertical fov 45, white background).

    Measured (viser 1.1.1, Chromium 156 with SwiftShader, this 2-core machine; identical over 3
    runs): right camera PSNR 41.5 / 42.0 dB (views 0 / 5), mean absolute error 0.0037 / 0.0035,
    silhouette IoU 0.972 / 0.977; one turntable step (10 degrees) off 23.4 / 22.8 dB; rotated by
    90 degrees 15.8 / 15.5 dB (IoU 0.92); mirrored left-right 15.7 / 15.4 dB. Without
    ``viewer.NUDGE`` view 0 loses half of the green arm: 34.9 dB. viser's renderer approximates
    ours (2.83-sigma cut-off, alpha cut at 0.01 instead of 1/255, no 0.99 opacity clamp, 8-bit
    colours, float16 covariances, a 16-bit depth sort) with the same 0.3 px^2 screen-space
    dilation and no sRGB curve. Floors: PSNR >= 37 dB, MAE <= 0.006, IoU >= 0.95, and the right
    camera beats the 90-degree one and the mirrored screenshot by >= 15 dB. Run time 7-10 s.
    """
    pytest.importorskip("viser", reason="the viewer needs viser: pip install -e '.[view]' (or make setup)")
    sync_api = pytest.importorskip("playwright.sync_api", reason="playwright's package: pip install -e '.[test]'")
    if not CHROMIUM.exists():
        pytest.skip(f"no browser at {CHROMIUM}: apt-get install chromium (scripts/setup.sh, make test-slow)")
    import imageio.v3 as iio

    from gdbench.app.viewer import serve

    scene = _test_scene()
    frames = 36
    cams = turntable_cameras(frames, W, H)
    viewer = serve(scene, port=_free_port(), block=False, view=0, verbose=False)
    try:
        with sync_api.sync_playwright() as pw:
            context = pw.chromium.launch_persistent_context(
                str(tmp_path / "profile"),
                executable_path=str(CHROMIUM),
                headless=True,
                args=CHROME_ARGS,
                viewport={"width": W, "height": H},
                device_scale_factor=1,
            )
            try:
                page = context.new_page()
                page.goto(viewer.url + "/?fixedDpr=1", timeout=60_000)
                page.wait_for_selector("canvas", timeout=60_000)
                page.add_style_tag(content=HIDE_OVERLAYS)
                shots = {0: _settled(page, None, time.monotonic() + 90)}
                viewer.show_view(5)
                shots[5] = _settled(page, shots[0], time.monotonic() + 60)
            finally:
                context.close()
    finally:
        viewer.stop()

    renders = render_views_alpha(scene, cams)[0].double().numpy()
    for k, shot in shots.items():
        right = _agreement(shot, renders[k])
        turned = _agreement(shot, renders[(k + frames // 4) % frames])
        mirrored = _agreement(shot[:, ::-1], renders[k])
        step = _agreement(shot, renders[(k + 1) % frames])
        side_by_side = np.concatenate([shot, renders[k]], axis=1)
        iio.imwrite(tmp_path / f"view{k}_browser_vs_ours.png", (side_by_side * 255 + 0.5).astype(np.uint8))
        msg = (
            f"view {k} (images in {tmp_path}): right {right}, one step (10 degrees) off {step}, "
            f"rotated 90 degrees {turned}, mirrored {mirrored}"
        )
        print(msg)
        assert right["psnr"] >= 37.0 and right["mae"] <= 0.006 and right["iou"] >= 0.95, msg
        assert right["psnr"] - turned["psnr"] >= 15.0 and right["psnr"] - mirrored["psnr"] >= 15.0, msg


def test_view_ends_on_sigterm_with_one_line_and_143(tmp_path):
    """`gdbench view` in a separate process, sent SIGTERM once it serves: the one line and exit
    code 128 + 15 that every other command gives (the viewer used to swallow it and exit 0)."""
    pytest.importorskip("viser", reason="the viewer needs viser: pip install -e '.[view]' (or make setup)")
    import os
    import signal
    import subprocess
    import sys
    import time

    ply = demo_scene(50).save_ply(tmp_path / "scene.ply")
    root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
    proc = subprocess.Popen([sys.executable, "-m", "gdbench.app.cli", "view", str(ply), "--port", str(_free_port())],
                            cwd=root, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        deadline = time.time() + 120
        line = ""
        while "gdbench view:" not in line and time.time() < deadline and proc.poll() is None:
            line = proc.stdout.readline()
        assert "gdbench view:" in line, line
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=60)
    finally:
        proc.kill()
    assert proc.returncode == 128 + signal.SIGTERM, err
    assert err.strip().splitlines()[-1] == "gdbench view: error: interrupted by SIGTERM", err


def test_a_host_this_machine_cannot_listen_on_is_refused_at_once(tmp_path):
    """viser takes any OSError for a busy port and tries the next, forever: the address is checked
    first, naming --host."""
    from gdbench.app.viewer import serve
    from gdbench.core.builtin import demo_scene

    demo_scene(50, seed=0).save_ply(tmp_path / "s.ply")
    for host in ("999.1.1.1", "8.8.8.8"):
        with pytest.raises(ValueError, match=r"host \(--host\): cannot listen on"):
            serve(tmp_path / "s.ply", host=host, block=False, verbose=False)
