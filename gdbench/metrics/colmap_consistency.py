"""COLMAP multi-view consistency of a generated object (our definition; the paper's and
3DFuse's exact variance is not published).

Render K views on one circle (fixed radius and elevation, 360/K degrees apart, default K = 100
at 256 px), run COLMAP on CPU (pycolmap: SIFT, exhaustive matching, incremental mapping with
one PINHOLE camera whose known intrinsics stay fixed; extraction and matching in two fixed
shares in two processes, each on one thread, the mapper on one thread, so a scene's score is
reproducible: ``SHARES``), take the largest model, align it to the true cameras by a similarity
(Umeyama on camera centres) and report:

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

import json
import math
import os
import shutil
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import torch

from gdbench.core.camera import Cameras, SphericalPoses

THREADS = 1
"""COLMAP's own threads in every call. One makes a scene's score reproducible: with two, the same
scene's Var(theta) read 1.9-2.5 and once 7.6 over seven runs (SIFT extraction, matching and the
mapper each change the result when COLMAP threads them; measured in docs/log/2026-11-26_cell_cost.md)."""

SHARES = 2
"""Feature extraction and matching run as this many fixed shares side by side, the first in this
process and each other in a process of its own (``_colmap_share.py``; two matchers in one
process interleave and give another result each time, one per process the same), each on one
thread; the mapper, on one thread, cannot be split. Extraction: share k extracts every
SHARES-th view from view k into a database of its own, and the rows are copied into one
database made by ``import_images``: the database one thread writes, row for row (tested), so the
features are COLMAP's. Matching: share k matches every SHARES-th pair of the exhaustive list
(i < j, in order) in its own copy of that database, and the rows are merged by pair id (each
table's key, so the order of insertion leaves no trace). Each pair's matches are one thread's
as sets (tested; a few pairs list them in another order), and the verification's RANSAC draws
differ from one thread's with that order and the pairs each share saw before: the verified
geometries are another draw than one thread's, the same in every run and whatever the number of
cores (the shares are fixed, not the machine's; another CPU or pycolmap build may round
differently, as one thread may). Shares pay on an otherwise idle machine; a sweep with as many
workers as cores runs two COLMAP processes per cell in these stages and gains little. Their
timings and their agreement with one thread on the calibration fixtures and trained scenes are in
docs/log/2026-11-26_cell_cost.md."""

MAX_SHARES = 16
"""The most shares ``score_images`` takes (each beyond the first is a process)."""

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
    shares: int = SHARES,
) -> ColmapScore:
    """Run COLMAP on uint8 images [K, H, W, 3] taken (in order around the circle) by ``cams``.
    COLMAP's own output goes to ``log`` (appended; None: discarded), not the console; ``phase``
    (optional) is called with the name of each stage as it starts. ``shares``: the shares of
    extraction and matching (``SHARES``); 1 is COLMAP on one thread throughout, exhaustive
    matching included: the metric as it was scored until 2026-11-26."""
    _check_shares(shares)
    t0 = time.perf_counter()
    with _Helpers(shares - 1, log) as helpers:
        est, points = _reconstruct(images, cams, workdir, helpers, seed=seed, max_image_size=max_image_size, log=log,
                                   phase=phase, shares=shares)  # fmt: skip
    return _score(est, points, cams, time.perf_counter() - t0)


def _check_shares(shares) -> None:
    if not isinstance(shares, int) or isinstance(shares, bool) or not 1 <= shares <= MAX_SHARES:
        raise ValueError(f"shares: expected an integer from 1 to {MAX_SHARES}, got {shares!r}")


def _reconstruct(
    images, cams: Cameras, workdir, helpers, *, seed: int, max_image_size: int, log=None, phase=None, shares=SHARES
):
    """COLMAP's estimate of each registered view: {index: (rotation, camera centre)}, and the
    number of 3D points, from SIFT, exhaustive matching and incremental mapping with the known
    PINHOLE intrinsics held fixed (the largest model); extraction and matching in ``shares``."""
    from PIL import Image

    from gdbench.core.io import captured_output
    from gdbench.metrics._colmap_share import extract, match, reader_options

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
        for stale in [db, *root.glob("share*.db")]:
            _remove_database(stale)
        fx, fy, cx, cy = (float(v) for v in cams.Ks[0, [0, 1, 0, 1], [0, 1, 2, 2]])
        camera = f"{fx},{fy},{cx},{cy}"
        views = _extraction_shares(names, shares)
        phase("COLMAP features")
        with captured_output(log):
            pycolmap.Database.open(db).close()
            pycolmap.import_images(db, img_dir, pycolmap.CameraMode.SINGLE, names, reader_options(camera))
            jobs = [{"job": "extract", "database": str(root / f"share{k}.db"), "images": str(img_dir), "names": v,
                     "camera_params": camera, "max_image_size": max_image_size, "threads": THREADS}
                    for k, v in enumerate(views)]  # fmt: skip
            helpers.run(jobs, extract)
            _copy_features(db, [Path(j["database"]) for j in jobs])
        phase("COLMAP matching")
        with captured_output(log):
            jobs, matched = [], []
            if shares == 1:  # one thread's exhaustive matching, in its own order of pairs
                matching = pycolmap.FeatureMatchingOptions()
                matching.num_threads = THREADS
                pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
            else:
                pairs = [(names[i], names[j]) for i in range(K) for j in range(i + 1, K)]
                matched = [m for m in (pairs[k::shares] for k in range(shares)) if m]
            for k, share in enumerate(matched):
                copy, listing = root / f"share{k}.db", root / f"share{k}.pairs"
                _remove_database(copy)
                shutil.copyfile(db, copy)
                listing.write_text("".join(f"{a} {b}\n" for a, b in share))
                jobs.append({"job": "match", "database": str(copy), "pairs": str(listing), "threads": THREADS})
            helpers.run(jobs, match)
            _merge_matches(db, [Path(j["database"]) for j in jobs])
        phase("COLMAP mapping")
        with captured_output(log):
            opts = pycolmap.IncrementalPipelineOptions()
            opts.ba_refine_focal_length = False
            opts.ba_refine_principal_point = False
            opts.ba_refine_extra_params = False
            opts.num_threads = THREADS
            opts.random_seed = seed
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


class _Helpers:
    """The processes of the shares after the first (``_colmap_share.py``), started on entry so
    their import of pycolmap overlaps the caller's work; their COLMAP lines go to ``log``. On an
    error or a stop in the block they are killed at once (a job under way is not waited for)."""

    def __init__(self, n: int, log):
        self.n, self.log, self.procs = n, log, []

    def __enter__(self):
        import subprocess
        import sys

        script = str(Path(__file__).with_name("_colmap_share.py"))
        err = open(os.fspath(self.log) if self.log is not None else os.devnull, "a")
        try:
            for _ in range(self.n):
                self.procs.append(subprocess.Popen([sys.executable, script], stdin=subprocess.PIPE,
                                                   stdout=subprocess.PIPE, stderr=err, text=True))  # fmt: skip
        except BaseException:
            self._end(kill=True)
            raise
        finally:
            err.close()
        return self

    def run(self, jobs: list[dict], local) -> None:
        """Job 0 here (``local(job)``), job k in process k; returns when all are done."""
        for proc, job in zip(self.procs, jobs[1:]):
            try:
                proc.stdin.write(json.dumps(job) + "\n")
                proc.stdin.flush()
            except OSError as e:  # the process is gone
                raise RuntimeError(f"COLMAP share process: ended with code {proc.wait()} ({e})") from e
        if jobs:
            local(jobs[0])
        for proc, _ in zip(self.procs, jobs[1:]):
            answer = proc.stdout.readline().strip()
            if answer != "ok":
                raise RuntimeError(f"COLMAP share process: {answer or f'ended with code {proc.wait()}'}")

    def _end(self, kill: bool) -> None:
        for proc in self.procs:
            try:
                if kill:
                    proc.kill()
                proc.stdin.close()
                proc.wait(timeout=10)
            except BaseException:  # a second stop while waiting: no process is left behind
                proc.kill()
                proc.wait()
                if not kill:
                    raise
            finally:
                proc.stdout.close()

    def __exit__(self, kind, *exc):
        self._end(kill=kind is not None)
        return False


def _extraction_shares(names: list[str], shares: int) -> list[list[str]]:
    """The views each share extracts: every ``shares``-th from view k. How long a view takes
    depends on its content and neighbouring views are alike, so contiguous halves of the circle
    would be uneven in time; which share extracts a view leaves its rows as they
    are. No empty share: extract_features given no names reads every image in the folder."""
    return [v for v in (names[k::shares] for k in range(shares)) if v]


def _remove_database(path: Path) -> None:
    """Remove an SQLite database and its sidecars, which SQLite would replay onto a new file of
    that name."""
    for p in (path, *(path.with_name(path.name + x) for x in ("-wal", "-shm", "-journal"))):
        p.unlink(missing_ok=True)


def _copy_features(db: Path, shares: list[Path]) -> None:
    """Copy the keypoints and descriptors rows of the share databases into ``db``, each under
    the id ``db`` gives its image (by name)."""
    import sqlite3

    main = sqlite3.connect(db)
    try:
        ids = dict(main.execute("SELECT name, image_id FROM images"))
        for share in shares:
            part = sqlite3.connect(share)
            try:
                names = {i: n for n, i in part.execute("SELECT name, image_id FROM images")}
                for table in ("keypoints", "descriptors"):
                    cols = [r[1] for r in part.execute(f"PRAGMA table_info({table})")]
                    insert = f"INSERT INTO {table} ({', '.join(cols)}) VALUES ({', '.join('?' * len(cols))})"
                    for row in part.execute(f"SELECT * FROM {table} ORDER BY rowid"):
                        main.execute(insert, (ids[names[row[0]]], *row[1:]))
            finally:
                part.close()
        main.commit()
    finally:
        main.close()


def _merge_matches(db: Path, shares: list[Path]) -> None:
    """Insert the matches and verified two-view geometries of the share databases into ``db``
    (keyed by pair id: each pair is in one share)."""
    import sqlite3

    main = sqlite3.connect(db)
    try:
        for share in shares:
            main.execute("ATTACH DATABASE ? AS share", (str(share),))
            for table in ("matches", "two_view_geometries"):
                main.execute(f"INSERT INTO main.{table} SELECT * FROM share.{table}")
            main.commit()
            main.execute("DETACH DATABASE share")
    finally:
        main.close()


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
    shares: int = SHARES,
    **pose_kw,
) -> ColmapScore:
    """Render a GaussianScene on the circle (on ``background``, a run's own) and score it
    (``log``, ``phase``, ``shares``: as ``score_images``). The share processes start after the
    render: started before it, their import of pycolmap slowed the two-thread render by more than
    it hid (docs/log/2026-11-26_cell_cost.md)."""
    from gdbench.core.turntable import render_views, to_uint8

    _check_shares(shares)
    cams = circle_poses(views, **pose_kw).cameras(size, size)
    if phase is not None:
        phase("COLMAP views")
    images = to_uint8(render_views(scene, cams, background=background))
    return score_images(images, cams, workdir, seed=seed, log=log, phase=phase, shares=shares)


def asset_circle_images(
    caption: str, cams: Cameras, *, mode: str = "consistent", seed: int = 0, jitter_deg: float = 12.0
) -> np.ndarray:
    """Calibration images of a procedural asset on the circle, uint8 [K, H, W, 3].

    ``consistent``: the asset as it is; ``jittered``: every view sees the asset turned by a
    random angle (uniform +-``jitter_deg``) about +Z, which no single scene renders (the failures
    a scene can show are ``fixture_circle_images``').
    """
    from gdbench.assets.library import build
    from renderers.pyrender_points.mesh import render_mesh

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
    """Calibration images of a 3D failure fixture (``metrics/failures3d.py``) on the circle,
    rendered by gdbench's splatting renderer, uint8 [K, H, W, 3]: ``asset``, ``floaters`` and
    ``two-faced`` are the fixtures of those names; ``flicker`` is the asset with every
    Gaussian's colour jittered by a random +-``flicker`` per channel anew in each view (the
    view-to-view colour inconsistency a scene's unconstrained view-dependent colour shows)."""
    from gdbench.core.turntable import render_views, to_uint8
    from gdbench.metrics.failures3d import failure_scene, flicker_colors

    if kind not in FIXTURES:
        raise ValueError(f"kind: expected one of {FIXTURES}, got {kind!r}")
    scene = failure_scene(caption, "asset" if kind == "flicker" else kind, seed=seed)
    if kind != "flicker":
        return to_uint8(render_views(scene, cams))
    views = [
        render_views(flicker_colors(scene, i, amount=flicker, seed=seed), cams[i : i + 1]) for i in range(len(cams))
    ]
    return to_uint8(torch.cat(views))
