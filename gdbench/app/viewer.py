"""``gdbench view``: an interactive browser viewer of a Gaussian scene (viser, docs/viewer.md).

``serve`` starts a viser web server that draws the scene's Gaussians with viser's WebGL splat
renderer, with the scene's up direction (+Z, docs/conventions.md), a GUI slider that moves the
browser's camera to the turntable views of a run (the cameras of ``train.run``'s turntable:
``turntable.RUN_TURNTABLE``; a PLY from elsewhere is framed from its bounds, as ``gdbench
render`` frames it), and a checkbox that shows a run's training-view frustums (the poses the run
drew, from its ``run.json``). viser is an optional dependency
(``pip install -e '.[view]'`` or ``make setup``) and is imported only here.

The pure parts (``splat_arrays``, ``turntable_cameras``, ``training_cameras``, ``viser_pose``)
need no viser: what viser receives is tested without a browser (tests/test_viewer.py).

viser's splats are an approximation of ``renderers.splat.rasterize``: colour is the SH DC term
only (view-independent), the covariance travels as float16 (hence ``SplatArrays.scale``), a
splat whose screen covariance is exactly diagonal can vanish (hence ``NUDGE``), the footprint is
cut at 2.83 sigma and alpha below 0.01, and one global depth sort is quantised to 16 bits.
Measured against our render in a browser: docs/viewer.md.
"""

from __future__ import annotations

import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import torch

from gdbench.core.camera import Cameras, SphericalPoses, rotmat_to_quat
from gdbench.core.filetags import UP_AXES as FILE_UP_AXES
from gdbench.core.filetags import up_rotation as up_rotation_named
from gdbench.core.scene import GaussianScene
from gdbench.core.turntable import RUN_TURNTABLE

if TYPE_CHECKING:
    import viser

VIEW_EXTRA = "pip install -e '.[view]' (or `make setup`)"
"""What installs the viewer's dependency, for error messages."""

UP_AXES = {k: tuple(float(x) for x in up_rotation_named(k)[:, 2]) for k in FILE_UP_AXES}
"""Named up directions (gdbench's ``filetags.UP_AXES``, viser's names) and their vectors;
gdbench's scenes are +Z up."""

TURNTABLE_FRAMES = 36
"""Turntable views when no run says otherwise (``TrainConfig.turntable_frames``'s default)."""

MAX_FRUSTUMS = 120
"""Training-view frustums drawn at most (evenly spaced over the run's steps)."""


def import_viser():
    """The ``viser`` module, or an ImportError that says what to install."""
    try:
        import viser
    except ImportError as e:
        raise ImportError(f"gdbench view needs the `viser` package ({e}); install it with {VIEW_EXTRA}") from e
    return viser


NUDGE = 1e-3
"""viser's vertex shader takes a splat's major axis as ``normalize((b, lambda1 - a))`` of its 2D
covariance ``[[a, b], [b, c]]``: (0, 0), so NaN and an invisible splat, when ``b`` is exactly 0 and
``a >= c``. That is an isotropic or axis-aligned Gaussian on the image's horizontal centre line,
e.g. one at the origin or an arm along +Y seen from turntable view 0 (measured: half of such an
arm missing). ``splat_arrays`` adds ``NUDGE * tr(Sigma) / 3 * v v^T`` with a fixed generic unit
``v``: positive semi-definite, 0.1% of the mean variance along ``v`` (well under a pixel at the
turntable's distance), and ``b`` is then non-zero for every view but a set of measure zero."""

_NUDGE_DIR = np.array([1.0, 2.0, 3.0]) / math.sqrt(14.0)


