"""COLMAP multi-view consistency of a generated object (our definition; the paper's and
3DFuse's exact variance is not published).

Render K views on one circle (fixed radius and elevation, 360/K degrees apart, default K = 100
at 256 px), run COLMAP on CPU (pycolmap: SIFT, exhaustive matching, incremental mapping with
one PINHOLE camera whose known intrinsics stay fixed; one thread, so a scene's score is
reproducible), take the largest model, align it to the
true cameras by a similarity (Umeyama on camera centres) and report:

- ``registration_rate``: registered views / K (always reported: variance alone misses views
  that fail to register);
- ``var_theta_deg2`` (headline): the variance of the rotation angle between adjacent registered
  views (truth: 360/K degrees for every pair). A consistent object gives a tight spread; a
  multi-faced or view-inconsistent one makes COLMAP jump or break the loop;
- ``mean_theta_deg``: their mean;
- ``translation_dir_err_deg``: mean angle between estimated and true directions of adjacent
  camera-centre steps, after the alignment.
"""

from __future__ import annotations

import math
import os
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from ..camera import Cameras, SphericalPoses

THREADS = 1
"""COLMAP's threads in every stage. One makes a scene's score reproducible: with two, the same
scene's Var(theta) read 1.9-2.5 and once 7.6 over seven runs (SIFT extraction, matching and the
mapper each change the result when threaded; measured in docs/performance.md), and a sweep runs
its cells on one core each anyway."""

FAIL_DEG = 5.0
"""An adjacent pair whose relative rotation is off the truth by more than this fails."""


@dataclass(frozen=True)
class ColmapScore:
    views: int
    registered: int
    registration_rate: float
    var_theta_deg2: float
    mean_theta_deg: float
    translation_dir_err_deg: float
    points3d: int
    seconds: float
    failure_rate: float = float("nan")
    """Share of the K adjacent pairs (i, i+1 around the circle) that are unregistered (either view)
    or whose relative rotation is off the truth by more than 5 degrees: unlike Var(theta), it
    counts the views that never registered."""

    def as_dict(self) -> dict:
        return asdict(self)


def circle_poses(k: int = 100, radius: float = 1.2, elevation: float = 15.0, fovy: float = 50.0) -> SphericalPoses:
    return SphericalPoses.orbit(k, radius=radius, elevation=elevation, fovy=fovy)


def _import_pycolmap():
    # COLMAP logs every image it reads to stderr (glog); keep warnings and errors only
    os.environ.setdefault("GLOG_minloglevel", "1")
    try:
        import pycolmap
    except ImportError as e:
        raise ImportError("COLMAP scoring needs pycolmap: pip install pycolmap==4.2.1 (CPU wheels)") from e
    try:
        pycolmap.logging.minloglevel = int(os.environ["GLOG_minloglevel"])
    except (AttributeError, ValueError):
        pass
    return pycolmap


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising |s R src + t - dst|^2 over point pairs [n, 3]."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / max(var, 1e-12))
    return s, R, mu_d - s * R @ mu_s


def _angle_deg(R: np.ndarray) -> float:
    return math.degrees(math.acos(float(np.clip((np.trace(R) - 1) / 2, -1.0, 1.0))))


def score_images(
    images: np.ndarray,
    cams: Cameras,
    workdir: str | Path | None = None,
    *,
    seed: int = 0,
    max_image_size: int = 512,
    log: str | Path | None = None,
    phase=None,
) -> ColmapScore:
    """Run COLMAP on uint8 images [K, H, W, 3] taken (in order around the circle) by ``cams``.
    COLMAP's own output goes to ``log`` (appended; None: discarded), not the console; ``phase``
    (optional) is called with the name of each stage as it starts."""
    t0 = time.perf_counter()
    est, points = _reconstruct(images, cams, workdir, seed=seed, max_image_size=max_image_size, log=log, phase=phase)
    return _score(est, points, cams, time.perf_counter() - t0)


