"""The Janus judge at run time: a result's views at known cameras and its caption -> one of the
labelling rule's classes (front_everywhere, second_face, blob, fine) with a confidence.

Two modes, one reading (``reading.result_features``):
- **six views**, as a label sheet shows a result (azimuths 0, 60, ..., 300 at elevation 15):
  ``Judge.views``; every committed sheet can be judged this way;
- **a run folder** (or a scene): its turntable's 36 frames, 10 degrees apart on the same orbit,
  rendered from scene.ply as turntable.gif shows them: ``Judge.run``, ``Judge.scene``.

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
"""The shipped judge: eye.safetensors (the eye's weights and its settings), head.json and, from the
judge's second version, templates.safetensors (the assets' renders its sameness reading compares
views with: ``sameness.py``; a folder without them is a first-version judge, read as it was)."""
TURNTABLE_FRAMES = 36
"""A run turntable's frames (azimuths 0, 10, ..., 350)."""


class Judge:
    def __init__(self, folder: Path = WEIGHTS):
        from safetensors.torch import load_file, safe_open

        from gdbench.metrics.judge.head import load_head
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
        self.head = load_head(self.head_info["head"])
        self.curves = self.head_info["aspect_curves"]
        parts = [eye_path.read_bytes(), head_path.read_bytes()]
        self.templates = None
        if (folder / "templates.safetensors").is_file():
            from gdbench.metrics.judge.sameness import Templates

            self.templates = Templates.load(folder / "templates.safetensors")
            parts.append((folder / "templates.safetensors").read_bytes())
        from gdbench.metrics.judge.look import LOOK
        from gdbench.metrics.judge.marking import FRONT
        from gdbench.metrics.judge.reading import FEATURES
        from gdbench.metrics.judge.sameness import ALIGNED, SAMENESS

        n, first, same = self.head.n_features, 2 * len(FEATURES), len(SAMENESS)
        self.references = self.head_info.get("references")
        """{caption: rows} of the asset's own fixtures the head reads a result against
        (``reference.against``; the seventh judge's), None for the others."""
        known, look = (first,), first + same + len(LOOK)  # the readings up to the look: the 50
        if self.templates is not None:
            known = (first + same - ALIGNED, first + same, look, look + len(FRONT))
        from gdbench.metrics.judge.reference import REFERENCE

        # the seventh's: the 50 against its references (no templates: the readings cannot give them)
        against = (1 + len(REFERENCE)) * (look if self.templates is not None else first)
        if self.references is not None:
            kinds = self.head_info.get("reference_kinds", list(REFERENCE))
            if list(kinds) != list(REFERENCE):
                raise ValueError(f"judge: {head_path} keeps references of {kinds}, this code reads {list(REFERENCE)}")
            known = (against,)
        if n not in known:
            why = ("its head reads the readings against references that head.json does not keep"
                   if self.references is None and n == against and self.templates is not None
                   else "templates.safetensors missing or extra, or references kept for another head?")  # fmt: skip
            raise ValueError(
                f"judge: {head_path} reads {n} features, the folder's parts give {' or '.join(map(str, known))} "
                f"({why}); train it again with `gdbench train-judge`"
            )
        self.n_features = n
        """How many of the readings' features the head reads, in order: a judge reads the ones it was
        fitted on (the first version 20, the second 26, the third 30, the fourth 50: the look too; the
        seventh 200: the 50 and the 50 less each of the asset's three reference fixtures'; the eighth
        57: the 50, the front marking and the outline's match, ``marking.FRONT``)."""
        self.version = hashlib.sha256(b"".join(parts)).hexdigest()[:12]

    def knows(self, caption: str | None) -> bool:
        return bool(caption) and caption in self.eye.config.captions

    def feature_names(self) -> list[str]:
        """The names of ``features``' values: the eye's turntable features, the outline's
        (``outline_`` before each) and, with templates, the sameness reading's and the look's; with
        references, then each of them less each reference's (``vs_<kind>_<name>``)."""
        from gdbench.metrics.judge.look import LOOK
        from gdbench.metrics.judge.marking import FRONT
        from gdbench.metrics.judge.reading import FEATURES
        from gdbench.metrics.judge.sameness import SAMENESS

        names = [*FEATURES, *(f"outline_{k}" for k in FEATURES)]
        if self.templates is not None:
            names += [*SAMENESS, *LOOK]
        if self.references is not None:
            from gdbench.metrics.judge.reference import names as against_names

            return against_names(names)
        names += list(FRONT) if self.templates is not None else []
        return names[: self.n_features]

    def features(self, views, azimuths, caption: str):
        """(features [F], the eye's readings [V, BINS]) of one result (``reading.result_features``),
        as the head reads them (``head_rows``)."""
        from gdbench.metrics.judge.reading import result_features

        x, q = result_features(self.eye, self.curves, torch.as_tensor(views), torch.as_tensor(azimuths),
                               caption, self.templates)  # fmt: skip
        return self.head_rows(x[None], [caption])[0], q

    def head_rows(self, x, captions: list[str]):
        """The readings [N, F] (``reading.result_features``, as many as the folder's parts give) of
        results of ``captions`` -> what the head reads: their first ``n_features``, or, for a judge
        with references (the seventh), the numbers its references hold (the first 50) and the same
        less the asset's reference fixtures' (``reference.against``)."""
        if self.references is None:
            return x[:, : self.n_features]
        from gdbench.metrics.judge.reference import REFERENCE, against

        return against(x[:, : self.n_features // (1 + len(REFERENCE))], list(captions), self.references)

    def views(self, views, azimuths, caption: str) -> dict:
        """Judge one result from ``views`` [V, H, W, 3] (uint8 or float in [0, 1], white
        background) at camera ``azimuths`` [V] (degrees, elevation 15 as the turntables)."""
        from gdbench.assets.library import has_front
        from gdbench.metrics.judge.head import CLASSES3, decide
        from gdbench.metrics.judge.net import BINS
        from gdbench.metrics.judge.reading import best_turn

        views = torch.as_tensor(np.asarray(views))
        azimuths = torch.as_tensor(azimuths, dtype=torch.float32)
        if views.ndim != 4 or views.shape[-1] < 3 or len(views) != len(azimuths) or len(views) < 3:
            raise ValueError(
                f"views: expected [V, H, W, 3] images at V >= 3 azimuths, got {tuple(views.shape)} "
                f"and {len(azimuths)} azimuths"
            )
        floats = views.is_floating_point()
        if (floats and float(views.max()) > 1.0) or (not floats and views.dtype != torch.uint8):
            raise ValueError(
                f"views: expected uint8 images or floats in [0, 1] (white background), got {views.dtype} "
                f"with values up to {float(views.max()):g}"
            )
        if not self.knows(caption):
            raise ValueError(f"caption: the judge knows no asset {caption!r}")
        x, q = self.features(views[..., :3], azimuths, caption)
        p = self.head.probabilities(x[None])[0]
        label, confidence = decide(p, x, has_front(caption))
        step = 360.0 / BINS
        reading = (q.argmax(1).float() * step + 180.0) % 360.0 - 180.0
        return {
            "label": label,
            "confidence": round(confidence, 4),
            "probabilities": {c: round(float(v), 4) for c, v in zip(CLASSES3, p)},
            "turn_deg": best_turn(q, azimuths),
            "features": dict(zip(self.feature_names(), (round(float(v), 4) for v in x))),
            "views": [
                {"azimuth": round(float(a), 2), "reads_deg": float(r), "reading_confidence": round(float(c), 4)}
                for a, r, c in zip(azimuths, reading, q.max(1).values)
            ],
            "mode": f"{len(views)} views",
            "version": self.version,
        }

    def run(self, folder: Path, caption: str | None = None) -> dict:
        """Judge a run folder: its scene (scene.ply) on the run turntable's orbit, the frames
        turntable.gif shows before its palette (``turntable_frames``), for the caption its run.json
        names unless ``caption``. A result with no asset to compare with gets ``{"label": None,
        "reason": ...}``, not a guess."""
        folder = Path(folder)
        if caption is None:
            info = json.loads((folder / "run.json").read_text()) if (folder / "run.json").is_file() else {}
            caption = info.get("caption") or None
        ply = folder / "scene.ply"
        if not ply.is_file():
            raise FileNotFoundError(f"run: {folder} has no scene.ply to judge (is the run finished?)")
        from gdbench.core.scene import GaussianScene

        return self.scene(GaussianScene.load_ply(ply), caption)

    def scene(self, scene, caption: str | None) -> dict:
        """Judge a scene from its 36 turntable frames (``turntable_frames``)."""
        if not self.knows(caption):
            why = "no caption" if not caption else f"the judge knows no asset {caption!r}"
            return {"label": None, "reason": f"{why}: nothing to compare the result with", "version": self.version}
        frames = turntable_frames(scene)
        out = self.views(frames, np.arange(len(frames)) * (360.0 / len(frames)), caption)
        out["mode"] = f"turntable: {len(frames)} frames"
        return out


def turntable_frames(scene, size: int = 128, frames: int = TURNTABLE_FRAMES) -> np.ndarray:
    """[frames, size, size, 3] uint8: ``scene`` on the run turntable's orbit (``turntable.RUN_TURNTABLE``,
    azimuths 0, 10, ..., 350 for the default 36; 0, 60, ..., 300 for a sheet's 6) on white, as a run's
    turntable.gif shows it (its frames are 128 px at the default training resolution; the GIF's
    palette aside)."""
    from gdbench.core.camera import SphericalPoses
    from gdbench.core.turntable import RUN_TURNTABLE, render_views, to_uint8

    cams = SphericalPoses.orbit(frames, **RUN_TURNTABLE).cameras(size, size)
    return to_uint8(render_views(scene.to("cpu"), cams, (1.0, 1.0, 1.0)))


SEVENTH_HEAD = Path(__file__).resolve().parents[3] / "docs/results/judge/seventh/head.json"
"""The seventh judge's head (c18485a29831), fitted on the same eye and templates as the eighth:
``with_head(SEVENTH_HEAD, folder)`` makes the seventh judge again, byte for byte."""


def with_head(head: Path, folder: Path) -> Path:
    """A judge folder at ``folder``: the shipped eye and templates with the head.json ``head`` (an
    earlier judge's head fitted on the same eye, ``SEVENTH_HEAD``); where the eye and templates are
    that judge's bytes, the folder's judge has that judge's version."""
    import shutil

    head, folder = Path(head), Path(folder)
    if not head.is_file():
        raise FileNotFoundError(f"head: {head} is missing")
    folder.mkdir(parents=True, exist_ok=True)
    for name in ("eye.safetensors", "templates.safetensors"):
        shutil.copyfile(WEIGHTS / name, folder / name)
    shutil.copyfile(head, folder / "head.json")
    return folder


@functools.lru_cache(maxsize=2)
def load_judge(folder: str | None = None) -> Judge:
    """The judge in ``folder`` (default: the shipped one), loaded once per process."""
    return Judge(Path(folder) if folder else WEIGHTS)


def judge_block(scene, caption: str | None) -> dict:
    """scores.json's ``judge`` block of a scene: the judge's label, confidence, per-view readings
    and version, with ``judge_janus`` (1 for front_everywhere or second_face; None for an asset
    without a front) and ``judge_failure`` (1 for anything but fine); ``label`` None with the
    reason where there is nothing to judge against (no caption, an asset the judge does not know)
    or no judge."""
    try:
        judge = load_judge()
    except FileNotFoundError as e:
        return {"label": None, "reason": str(e), "version": None}
    out = judge.scene(scene, caption)
    if out["label"] is not None:
        from gdbench.assets.library import has_front
        from gdbench.metrics.agreement import JANUS

        # an asset without a front cannot be Janus: undefined, as the view classes' Janus rate
        out["judge_janus"] = int(out["label"] in JANUS) if has_front(caption) else None
        out["judge_failure"] = int(out["label"] != "fine")
    return out


def judge_version() -> str | None:
    """The shipped judge's version, None where its weights are missing."""
    try:
        return load_judge().version
    except FileNotFoundError:
        return None