# ---------------------------------------------------------------------------- pure parts
@dataclass(frozen=True)
class SplatArrays:
    """What ``viser``'s ``scene.add_gaussian_splats`` takes, in the node's frame, and the node's
    ``scale``: world = ``scale`` x node coordinates."""

    centers: np.ndarray
    """[N, 3] float32, means / scale."""
    covariances: np.ndarray
    """[N, 3, 3] float32, Sigma / scale^2 (Sigma = R S S^T R^T, plus ``NUDGE``'s term)."""
    rgbs: np.ndarray
    """[N, 3] float32 in [0, 1]: the SH DC colour C0 sh[:, 0] + 0.5, clipped."""
    opacities: np.ndarray
    """[N, 1] float32, sigmoid of the logits."""
    scale: float
    """The node's scale: the median standard deviation (a power of two), so that the covariances
    viser sends as float16 are O(1) instead of float16-subnormal (a trained scene's Gaussians are
    mostly below 0.008 in standard deviation, whose variances float16 stores with a few bits)."""

    def world_covariances(self) -> np.ndarray:
        """[N, 3, 3] float64 covariances in world units."""
        return self.covariances.astype(np.float64) * self.scale**2


def splat_arrays(scene: GaussianScene) -> SplatArrays:
    """The scene as viser splats: centres, covariances ``R(q) S S^T R(q)^T`` (float64, then
    float32; with ``NUDGE``'s term), DC colours and opacities, scaled by a power of two
    (``SplatArrays.scale``)."""
    from renderers.splat.project import covariance_factor
    from renderers.splat.sh import sh0_to_rgb

    s = scene.detach().to("cpu", torch.float64)
    M = covariance_factor(s.quats, s.scales)  # R(q) diag(s), quaternions normalised (zero: identity)
    cov = (M @ M.transpose(-1, -2)).numpy()
    cov = cov + NUDGE * (np.trace(cov, axis1=1, axis2=2) / 3)[:, None, None] * np.outer(_NUDGE_DIR, _NUDGE_DIR)
    std = s.scales.numpy()
    med = float(np.median(std)) if std.size else 1.0
    scale = 2.0 ** round(math.log2(med)) if med > 0 and math.isfinite(med) else 1.0
    return SplatArrays(
        centers=(s.means.numpy() / scale).astype(np.float32),
        covariances=(cov / scale**2).astype(np.float32),
        rgbs=np.clip(sh0_to_rgb(s.sh[:, 0]).numpy(), 0.0, 1.0).astype(np.float32),
        opacities=s.opacities.numpy()[:, None].astype(np.float32),
        scale=scale,
    )


def up_vector(up: str | Sequence[float]) -> np.ndarray:
    """Unit up vector of ``up``: one of ``UP_AXES`` ('+z', '-y', ...) or three numbers."""
    if isinstance(up, str):
        key = up.strip().lower()
        key = key if key[:1] in "+-" else "+" + key
        if key not in UP_AXES:
            raise ValueError(f"up: expected one of {', '.join(UP_AXES)} or three numbers, got {up!r}")
        return np.array(UP_AXES[key])
    v = np.asarray(up, dtype=np.float64)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or np.linalg.norm(v) < 1e-12:
        raise ValueError(f"up: expected a non-zero finite 3-vector, got {up!r}")
    return v / np.linalg.norm(v)


def up_rotation(up: str | Sequence[float]) -> np.ndarray:
    """Rotation [3, 3] taking gdbench's +Z up to ``up`` (the smallest one; a half turn about +X for
    -Z; for a named axis, ``filetags.up_rotation``'s). The turntable and training cameras, defined
    with +Z up, are turned by it."""
    if isinstance(up, str):
        up_vector(up)  # the name checked, with this function's error
        key = up.strip().lower()
        return up_rotation_named(key if key[:1] in "+-" else "+" + key).numpy()
    u = up_vector(up)
    z = np.array([0.0, 0.0, 1.0])
    c = float(z @ u)
    if c < -1 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(z, u)
    K = np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])
    return np.eye(3) + K + K @ K / (1.0 + c)


def turntable_cameras(
    frames: int = TURNTABLE_FRAMES, width: int = 256, height: int | None = None, *, radius: float | None = None
) -> Cameras:
    """The turntable of a run (``turntable.write_turntable`` with ``RUN_TURNTABLE``): ``frames``
    views 360/frames degrees apart around the origin, +Z up, ``width`` x ``height`` (default
    square) pixels with the turntable's vertical fov (a browser window's aspect widens the
    horizontal one, as viser's does); ``radius`` replaces the run's (a framed PLY)."""
    orbit = RUN_TURNTABLE | ({} if radius is None else {"radius": float(radius)})
    return SphericalPoses.orbit(frames, **orbit).cameras(width, height or width)


