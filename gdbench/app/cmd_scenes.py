"""Commands on a finished scene: ``render`` (a turntable), ``score`` (against the asset and
COLMAP), ``export`` (to other formats) and ``view`` (the interactive viewer). Each is an options
dataclass (its field docstrings are the help) and a ``run_*`` function."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Literal

import tyro

from gdbench.core.constraints import AtLeast, Between, Positive
from gdbench.core.filetags import UpAxis


@dataclass
class Render:
    """Turntable (GIF, MP4, contact sheet) of a run folder, a 3DGS or compressed PLY, or a .splat."""

    run: tyro.conf.Positional[Path]
    """A run folder (its scene.ply is used), a .ply file (Inria 3DGS, or the compressed PLY) or a
    .splat file."""
    out: Path | None = None
    """Output folder (default: the run folder, or the PLY's folder)."""
    frames: Annotated[int | None, AtLeast(1)] = None
    """Views on the orbit, 360/frames degrees apart (default: a run's turntable frames, else 36)."""
    size: Annotated[int | None, AtLeast(8, "px")] = None
    """Side of each frame in pixels (default: a run's turntable size, else 256)."""
    radius: Annotated[float | None, Positive()] = None
    """Orbit radius in scene units (default: a run's turntable radius, 1.3; a PLY from elsewhere:
    framed from its bounds, centred on them)."""
    elevation: Annotated[float, Between(-90, 90, unit="degrees")] = 15.0
    """Camera elevation above the scene's horizontal plane (+Z up), degrees."""
    fovy: Annotated[float, Between(1, 179, unit="degrees")] = 45.0
    """Vertical field of view, degrees."""
    up: Annotated[UpAxis | None, tyro.conf.DisallowNone] = None
    """The up axis of the scene file (default: the one the file records, as every file gdbench
    writes does, else +z): +z for gdbench's runs, -y for Inria/COLMAP captures and `gdbench
    export`'s default. One that differs from the file's recorded axis is refused."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Where the frames are rendered: cpu (the C++ compositor), cuda (gsplat's CUDA kernels with
    gdbench's conventions, or the torch path where they cannot run) or auto (cuda when torch sees
    one)."""
    outputs: str = "rgb"
    """What to render, comma-separated: rgb, depth (expected depth, scene units; a turbo-coloured
    turntable and its values in *_depth.npy), alpha (grey, and *_alpha.npy)."""
    camera_path: Path | None = None
    """A camera path in nerfstudio's camera_path.json format (what its viewer exports): its
    cameras, size and fps replace the orbit (--frames, --size, --radius, --elevation, --fovy)."""


def _writable(out: Path, *, file: bool) -> Path:
    """``out`` (--out) checked before any work: a file name whose folder can take files, or a
    folder that can (``file=False``); errors name --out."""
    from gdbench.core.io import check_folder, probe_writable

    if file and out.is_dir():
        raise ValueError(f"out (--out): {out} is a folder; expected a file name")
    folder = out.parent if file else out
    check_folder(folder, "out (--out)")
    probe_writable(folder, "out (--out)")
    return out


def _axis_note(path: Path, asked: str | None, flag: str, command: str) -> None:
    """One line when ``path`` was read as +Z up only because it records no axis (a file from
    elsewhere, or a .splat copied without its sidecar)."""
    from gdbench.core.filetags import read_tags

    if asked is None and read_tags(path).up is None:
        print(f"gdbench {command}: note: {path} records no up axis; read as +z (gdbench's); pass {flag} otherwise")


def _outputs(value: str) -> tuple[str, ...]:
    from gdbench.core.turntable import OUTPUTS

    names = tuple(dict.fromkeys(o.strip() for o in value.replace(" ", ",").split(",") if o.strip()))
    bad = [o for o in names if o not in OUTPUTS]
    if bad or not names:
        raise ValueError(f"outputs (--outputs): expected some of {','.join(OUTPUTS)}, comma-separated; got {value!r}")
    return names


def run_render(cmd: Render) -> dict:
    import contextlib

    from gdbench.app.export import load_scene
    from gdbench.app.resources import check_render_memory
    from gdbench.core.devices import resolve_device
    from gdbench.core.io import FolderLock
    from gdbench.core.turntable import write_turntable

    device = resolve_device(cmd.device, "device (--device)")
    outputs = _outputs(cmd.outputs)
    cams, fps = None, 12
    if cmd.camera_path is not None:
        from gdbench.core.camera_path import read_camera_path

        cams, fps = read_camera_path(cmd.camera_path)
    src = Path(cmd.run)
    ply = src / "scene.ply" if src.is_dir() else src
    if not ply.is_file():
        raise FileNotFoundError(f"run: no scene at {ply} (pass a run folder, a .ply or a .splat file)")
    run = _run_turntable(ply)
    frames = cmd.frames or run.get("frames", 36)
    size = cmd.size or run.get("size", 256)
    if cams is not None:
        frames, size = len(cams), max(cams.width, cams.height)
    try:
        check_render_memory(size, frames)
    except ValueError as e:
        if cams is None:
            raise
        raise ValueError(f"camera_path (--camera-path): {cmd.camera_path}: render_width x render_height: {e}") from None
    out = _writable(Path(cmd.out or ply.parent), file=False)
    # a run folder has one writer: not while a generate (--overwrite) or score writes there
    run_folder = (out / "run.json").is_file() or (out / FolderLock.NAME).is_file()
    with FolderLock(out) if run_folder else contextlib.nullcontext():
        scene = load_scene(ply, up=cmd.up, flag="--up")  # a 3DGS or compressed PLY, or a .splat; +Z up
        _axis_note(ply, cmd.up, "--up", "render")
        radius = cmd.radius or run.get("radius")
        framing = ""
        if cams is not None:
            framing, radius = f", cameras from {cmd.camera_path}", radius or 1.0
        elif radius is None:  # not a run's scene: centred on its bounds and framed whole
            from gdbench.core.framing import frame

            scene, radius = frame(scene, cmd.fovy)
            framing = f", framed from its bounds at radius {radius:.3g}"
        res = write_turntable(
            scene.to(device),
            out,
            frames=frames,
            size=size,
            radius=radius,
            elevation=cmd.elevation,
            fovy=cmd.fovy,
            background=run.get("background", (1.0, 1.0, 1.0)),
            stem=ply.stem + ("_camera_path" if cams is not None else "_turntable"),
            cams=cams,
            fps=fps,
            outputs=outputs,
        )
    print(
        f"gdbench render: {len(scene)} Gaussians, {frames} frames at {size}px{framing} ({','.join(outputs)}), "
        f"median {1e3 * sorted(res.seconds_per_frame)[frames // 2]:.1f} ms per frame"
    )
    width = max(map(len, res.paths))
    for k, v in res.paths.items():
        print(f"  {k:{width}s} -> {v}")
    return {k: str(v) for k, v in res.paths.items()}


def _run_of(path: Path) -> dict | None:
    """The run.json (content) of the run whose scene ``path`` holds: a run's own scene.ply (its
    run.json names the same scene), or a file in the run's folder that records the run's id
    (an export, ``core.filetags``); None for any other file."""
    from gdbench.core.filetags import read_tags
    from gdbench.core.io import read_json, run_json_of

    found = run_json_of(path)
    if found is not None:
        return found[1]
    beside = path.parent / "run.json"
    try:
        run = read_tags(path).run
        info = read_json(beside, what="run.json") if run and beside.is_file() else None
    except (OSError, ValueError):
        return None
    return info if isinstance(info, dict) and info.get("run_id") == run else None


def _run_turntable(ply: Path) -> dict:
    """The turntable settings of the run whose scene ``ply`` holds (``_run_of``), so ``render``
    shows it from ``generate``'s cameras; {} for any other file (framed from its bounds)."""
    from gdbench.core.turntable import RUN_TURNTABLE
    from gdbench.train.run import turntable_size

    found = _run_of(ply)
    if found is None:  # not a run's scene, or a run.json of another scene: framed as any PLY
        return {}
    config = found.get("config") or {}
    return {
        "frames": int(config.get("turntable_frames", 36)),
        "size": turntable_size(config.get("resolution", 128)),
        "background": tuple(float(c) for c in config.get("background", (1.0, 1.0, 1.0))),
        "radius": RUN_TURNTABLE["radius"],
    }


@dataclass
class Score:
    """Score a finished run folder: GT PSNR/SSIM against the asset and COLMAP consistency: the
    registration rate, Var(theta) and translation-direction error, written to its scores.json.
    Each block records its parameters, commit and time; a block is reused (and marked so) only
    when the scene, its parameters and the code (commit and uncommitted edits) match, and
    dropped when they do not."""

    run: tyro.conf.Positional[Path]
    """A run folder with scene.ply (and run.json for the caption)."""
    gt: bool = True
    """Score against the procedural asset (empirical-prior runs)."""
    colmap: bool = True
    """Run the COLMAP consistency metric (seconds on 2 cores; the measured times and their
    conditions: docs/performance.md)."""
    views: Annotated[int, AtLeast(2)] = 100
    """COLMAP's: the number of turntable views rendered and registered."""
    size: Annotated[int, AtLeast(16, "px")] = 256
    """COLMAP's: the side of each rendered view, in pixels."""
    device: Literal["cpu", "cuda", "auto"] = "cpu"
    """Where the scene's views are rendered: cpu, cuda or auto (cuda when torch sees one); the
    images are compared on the CPU, and scores agree across devices to float rounding."""


def run_score(cmd: Score) -> dict:
    from gdbench.app.resources import check_score_memory
    from gdbench.metrics.run_scores import report, score_run

    if not Path(cmd.run).is_dir():
        raise FileNotFoundError(f"run: expected a run folder, got {cmd.run}")
    if cmd.colmap:
        check_score_memory(cmd.size, cmd.views)
    s = score_run(
        cmd.run, gt=cmd.gt, colmap=cmd.colmap, views=cmd.views, size=cmd.size, progress=True, device=cmd.device
    )
    print(report(s))
    return s


@dataclass
class JudgeRuns:
    """Judge run folders with the Janus judge (docs/scoring.md, "The Janus judge"): each result gets one
    of front_everywhere, second_face, blob, fine and a confidence, from its turntable's frames and
    its asset, written to the run's scores.json (the judge block; one made by the same judge on the
    same scene is kept). A sweep folder judges every run folder under it and writes judge.csv
    beside its cells.csv; old runs and sweeps are judged the same way."""

    paths: tyro.conf.Positional[tuple[Path, ...]]
    """Run folders, or folders holding run folders (a sweep's --out)."""
    labels: Path | None = None
    """A labels CSV (run_id, label; as fixtures/labels/*.csv): also print the judge's agreement
    with it (Cohen's kappa on the Janus split and over the four classes)."""


def run_judge(cmd: JudgeRuns) -> list[dict]:
    from gdbench.core.io import read_json, write_csv
    from gdbench.metrics.run_scores import judge_only, judge_text

    if not cmd.paths:
        raise ValueError("paths: expected at least one run folder or folder of run folders")
    runs, tables = [], {}
    for p in cmd.paths:
        p = Path(p)
        if (p / "run.json").is_file():
            runs.append(p)
        elif p.is_dir():
            found = sorted(r.parent for r in p.rglob("run.json") if (r.parent / "scene.ply").is_file())
            if not found:
                raise FileNotFoundError(f"paths: {p} holds no finished run folder (run.json and scene.ply)")
            runs += found
            tables[p] = found
        else:
            raise FileNotFoundError(f"paths: expected a run folder or a folder of run folders, got {p}")
    labels = None
    if cmd.labels:  # checked before any run is judged
        labels = _read_judge_labels(cmd.labels)
        ids = {read_json(r / "run.json", what="run.json").get("run_id") for r in runs}
        unknown = sorted(set(labels) - ids)
        if unknown:
            raise ValueError(f"labels: {cmd.labels} names run id {unknown[0]!r}, which none of the runs under "
                             f"{', '.join(map(str, cmd.paths))} has ({len(unknown)} unknown)")  # fmt: skip
    rows = []
    for run in runs:
        s = judge_only(run)
        j = s["judge"]
        rows.append({"run": str(run), "run_id": s.get("run_id"), "caption": s.get("caption"), "label": j.get("label"),
                     "confidence": j.get("confidence"), "judge_janus": j.get("judge_janus"),
                     "judge_failure": j.get("judge_failure"), "turn_deg": j.get("turn_deg"),
                     "version": j.get("version"), "reused": "judge" in s.get("reused", ())})  # fmt: skip
        print(f"{run}: {judge_text(j)}{' (reused)' if rows[-1]['reused'] else ''}")
    for root, found in tables.items():
        mine = {str(r) for r in found}
        print(
            f"{root}: {len(mine)} runs judged -> {write_csv([r for r in rows if r['run'] in mine], root / 'judge.csv')}"
        )
    if labels is not None:
        _print_agreement(rows, labels, cmd.labels)
    return rows


def _read_judge_labels(path: Path) -> dict[str, str]:
    from gdbench.metrics.agreement import read_labels

    return {r["run_id"]: r["label"] for r in read_labels(Path(path))}


def _print_agreement(rows: list[dict], labels: dict[str, str], path: Path) -> None:
    from gdbench.metrics.judge.evaluate import agreement

    ids = {r["run_id"]: r for r in rows}
    pairs = [(labels[i], ids[i]["label"]) for i in labels if ids[i]["label"] is not None]
    if not pairs:
        print(f"agreement with {path}: none of its {len(labels)} results has a judge's label (no caption?)")
        return
    a = agreement([t for t, _ in pairs], [j for _, j in pairs])
    print(f"agreement with {path} over {a['n']} results: kappa {a['kappa_janus']:.2f} on the Janus split, "
          f"{a['kappa_four']:.2f} over the four classes")  # fmt: skip


@dataclass
class Export:
    """Write a run's scene (or any scene file) for other viewers and editors: the Inria 3DGS PLY
    (padded to an SH degree for Inria's loader), antimatter15's .splat (web viewers),
    SuperSplat's compressed PLY, a triangle mesh (.glb, .obj) by TSDF fusion of rendered depth, or
    an Inria model folder; rotated so the viewer's up axis is up (docs/export.md)."""

    src: tyro.conf.Positional[Path]
    """A run folder (its scene.ply), a PLY (3DGS or compressed) or a .splat file."""
    format: Literal["ply", "splat", "ply-compressed", "glb", "obj", "inria"] = "ply"
    """ply: exact float32, read by Inria's code and most tools; splat: 32 bytes per Gaussian, DC
    colour only; ply-compressed: about 16 bytes per Gaussian plus SH bands at 8 bits; glb, obj: a
    mesh with vertex colours (TSDF fusion of 64 rendered views; needs Open3D; about 20 s); inria:
    an Inria model folder (point_cloud/iteration_N/point_cloud.ply, cameras.json, cfg_args and the
    turntable views as its source) that the SIBR viewer and Inria's render.py load."""
    up: Annotated[UpAxis | None, tyro.conf.DisallowNone] = None
    """The axis that is up in the file written (default: -y for the Gaussian formats, the
    Inria/COLMAP convention of SuperSplat and the .splat viewers; +y for meshes, glTF's). The
    file records it (and the run it comes from), and gdbench's commands read it back."""
    mesh_resolution: Annotated[int, Between(16, 512)] = 192
    """glb, obj: voxels along each side of the fusion's cube (finer: more detail, cube-law memory:
    about 240 MB at 192)."""
    sh_degree: Annotated[int | None, Between(0, 3)] = None
    """SH degree written (ply, ply-compressed): higher pads with zeros (Inria's loader at degree
    3 wants all 45 f_rest_* properties), lower drops view-dependent colour (default: the scene's)."""
    out: Path | None = None
    """The file written (default: beside the source, named by the up axis and, when it differs from
    the scene's, the SH degree: scene.y_down.ply, scene.y_down.sh3.ply, scene.y_down.splat,
    scene.z_up.compressed.ply, scene.y_up.glb, ...); for inria, the folder (default:
    inria.y_down beside the source)."""
    src_up: Annotated[UpAxis | None, tyro.conf.DisallowNone] = None
    """The up axis of the source file (default: the one it records, as every file gdbench writes
    does, else +z). One that differs from the recorded axis is refused: it would rotate the scene
    twice."""


def run_export(cmd: Export) -> dict:
    from gdbench.app.export import SUFFIXES, export_scene, load_scene
    from gdbench.core.filetags import UP_NAMES, read_tags

    src = Path(cmd.src)
    path = src / "scene.ply" if src.is_dir() else src
    if not path.is_file():
        raise FileNotFoundError(f"src: no scene at {path} (pass a run folder, a .ply or a .splat file)")
    scene = load_scene(path, up=cmd.src_up, flag="--src-up")  # checked before --out is decided
    _axis_note(path, cmd.src_up, "--src-up", "export")
    mesh = cmd.format in ("glb", "obj")
    up = cmd.up or ("+y" if mesh else "-y")
    if cmd.format == "inria" and cmd.sh_degree not in (None, 3):
        raise ValueError("sh_degree (--sh-degree): --format inria writes SH degree 3, the Inria loader's")
    if cmd.format == "splat" and cmd.sh_degree not in (None, 0):
        raise ValueError(f"sh_degree (--sh-degree): a .splat holds the DC colour only (degree 0); got {cmd.sh_degree}")
    if cmd.format == "inria":
        return _export_inria(cmd, path, scene, up, read_tags(path).run)
    degree = scene.sh_degree if cmd.sh_degree is None or cmd.format in ("splat", "glb", "obj") else cmd.sh_degree
    stem = path.name.removesuffix(".compressed.ply").removesuffix(".ply").removesuffix(".splat")
    for name in UP_NAMES.values():  # scene.y_down -> scene: the name says the new axis alone
        stem = stem.removesuffix(f".{name}")
    shn = f".sh{degree}" if degree != scene.sh_degree else ""
    suffix = {"ply": ".ply", "splat": ".splat", "ply-compressed": ".compressed.ply", "glb": ".glb", "obj": ".obj"}
    out = Path(cmd.out) if cmd.out is not None else path.parent / f"{stem}.{UP_NAMES[up]}{shn}{suffix[cmd.format]}"
    want = SUFFIXES.get(cmd.format, suffix[cmd.format])
    if out.suffix.lower() != want:  # the API's rule (export._check_path), in the flags' names
        raise ValueError(f"out (--out): --format {cmd.format} writes a {suffix[cmd.format]} file; got {str(out)!r}")
    if out.resolve() == path.resolve():
        raise ValueError(f"out: {out} is the source file; pass another --out")
    from gdbench.train.run import RUN_OUTPUTS

    if out.name in RUN_OUTPUTS and (out.parent / "run.json").is_file():
        raise ValueError(f"out (--out): {out} is one of the run's own outputs; pass another name")
    if cmd.format == "ply" and out.name.lower().endswith(".compressed.ply"):
        raise ValueError(
            f"out (--out): {out.name} names a compressed PLY; pass --format ply-compressed or another name"
        )
    _writable(out, file=True)
    if mesh and cmd.sh_degree is not None:
        raise ValueError(f"sh_degree (--sh-degree): --format {cmd.format} writes vertex colours, not SH bands")
    if cmd.format == "splat" and scene.sh.shape[1] > 1:
        print(f"gdbench export: note: .splat holds the DC colour only; SH degree {scene.sh_degree} dropped")
    if cmd.format == "ply-compressed" and degree > scene.sh_degree:
        print(
            f"gdbench export: warning: SH degree {scene.sh_degree} padded to {degree} with zeros; SuperSplat's engine "
            "reads a zero coefficient (byte 128) as 0.0157, not 0, so its colours shift slightly (docs/export.md)"
        )
    run = read_tags(path).run
    if mesh:
        from gdbench.app.mesh import extract_mesh, write_mesh

        m = extract_mesh(scene, resolution=cmd.mesh_resolution)
        written = write_mesh(m, out, up=up, run=run)
        what = f"{len(m.vertices)} vertices, {len(m.faces)} faces"
    else:
        written = export_scene(scene, out, fmt=cmd.format, up=up, sh_degree=cmd.sh_degree, run=run)
        what = f"SH degree {degree}"
    size = written.stat().st_size
    print(f"gdbench export: {len(scene)} Gaussians -> {written} ({cmd.format}, {up} up, {what}, {size / 1e6:.2f} MB)")
    return {"path": str(written), "bytes": size, "gaussians": len(scene), "up": up, "run": run}


def _export_inria(cmd: Export, path: Path, scene, up: str, run: str | None) -> dict:
    """``export --format inria``: the model folder, seen from the run's turntable (a scene from
    elsewhere: the same orbit about its bounds, at the distance that frames it)."""
    import torch

    from gdbench.app.inria import write_inria_model
    from gdbench.core.camera import SphericalPoses
    from gdbench.core.filetags import UP_NAMES
    from gdbench.core.framing import bounds, orbit_radius
    from gdbench.core.turntable import RUN_TURNTABLE

    out = Path(cmd.out) if cmd.out is not None else path.parent / f"inria.{UP_NAMES[up]}"
    if out.suffix.lower() in (".ply", ".splat", ".glb", ".obj", ".json"):
        raise ValueError(f"out (--out): --format inria writes a folder; got the file name {str(out)!r}")
    _writable(out, file=False)
    turntable = _run_turntable(path)
    if turntable:
        orbit, centre = RUN_TURNTABLE, torch.zeros(3, dtype=torch.float64)
        iteration = int(_run_of(path).get("steps", 0)) or None
    else:
        c, r = bounds(scene)
        centre = c.double()
        orbit = RUN_TURNTABLE | {"radius": orbit_radius(r, RUN_TURNTABLE["fovy"])}
        iteration = None
    size = turntable.get("size", 256)
    cams = SphericalPoses.orbit(turntable.get("frames", 36), **orbit).cameras(size, size)
    shift = torch.eye(4, dtype=torch.float64)
    shift[:3, 3] = -centre
    cams = type(cams)((cams.viewmats.double() @ shift).float(), cams.Ks, size, size)
    folder = write_inria_model(
        scene, out, cams, up=up, run=run, iteration=iteration, background=turntable.get("background", (1.0, 1.0, 1.0))
    )
    print(f"gdbench export: {len(scene)} Gaussians -> {folder}/ (inria model folder, {up} up, {len(cams)} views)")
    return {"path": str(folder), "gaussians": len(scene), "up": up, "run": run}


@dataclass
class View:
    """Interactive viewer of a run folder or any scene file in the browser (viser): the splats,
    the run's turntable cameras on a slider and its training-view frustums (docs/viewer.md).
    Serves until Ctrl-C."""

    run: tyro.conf.Positional[Path]
    """A run folder (its scene.ply, and run.json for the turntable and training views) or a scene
    file (3DGS or compressed PLY, .splat)."""
    port: Annotated[int, Between(1, 65535)] = 8080
    """Port to serve on (viser takes the next free one when it is busy)."""
    host: str = "127.0.0.1"
    """Interface to listen on (0.0.0.0: every interface; default: this machine only)."""
    up: Annotated[UpAxis | None, tyro.conf.DisallowNone] = None
    """The up axis of the scene file (default: the one the file records, as every file gdbench
    writes does, else +z): +z for gdbench's runs, -y for Inria/COLMAP captures. One that differs
    from the file's recorded axis is refused."""
    frustums: bool = False
    """Show the run's training-view frustums at start (a checkbox toggles them)."""


def run_view(cmd: View) -> dict:
    from gdbench.app.viewer import serve

    v = serve(cmd.run, host=cmd.host, port=cmd.port, up=cmd.up, frustums=cmd.frustums)  # until Ctrl-C
    return {"url": v.url}
