"""Turntables: render a scene from an orbit and write a GIF, an MP4 and a contact sheet."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from gdbench.core.camera import Cameras, SphericalPoses
from gdbench.core.scene import GaussianScene

RUN_TURNTABLE = {"radius": 1.3, "elevation": 15.0, "fovy": 45.0}
"""The orbit of a training run's turntable (``train.run``; ``cfg.turntable_frames`` frames) and of
the browser viewer's turntable views (``gdbench.app.viewer``)."""


@dataclass
class TurntableResult:
    frames: np.ndarray
    """[F, H, W, 3] uint8."""
    seconds_per_frame: list[float]
    paths: dict[str, Path]


def render_views_outputs(
    scene: GaussianScene,
    cams: Cameras,
    background=(1.0, 1.0, 1.0),
    batch: int = 8,
    outputs: tuple[str, ...] = ("rgb", "alpha"),
    **kwargs,
) -> dict[str, torch.Tensor]:
    """Render cameras in batches without gradients, on the scene's device; returns each of
    ``outputs`` on the CPU, where outputs and scores are made: rgb [C, H, W, 3] in [0, 1], alpha
    and depth [C, H, W]."""
    from renderers.splat import rasterize

    bg = torch.as_tensor(background, dtype=scene.means.dtype, device=scene.means.device)
    out: dict[str, list] = {o: [] for o in outputs}
    with torch.no_grad():
        for i in range(0, len(cams), batch):
            c = cams[i : i + batch].to(scene.means.device)
            r = rasterize(
                **scene.render_args(),
                viewmats=c.viewmats,
                Ks=c.Ks,
                width=c.width,
                height=c.height,
                background=bg,
                outputs=outputs,
                **kwargs,
            )
            for o in outputs:
                x = getattr(r, o)
                out[o].append((x.clamp(0, 1) if o == "rgb" else x[..., 0]).cpu())
    return {o: torch.cat(v) for o, v in out.items()}


def render_views_alpha(
    scene: GaussianScene, cams: Cameras, background=(1.0, 1.0, 1.0), batch: int = 8, **kwargs
) -> tuple[torch.Tensor, torch.Tensor]:
    """(rgb [C, H, W, 3] in [0, 1], alpha [C, H, W]) of ``render_views_outputs``."""
    r = render_views_outputs(scene, cams, background, batch, ("rgb", "alpha"), **kwargs)
    return r["rgb"], r["alpha"]


def render_views(
    scene: GaussianScene, cams: Cameras, background=(1.0, 1.0, 1.0), batch: int = 8, **kwargs
) -> torch.Tensor:
    """Render cameras in batches without gradients; returns [C, H, W, 3] in [0, 1], on the CPU."""
    return render_views_alpha(scene, cams, background, batch, **kwargs)[0]


def to_uint8(images: torch.Tensor) -> np.ndarray:
    return (images.clamp(0, 1) * 255 + 0.5).to(torch.uint8).cpu().numpy()


def contact_sheet(frames: np.ndarray, columns: int = 6) -> np.ndarray:
    """Tile [F, H, W, 3] frames into one image, ``columns`` per row (white padding)."""
    f, h, w, c = frames.shape
    columns = max(1, min(columns, f))
    rows = (f + columns - 1) // columns
    sheet = np.full((rows * h, columns * w, c), 255, dtype=np.uint8)
    for i in range(f):
        r, col = divmod(i, columns)
        sheet[r * h : (r + 1) * h, col * w : (col + 1) * w] = frames[i]
    return sheet


OUTPUTS = ("rgb", "depth", "alpha")
"""What ``write_turntable`` renders: colour, expected depth (scene units along the view axis, 0
where nothing is), alpha."""