def framed_orbit(scene: GaussianScene) -> tuple[np.ndarray, float]:
    """(centre [3], orbit radius) for a scene that is not a run's: the centre of its visible
    Gaussians' bounds and the distance at which they fill the turntable's fov (``framing``, as
    ``gdbench render`` frames a PLY from elsewhere)."""
    from gdbench.core.framing import bounds, orbit_radius

    centre, radius = bounds(scene.detach().to("cpu"))
    return centre.double().numpy(), orbit_radius(radius, RUN_TURNTABLE["fovy"])


def training_cameras(config: dict, steps: int, max_views: int = MAX_FRUSTUMS) -> tuple[Cameras, list[int]]:
    """The training views of a run (``config``: run.json's ``config``), drawn as the trainer draws
    them (``train.views.sample_views``: the ``views`` stream of the run's seed, one
    ``SphericalPoses.sample`` of ``views_per_step`` poses per step, in the config's radius, fov,
    azimuth and elevation ranges), for the first ``steps`` steps; returns the first view of every
    k-th step (at most ``max_views``) and the steps they belong to."""
    from gdbench.train.layout import flat_config
    from gdbench.train.streams import make_streams

    config = flat_config(config)  # either layout of run.json
    try:
        keys = ("seed", "camera_radius", "fovy_range", "azimuth_range", "elevation_range", "resolution")
        seed, radius, fovy, az, el, res = (config[k] for k in keys)
    except KeyError as e:
        raise ValueError(f"run.json: config has no {e.args[0]!r}; expected a run folder's run.json") from None
    g = make_streams(int(seed))["views"]
    every = max(1, math.ceil(steps / max(1, max_views)))
    picked, kept = [], []
    for step in range(steps):
        poses = SphericalPoses.sample(
            int(config.get("views_per_step", 1)),
            generator=g,
            radius=float(radius),
            fovy_range=tuple(fovy),
            azimuth_range=tuple(az),
            elevation_range=tuple(el),
            spread_deg=config.get("views_spread_deg"),
        )
        if step % every == 0:
            picked.append(poses.cameras(int(res), int(res))[0])
            kept.append(step)
    if not picked:
        return Cameras(torch.zeros(0, 4, 4), torch.zeros(0, 3, 3), int(res), int(res)), []
    return Cameras.cat(picked), kept


@dataclass(frozen=True)
class ViserPose:
    """One camera in viser's terms (world frame, OpenCV camera axes like ours)."""

    position: np.ndarray
    """[3] camera centre."""
    wxyz: np.ndarray
    """[4] camera-to-world rotation (viser's ``R_world_camera``)."""
    look_at: np.ndarray
    """[3] the orbit centre: the point of the optical axis nearest the orbit's centre."""
    up: np.ndarray
    """[3] the scene's up vector (viser's orbit controls turn about it)."""
    fov: float
    """Vertical field of view, radians."""


def viser_pose(
    cams: Cameras, index: int, rotation: np.ndarray | None = None, centre: Sequence[float] | None = None
) -> ViserPose:
    """Camera ``index`` of ``cams`` (+Z up, about the origin) turned by ``rotation``
    (``up_rotation``) and moved by ``centre``, in viser's terms. For a camera looking at the origin
    with up +Z (turntable, training) viser's camera from ``position``, ``look_at`` and ``up`` is
    the same camera (tested)."""
    Rup = np.eye(3) if rotation is None else np.asarray(rotation, dtype=np.float64)
    o = np.zeros(3) if centre is None else np.asarray(centre, dtype=np.float64)
    c2w = torch.linalg.inv(cams.viewmats[index].double()).numpy()
    R = Rup @ c2w[:3, :3]
    c = Rup @ c2w[:3, 3] + o
    fwd = R[:, 2]
    depth = max(float((o - c) @ fwd), 1e-3 * max(float(np.linalg.norm(c - o)), 1.0))
    fovy = float(cams.fovy_deg()[index])
    return ViserPose(
        position=c,
        wxyz=rotmat_to_quat(torch.from_numpy(R)).numpy(),
        look_at=c + depth * fwd,
        up=Rup[:, 2].copy(),
        fov=math.radians(fovy),
    )