def _reconstruct(images, cams: Cameras, workdir, *, seed: int, max_image_size: int, log=None, phase=None):
    """COLMAP's estimate of each registered view: {index: (rotation, camera centre)}, and the
    number of 3D points, from SIFT, exhaustive matching and incremental mapping with the known
    PINHOLE intrinsics held fixed (the largest model)."""
    from PIL import Image

    from ..io import captured_output

    pycolmap = _import_pycolmap()
    phase = phase or (lambda name: None)
    K = len(cams)
    with tempfile.TemporaryDirectory() as tmp:
        root = Path(workdir) if workdir is not None else Path(tmp)
        img_dir, out_dir = root / "images", root / "sparse"
        img_dir.mkdir(parents=True, exist_ok=True)
        out_dir.mkdir(parents=True, exist_ok=True)
        # BMP: the same pixels as PNG, written 5x faster, and no zlib: a process that imported
        # pycolmap before Pillow's zlib encoder crashed in it (double free in deflateEnd)
        names = [f"{i:04d}.bmp" for i in range(K)]
        for name, im in zip(names, images):
            Image.fromarray(np.ascontiguousarray(im)).save(img_dir / name)
        db = root / "database.db"
        if db.exists():
            db.unlink()
        fx, fy, cx, cy = (float(v) for v in cams.Ks[0, [0, 1, 0, 1], [0, 1, 2, 2]])
        reader = pycolmap.ImageReaderOptions()
        reader.camera_model = "PINHOLE"
        reader.camera_params = f"{fx},{fy},{cx},{cy}"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.max_image_size = max_image_size
        extraction.num_threads = THREADS
        opts = pycolmap.IncrementalPipelineOptions()
        opts.ba_refine_focal_length = False
        opts.ba_refine_principal_point = False
        opts.ba_refine_extra_params = False
        opts.num_threads = THREADS
        opts.random_seed = seed
        phase("COLMAP features")
        with captured_output(log):
            pycolmap.extract_features(
                db,
                img_dir,
                image_names=names,
                camera_mode=pycolmap.CameraMode.SINGLE,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
        phase("COLMAP matching")
        with captured_output(log):
            matching = pycolmap.FeatureMatchingOptions()
            matching.num_threads = THREADS
            pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        phase("COLMAP mapping")
        with captured_output(log):
            models = pycolmap.incremental_mapping(db, img_dir, out_dir, options=opts)
    if not models:
        return {}, 0
    rec = max(models.values(), key=lambda r: r.num_reg_images())
    est: dict[int, tuple[np.ndarray, np.ndarray]] = {}
    for image in rec.images.values():
        if image.has_pose:
            pose = image.cam_from_world()
            R = np.asarray(pose.rotation.matrix())
            est[int(Path(image.name).stem)] = (R, -R.T @ np.asarray(pose.translation))  # rotation, centre
    return est, int(rec.num_points3D())


def _score(est: dict, points: int, cams: Cameras, seconds: float) -> ColmapScore:
    """Registration, Var(theta) of adjacent steps, failure rate and translation-direction error
    of COLMAP's estimates against the true cameras (Sim(3)-aligned on the centres)."""
    K = len(cams)
    gt_c = cams.centers.double().numpy()
    gt_R = cams.viewmats[:, :3, :3].double().numpy()
    reg = sorted(est)
    failures = 0
    for i in range(K):
        j = (i + 1) % K
        if i not in est or j not in est:
            failures += 1
            continue
        truth = _angle_deg(gt_R[j] @ gt_R[i].T)
        failures += abs(_angle_deg(est[j][0] @ est[i][0].T) - truth) > FAIL_DEG
    thetas, dir_errs = [], []
    if len(reg) >= 3:
        s, Ra, _ = umeyama(np.stack([est[i][1] for i in reg]), gt_c[reg])  # relative steps need no t
        for i in reg:
            j = (i + 1) % K
            if j not in est:
                continue
            thetas.append(_angle_deg(est[j][0] @ est[i][0].T))
            step = s * Ra @ (est[j][1] - est[i][1])
            true = gt_c[j] - gt_c[i]
            cos = float(step @ true / max(np.linalg.norm(step) * np.linalg.norm(true), 1e-12))
            dir_errs.append(math.degrees(math.acos(max(-1.0, min(1.0, cos)))))
    th = np.asarray(thetas)
    return ColmapScore(
        views=K,
        registered=len(reg),
        registration_rate=len(reg) / K,
        var_theta_deg2=float(th.var()) if len(th) >= 2 else float("nan"),
        mean_theta_deg=float(th.mean()) if len(th) else float("nan"),
        translation_dir_err_deg=float(np.mean(dir_errs)) if dir_errs else float("nan"),
        points3d=points,
        seconds=seconds,
        failure_rate=failures / K,
    )


def score_scene(
    scene,
    *,
    views: int = 100,
    size: int = 256,
    workdir=None,
    seed: int = 0,
    background=(1.0, 1.0, 1.0),
    log=None,
    phase=None,
    **pose_kw,
) -> ColmapScore:
    """Render a GaussianScene on the circle (on ``background``, a run's own) and score it
    (``log``, ``phase``: as ``score_images``)."""
    from ..turntable import render_views, to_uint8

    cams = circle_poses(views, **pose_kw).cameras(size, size)
    if phase is not None:
        phase("COLMAP views")
    images = to_uint8(render_views(scene, cams, background=background))
    return score_images(images, cams, workdir, seed=seed, log=log, phase=phase)


def asset_circle_images(
    caption: str, cams: Cameras, *, mode: str = "consistent", seed: int = 0, jitter_deg: float = 12.0
) -> np.ndarray:
    """Calibration images of a procedural asset on the circle, uint8 [K, H, W, 3].

    ``consistent``: the asset as it is; ``jittered``: every view sees the asset turned by a
    random angle (uniform +-``jitter_deg``) about +Z, which no single scene renders (the failures
    a scene can show are ``fixture_circle_images``').
    """
    from renderers.pyrender_points.mesh import render_mesh

    from ..assets.library import build

    if mode not in ("consistent", "jittered"):
        raise ValueError(f"mode: expected 'consistent' or 'jittered', got {mode!r}")
    mesh = build(caption)
    pose_gl, Ks = cams.to_opengl()
    g = torch.Generator().manual_seed(seed)
    poses = []
    for i in range(len(cams)):
        turn = float((torch.rand(1, generator=g) * 2 - 1) * jitter_deg) if mode == "jittered" else 0.0
        c, s = math.cos(math.radians(turn)), math.sin(math.radians(turn))
        Rz = np.array([[c, -s, 0, 0], [s, c, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]])
        # turning the object by Rz is turning the camera by Rz^-1 about the origin
        poses.append(np.linalg.inv(Rz) @ pose_gl[i].double().numpy())
    rgb, _, _ = render_mesh(mesh, np.stack(poses), Ks.double().numpy(), cams.width, cams.height)
    return (np.clip(rgb, 0, 1) * 255 + 0.5).astype(np.uint8)


FIXTURES = ("asset", "flicker", "floaters", "two-faced")


def fixture_circle_images(caption: str, cams: Cameras, kind: str, *, seed: int = 0, flicker: float = 0.2) -> np.ndarray:
    """Calibration images of a 3D failure fixture (``metrics/fixtures3d.py``) on the circle,
    rendered by gdbench's splatting renderer, uint8 [K, H, W, 3]: ``asset``, ``floaters`` and
    ``two-faced`` are the fixtures of those names; ``flicker`` is the asset with every
    Gaussian's colour jittered by a random +-``flicker`` per channel anew in each view (the
    view-to-view colour inconsistency a scene's unconstrained view-dependent colour shows)."""
    from ..turntable import render_views, to_uint8
    from .fixtures3d import failure_scene, flicker_colors

    if kind not in FIXTURES:
        raise ValueError(f"kind: expected one of {FIXTURES}, got {kind!r}")
    scene = failure_scene(caption, "asset" if kind == "flicker" else kind, seed=seed)
    if kind != "flicker":
        return to_uint8(render_views(scene, cams))
    views = [
        render_views(flicker_colors(scene, i, amount=flicker, seed=seed), cams[i : i + 1]) for i in range(len(cams))
    ]
    return to_uint8(torch.cat(views))