def _visual(name: str, x: torch.Tensor) -> torch.Tensor:
    """[F, H, W] depth or alpha as [F, H, W, 3] images in [0, 1]: alpha grey (white: opaque),
    depth by matplotlib's turbo over the covered pixels' 1st-99th percentile (near: red), empty
    pixels white."""
    if name == "alpha":
        return x[..., None].expand(*x.shape, 3)
    from matplotlib import colormaps

    covered = x > 0
    if not bool(covered.any()):
        return torch.ones(*x.shape, 3)
    v = x[covered].double()
    lo, hi = (
        float(q)
        for q in torch.quantile(v[:: max(1, v.numel() // 1_000_000)], torch.tensor([0.01, 0.99], dtype=v.dtype))
    )
    t = ((x.double() - lo) / max(hi - lo, 1e-12)).clamp(0, 1)
    rgb = torch.from_numpy(colormaps["turbo"](1.0 - t.numpy())[..., :3]).float()
    return torch.where(covered[..., None], rgb, torch.ones_like(rgb))


def write_turntable(
    scene: GaussianScene,
    out_dir: str | Path,
    *,
    frames: int = 36,
    size: int = 256,
    radius: float = 1.3,
    elevation: float = 20.0,
    fovy: float = 45.0,
    background=(1.0, 1.0, 1.0),
    fps: float = 12,
    mp4: bool = True,
    stem: str = "turntable",
    cams: Cameras | None = None,
    outputs: tuple[str, ...] = ("rgb",),
) -> TurntableResult:
    """Render ``frames`` views on a circle (or ``cams``, then frames, size, radius, elevation and
    fovy are theirs) and write ``{stem}.gif``, ``.mp4`` and ``_sheet.png`` of each of ``outputs``
    (``OUTPUTS``): rgb as ``{stem}.*``, depth and alpha as ``{stem}_depth.*`` and
    ``{stem}_alpha.*`` (``_visual``), with their values as float32 [F, H, W] in ``{stem}_depth.npy``
    and ``{stem}_alpha.npy``."""
    import imageio.v3 as iio

    from gdbench.core.io import atomic_path

    bad = [o for o in outputs if o not in OUTPUTS]
    if bad or not outputs:
        raise ValueError(f"outputs: expected some of {', '.join(OUTPUTS)}, got {list(outputs)!r}")
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    if cams is None:
        cams = SphericalPoses.orbit(frames, radius=radius, elevation=elevation, fovy=fovy).cameras(size, size)
    frames = len(cams)
    want = tuple(o for o in OUTPUTS if o in {"rgb", "alpha", *outputs})
    times, imgs = [], {o: [] for o in want}
    for i in range(frames):
        t0 = time.perf_counter()
        r = render_views_outputs(scene, cams[i], background, outputs=want)
        for o in want:
            imgs[o].append(r[o])
        times.append(time.perf_counter() - t0)
    paths: dict[str, Path] = {}
    for name in outputs:
        values = torch.cat(imgs[name])
        tag = "" if name == "rgb" else f"_{name}"
        if name != "rgb":
            with atomic_path(out_dir / f"{stem}{tag}.npy") as tmp:
                np.save(tmp, values.float().numpy())
            paths[f"{name}_npy"] = out_dir / f"{stem}{tag}.npy"
        arr = to_uint8(values if name == "rgb" else _visual(name, values))
        key = lambda k, name=name: k if name == "rgb" else f"{name}_{k}"  # noqa: E731
        paths[key("gif")] = out_dir / f"{stem}{tag}.gif"
        paths[key("sheet")] = out_dir / f"{stem}{tag}_sheet.png"
        with atomic_path(paths[key("gif")]) as tmp:
            iio.imwrite(tmp, arr, duration=1000 / fps, loop=0)
        with atomic_path(paths[key("sheet")]) as tmp:
            iio.imwrite(tmp, contact_sheet(arr[:: max(1, frames // 12)][:12]))
        if mp4:
            try:
                with atomic_path(out_dir / f"{stem}{tag}.mp4") as tmp:
                    iio.imwrite(tmp, arr, fps=fps, codec="libx264", plugin="pyav")
                paths[key("mp4")] = out_dir / f"{stem}{tag}.mp4"
            except OSError:  # a full disk is the run's error, not a missing codec
                raise
            except Exception as e:  # pyav missing or without x264: the GIF is still there
                print(f"note: MP4 not written ({type(e).__name__}: {e}); install `av` for MP4 output")
                mp4 = False
    return TurntableResult(to_uint8(torch.cat(imgs["rgb"])), times, paths)


def demo(out: Path, *, frames: int = 36, size: int = 256, gaussians: int = 3000, seed: int = 0) -> dict:
    """``gdbench demo``: the built-in scene as a turntable; writes summary.json and prints timings."""
    import platform
    import time

    from gdbench.core.builtin import demo_scene
    from renderers.splat._ext import extension_status

    out = Path(out)
    t0 = time.perf_counter()
    scene = demo_scene(gaussians, seed=seed)
    res = write_turntable(scene, out, frames=frames, size=size)
    total = time.perf_counter() - t0
    ply = scene.save_ply(out / "scene.ply")
    per = sorted(res.seconds_per_frame)
    summary = {
        "command": "demo",
        "config": {"out": str(out), "frames": frames, "size": size, "gaussians": gaussians, "seed": seed},
        "gaussians": len(scene),
        "frames": frames,
        "resolution": [size, size],
        "first_frame_s": res.seconds_per_frame[0],
        "median_frame_s": per[len(per) // 2],
        "fps_median": 1.0 / per[len(per) // 2],
        "total_s": total,
        "compositor": extension_status(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "machine": platform.machine(),
        "outputs": {k: str(v) for k, v in res.paths.items()} | {"ply": str(ply)},
    }
    from gdbench.core.io import write_json

    write_json(summary, out / "summary.json")
    print(f"gdbench demo: {len(scene)} Gaussians, {frames} frames at {size}x{size}")
    print(f"  first frame {summary['first_frame_s'] * 1e3:8.1f} ms (includes loading the compositor)")
    print(f"  median      {summary['median_frame_s'] * 1e3:8.1f} ms  ({summary['fps_median']:.1f} frames/s)")
    print(f"  total       {total:8.2f} s   compositor: {summary['compositor']}")
    for k, v in summary["outputs"].items():
        print(f"  {k:5s} -> {v}")
    return summary