def resolve_inputs(
    scene_or_path, run_json: str | Path | None, up: str | None = None
) -> tuple[GaussianScene, str, dict | None]:
    """(scene, its description, run.json or None) from a scene, a PLY or a run folder; a file is
    read with up axis ``up`` (None: the one it records, else +z) and turned to +Z up. Unless
    ``run_json`` is given, a ``scene.ply`` (a run folder's, or named directly) brings the
    ``run.json`` beside it when that names the same scene (its ``scene_sha256``, as ``gdbench
    render`` decides); any other PLY has none."""
    from gdbench.core.io import read_json, run_json_of

    run = read_json(run_json, what="run.json") if run_json is not None else None
    if isinstance(scene_or_path, GaussianScene):
        scene, name = scene_or_path, f"{len(scene_or_path)} Gaussians"
    else:
        path = Path(scene_or_path)
        if path.is_dir():
            path = path / "scene.ply"
        if not path.is_file():
            raise FileNotFoundError(f"{scene_or_path}: expected a scene file (PLY, .splat) or a run folder")
        from gdbench.app.export import load_scene

        scene, name = load_scene(path, up=up, flag="--up"), str(path)  # 3DGS or compressed PLY, .splat; +Z up
        found = run_json_of(path) if run_json is None else None
        if found is not None:
            run_json, run = found
    if run is not None and not isinstance(run.get("config"), dict):
        raise ValueError(f"run.json: {run_json} has no 'config' object; expected a run folder's run.json")
    return scene, name, run


# ------------------------------------------------------------------------------ server
def _set_camera(client, pose: ViserPose) -> None:
    cam = client.camera
    with client.atomic():
        cam.fov = pose.fov
        cam.up_direction = pose.up
        cam.position = pose.position
        cam.look_at = pose.look_at


def _add_splats(server, scene: GaussianScene) -> None:
    """Show ``scene`` as the server's splats (``splat_arrays``), replacing any shown before."""
    splats = splat_arrays(scene)
    server.scene.add_gaussian_splats(
        "/scene",
        centers=splats.centers,
        covariances=splats.covariances,
        rgbs=splats.rgbs,
        opacities=splats.opacities,
        scale=splats.scale,
    )


def _check_host(host: str) -> None:
    """A ValueError naming --host unless this machine can listen on ``host`` (viser takes any
    OSError for a busy port and tries the next one, forever, for an address it cannot have)."""
    import socket

    try:
        family = socket.getaddrinfo(host, None, type=socket.SOCK_STREAM)[0][0]
        with socket.socket(family, socket.SOCK_STREAM) as s:
            s.bind((host, 0))
    except (OSError, UnicodeError) as e:
        raise ValueError(f"host (--host): cannot listen on {host!r} ({getattr(e, 'strerror', None) or e})") from None


class Viewer:
    """A running viewer (``serve``): the viser ``server``, its GUI handles and the turntable poses."""

    def __init__(self, server: viser.ViserServer, poses: list[ViserPose], frustum_steps: list[int], radius: float):
        self.server = server
        self.poses = poses
        """The turntable views in viser's terms (``viser_pose``)."""
        self.radius = radius
        """The turntable's orbit radius (the run's, or a framed PLY's)."""
        self.frustum_steps = frustum_steps
        """The run's steps whose first training view is drawn as a frustum (empty without a run)."""
        self._lock = threading.Lock()
        self.slider = self.checkbox = self.frustums = self._info = None

    @property
    def port(self) -> int:
        return self.server.get_port()

    @property
    def url(self) -> str:
        host = self.server.get_host()
        return f"http://{'127.0.0.1' if host in ('0.0.0.0', '') else host}:{self.port}"

    def show_view(self, k: int) -> None:
        """Move the GUI's slider, and with it every browser's camera, to turntable view ``k``."""
        self.slider.value = int(k) % len(self.poses)

    def show_frustums(self, on: bool) -> None:
        """Tick or untick the training-views checkbox (disabled without a run)."""
        if self.frustum_steps:
            self.checkbox.value = bool(on)

    def stop(self) -> None:
        self.server.stop()

    def update_scene(self, scene: GaussianScene) -> None:
        """Replace the splats every browser shows with ``scene``'s (``generate --view``)."""
        _add_splats(self.server, scene)

    # ------------------------------------------------------------------ GUI callbacks
    def _go(self, k: int) -> None:
        self._info.content = _describe(k, len(self.poses), self.radius)
        with self._lock:
            for client in self.server.get_clients().values():
                _set_camera(client, self.poses[k])

    def _toggle(self) -> None:
        if self.frustums is not None:
            self.frustums.visible = bool(self.checkbox.value)


