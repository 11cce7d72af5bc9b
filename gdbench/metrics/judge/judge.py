"""The Janus judge at run time: a result's views at known cameras and its caption -> one of the
labelling rule's classes (front_everywhere, second_face, blob, fine) with a confidence.

Two modes, one reading (``reading.turntable_features``):
- **six views**, as a label sheet shows a result (azimuths 0, 60, ..., 300 at elevation 15):
  ``Judge.views``; every committed sheet can be judged this way;
- **a run folder**: its turntable's frames (``turntable.gif``: 36 frames, 10 degrees apart, the
  same orbit) or, where the GIF is gone, ``scene.ply`` rendered on that orbit: ``Judge.run``.

The judge's version is the hash of its weights and its head (``Judge.version``): a score block
stamped with another version is judged again, not reused.
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path

import numpy as np
import torch

WEIGHTS = Path(__file__).parent / "weights"
"""The shipped judge: eye.safetensors (the eye's weights and its settings) and head.json."""
TURNTABLE_FRAMES = 36
"""A run turntable's frames (azimuths 0, 10, ..., 350)."""


class Judge:
    def __init__(self, folder: Path = WEIGHTS):
        from safetensors.torch import load_file, safe_open

        from gdbench.metrics.judge.head import Head
        from gdbench.metrics.judge.net import Eye, EyeConfig

        folder = Path(folder)
        eye_path, head_path = folder / "eye.safetensors", folder / "head.json"
        for p in (eye_path, head_path):
            if not p.is_file():
                raise FileNotFoundError(f"judge: {p} is missing; train the judge with `gdbench train-judge`")
        with safe_open(str(eye_path), "pt") as f:
            self.meta = dict(f.metadata() or {})
        self.eye = Eye(EyeConfig.from_dict(json.loads(self.meta["config"])))
        self.eye.load_state_dict({k: v.float() for k, v in load_file(str(eye_path)).items()})
        self.eye.eval().requires_grad_(False)
        self.head_info = json.loads(head_path.read_text())
        self.head = Head.from_dict(self.head_info["head"])
        digest = hashlib.sha256(eye_path.read_bytes() + head_path.read_bytes()).hexdigest()
        self.version = digest[:12]

    def knows(self, caption: str | None) -> bool:
        return bool(caption) and caption in self.eye.config.captions

    def views(self, views, azimuths, caption: str) -> dict:
        """Judge one result from ``views`` [V, H, W, 3] (uint8 or float in [0, 1], white
        background) at camera ``azimuths`` [V] (degrees, elevation 15 as the turntables)."""
        from gdbench.assets.library import has_front
        from gdbench.metrics.judge.head import CLASSES3, decide
        from gdbench.metrics.judge.net import BINS, crop_views
        from gdbench.metrics.judge.reading import FEATURES, best_turn, read_views, turntable_features

        views = torch.as_tensor(np.asarray(views))
        azimuths = torch.as_tensor(azimuths, dtype=torch.float32)
        if views.ndim != 4 or views.shape[-1] < 3 or len(views) != len(azimuths) or len(views) < 3:
            raise ValueError(
                f"views: expected [V, H, W, 3] images at V >= 3 azimuths, got {tuple(views.shape)} "
                f"and {len(azimuths)} azimuths"
            )
        q = read_views(self.eye, crop_views(views[..., :3]), caption)
        x = turntable_features(q, azimuths)
        p = self.head.probabilities(x[None])[0]
        label, confidence = decide(p, x, has_front(caption))
        step = 360.0 / BINS
        reading = (q.argmax(1).float() * step + 180.0) % 360.0 - 180.0
        return {
            "label": label,
            "confidence": round(confidence, 4),
            "probabilities": {c: round(float(v), 4) for c, v in zip(CLASSES3, p)},
            "turn_deg": best_turn(q, azimuths),
            "features": {k: round(float(v), 4) for k, v in zip(FEATURES, x)},
            "views": [
                {"azimuth": round(float(a), 2), "reads_deg": float(r), "reading_confidence": round(float(c), 4)}
                for a, r, c in zip(azimuths, reading, q.max(1).values)
            ],
            "mode": f"{len(views)} views",
            "version": self.version,
        }

    def run(self, folder: Path, caption: str | None = None) -> dict:
        """Judge a run folder (its run.json's caption unless ``caption``) from its turntable's
        frames, or from scene.ply rendered on the turntable's orbit where the GIF is gone.
        A result with no asset to compare with gets ``{"label": None, "reason": ...}``."""
        folder = Path(folder)
        if caption is None:
            info = json.loads((folder / "run.json").read_text()) if (folder / "run.json").is_file() else {}
            caption = info.get("caption") or None
        if not self.knows(caption):
            why = "no caption" if not caption else f"the judge knows no asset {caption!r}"
            return {"label": None, "reason": f"{why}: nothing to compare the result with", "version": self.version}
        frames, mode = turntable_frames(folder)
        out = self.views(frames, np.arange(len(frames)) * (360.0 / len(frames)), caption)
        out["mode"] = mode
        return out


def turntable_frames(folder: Path) -> tuple[np.ndarray, str]:
    """The run's turntable as [36, H, W, 3] uint8 frames and where they came from."""
    gif = Path(folder) / "turntable.gif"
    if gif.is_file():
        import imageio.v3 as iio

        frames = iio.imread(gif)[..., :3]
        if len(frames) == TURNTABLE_FRAMES:
            return frames, "turntable.gif"
    ply = Path(folder) / "scene.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"run: {folder} has neither turntable.gif nor scene.ply to judge")
    from gdbench.core.camera import SphericalPoses
    from gdbench.core.scene import GaussianScene
    from gdbench.core.turntable import RUN_TURNTABLE, render_views, to_uint8

    cams = SphericalPoses.orbit(TURNTABLE_FRAMES, **RUN_TURNTABLE).cameras(128, 128)
    return to_uint8(render_views(GaussianScene.load_ply(ply), cams, (1.0, 1.0, 1.0))), "scene.ply"


@functools.lru_cache(maxsize=2)
def load_judge(folder: str | None = None) -> Judge:
    """The judge in ``folder`` (default: the shipped one), loaded once per process."""
    return Judge(Path(folder) if folder else WEIGHTS)