def _describe(k: int, frames: int, radius: float) -> str:
    az = float(SphericalPoses.orbit(frames, **RUN_TURNTABLE).azimuth[k])
    t = RUN_TURNTABLE
    return (
        f"azimuth {az:g}° (views {360 / frames:g}° apart), elevation {t['elevation']:g}°, "
        f"radius {radius:.3g}, fovy {t['fovy']:g}°"
    )


def _rng(r) -> str:
    return f"{r[0]:g} to {r[1]:g}"


def _turntable_panel(viewer: Viewer, view: int, frames: int, radius: float) -> None:
    """The turntable's folder: a slider over its views, where it stands, Previous and Next."""
    gui = viewer.server.gui
    with gui.add_folder("Turntable"):
        viewer.slider = gui.add_slider("View", min=0, max=frames - 1, step=1, initial_value=view)
        viewer._info = gui.add_markdown(_describe(view, frames, radius))
        prev, nxt = gui.add_button("Previous"), gui.add_button("Next")
    viewer.slider.on_update(lambda _e: viewer._go(int(viewer.slider.value)))
    prev.on_click(lambda _e: viewer.show_view(int(viewer.slider.value) - 1))
    nxt.on_click(lambda _e: viewer.show_view(int(viewer.slider.value) + 1))


def _training_panel(viewer: Viewer, config: dict | None, kept: list[int], steps: int, on: bool) -> None:
    """The training views' folder: the frustums' checkbox and what they are (or why there are none)."""
    gui = viewer.server.gui
    with gui.add_folder("Training views"):
        viewer.checkbox = gui.add_checkbox("Show frustums", initial_value=on, disabled=not kept)
        if config is None:
            gui.add_markdown("No run.json: serve a run folder (or pass its run.json) to see them.")
        else:
            gui.add_markdown(
                f"First view of {len(kept)} of the run's {steps} steps (blue: early, orange: late); "
                f"radius {config['camera_radius']:g}, fovy {_rng(config['fovy_range'])}°, "
                f"azimuth {_rng(config['azimuth_range'])}°, elevation {_rng(config['elevation_range'])}°"
            )
    viewer.checkbox.on_update(lambda _e: viewer._toggle())


def _add_frustums(viewer: Viewer, train_cams, kept: list[int], steps: int, rotation, on: bool) -> None:
    """One frustum per kept training step, coloured from blue (early) to orange (late)."""
    server = viewer.server
    viewer.frustums = server.scene.add_frame("/training_views", show_axes=False, visible=on)
    for i, step in enumerate(kept):
        q = viser_pose(train_cams, i, rotation)
        t = step / max(steps - 1, 1)
        server.scene.add_camera_frustum(
            f"/training_views/step_{step:06d}",
            fov=q.fov,
            aspect=train_cams.width / train_cams.height,
            scale=0.06,
            thickness=0.002,
            color=(int(40 + 200 * t), int(110 + 40 * t), int(230 - 190 * t)),
            wxyz=q.wxyz,
            position=q.position,
        )


def serve(
    scene_or_path: GaussianScene | str | Path,
    *,
    host: str = "127.0.0.1",
    port: int = 8080,
    up: str | Sequence[float] | None = None,
    run_json: str | Path | None = None,
    frustums: bool = False,
    block: bool = True,
    view: int = 0,
    framed: bool | None = None,
    verbose: bool = True,
) -> Viewer:
    """Serve a Gaussian scene to the browser at ``http://host:port`` (viser; docs/viewer.md).

    ``scene_or_path``: a ``GaussianScene``, a 3DGS PLY, or a run folder (its ``scene.ply``, and its
    ``run.json`` unless ``run_json`` names one). ``up``: the scene's up axis. For a file, a name
    (``filetags.UP_AXES``) or None: the file is read with it (None: the axis the file records, else
    +z; one that differs from the recorded axis is refused) and turned to +Z up. For a
    ``GaussianScene``, or as three numbers, the direction the view keeps up: the turntable and
    training cameras are turned with it (default +Z). ``run_json``: a run's run.json, whose config
    gives the turntable's frame count and the training views; without one the training-views
    checkbox is disabled. ``frustums``: show the
    training views at start. ``view``: the turntable view new browsers open at (and "Reset View"
    returns to). ``framed``: turntable about the scene's bounds at the distance that shows it whole
    (``framed_orbit``) instead of the run's orbit about the origin; by default for a PLY without
    a run.json (a scene from elsewhere), not for a run's scene or a ``GaussianScene``. ``block``:
    serve until a stop signal (Ctrl-C, SIGTERM), then stop the server and let the interrupt
    through (the command line ends with one line and 128 + the signal's number); else return at
    once (``Viewer.stop``). viser moves to the next
    free port when ``port`` is taken (``Viewer.port``).
    """
    _check_host(host)
    viser = import_viser()
    named = up is None or isinstance(up, str)
    scene, name, run = resolve_inputs(scene_or_path, run_json, up if named else None)
    if len(scene) == 0:
        raise ValueError(f"{name}: the scene has no Gaussians to show")
    if named and not isinstance(scene_or_path, GaussianScene):
        up = "+z"  # the file was turned to +Z up as it was read
    up = "+z" if up is None else up
    rotation = up_rotation(up)
    config = run["config"] if run is not None else None
    frames = int(config.get("turntable_frames", TURNTABLE_FRAMES)) if config else TURNTABLE_FRAMES
    if not 0 <= view < frames:
        raise ValueError(f"view: expected a turntable view in [0, {frames - 1}], got {view}")
    if framed is None:
        framed = run is None and not isinstance(scene_or_path, GaussianScene)
    centre, radius = framed_orbit(scene) if framed else (np.zeros(3), RUN_TURNTABLE["radius"])
    turn = turntable_cameras(frames, radius=radius)
    poses = [viser_pose(turn, k, rotation, centre) for k in range(frames)]
    if config is not None:
        steps = int(run.get("steps", config.get("steps", 0)))
        train_cams, kept = training_cameras(config, steps)
    else:
        steps, train_cams, kept = 0, None, []

    server = viser.ViserServer(host=host, port=port, verbose=verbose)
    viewer = Viewer(server, poses, kept, radius)
    try:
        server.gui.configure_theme(show_share_button=False)  # the share link needs viser's relay
        server.scene.set_up_direction(up_vector(up))
        _add_splats(server, scene)
        p = poses[view]
        server.initial_camera.fov = p.fov
        server.initial_camera.up = p.up
        server.initial_camera.position = p.position
        server.initial_camera.look_at = p.look_at
        about = f"{len(scene)} Gaussians, SH degree {scene.sh_degree} (shown: DC colour)"
        if framed:
            about += f"; not a run's scene: turntable about its bounds' centre {np.round(centre, 3).tolist()}"
        server.gui.add_markdown(f"**{name}**  \n{about}")
        _turntable_panel(viewer, view, frames, radius)
        _training_panel(viewer, config, kept, steps, bool(frustums and kept))
        if kept:
            _add_frustums(viewer, train_cams, kept, steps, rotation, bool(frustums and kept))
    except BaseException:
        server.stop()
        raise
    if verbose:
        print(f"gdbench view: {name} at {viewer.url}" + (" (Ctrl-C stops)" if block else ""))
    if not block:
        return viewer
    try:  # until a stop signal: the command line ends with its one line and 128 + its number
        while True:
            time.sleep(3600)
    finally:
        server.stop()
