"""Guidance in one network call: a student distilled from a finished model (the teacher).

Classifier-free guidance evaluates the network twice per prediction, with the conditions and
without: ``v_u + s (v_c - v_u)``. The student, the teacher's architecture started from its weights,
learns that guided prediction at one scale ``s`` for the teacher's own training inputs (the same
views, noise levels and condition drops, so it also keeps the caption-only prediction of view
prompting 'none'):

    loss = |v_student(x_t, t, c) - (v_teacher(x_t, t, 0) + s (v_teacher(x_t, t, c) - v_teacher(x_t, t, 0)))|^2

(the combination is affine, so it is the same in epsilon or v terms; ``training.guided_target``,
and ``training.load_teacher`` checks the teacher against the run). The weights record
``teacher_guidance`` in their metadata; the prior then makes one call where the teacher made two,
and refuses any other ``--learned-guidance`` in one line naming the model (``prior.LearnedPrior``).

    gdbench train-prior --teacher runs/prior-world64p4-uniform/model.safetensors --teacher-guidance 3 \\
        --steps 3000 --out runs/prior-world64p4-uniform-1call
"""

from __future__ import annotations

import json
from pathlib import Path

from gdbench.priors.learned.training import PriorTrainConfig


def _identity_of(teacher: str | Path) -> dict:
    from gdbench.priors.learned.prior import _metadata, model_path

    meta = _metadata(model_path(teacher))
    if "train" not in meta or "unet" not in meta:
        raise ValueError(f"teacher: {teacher} has no training settings in its metadata (not written by train-prior)")
    ident = json.loads(meta["train"])
    if ident.get("teacher"):
        raise ValueError(f"teacher: {teacher} is itself distilled (guidance {ident.get('teacher_guidance')}); "
                         "distil from the model it was distilled from")  # fmt: skip
    return ident


def distill_config(teacher: str | Path, scale: float, **kw) -> PriorTrainConfig:
    """The training settings of a student of ``teacher`` (a weights path or shipped name) at guidance
    ``scale``: the teacher's architecture, data, captions, view weighting and drop rates, with ``kw``
    (out, steps, lr, batch, warmup, seed, threads, device, ...) on top."""
    from gdbench.priors.learned.data import DataConfig
    from gdbench.priors.learned.prior import model_path
    from gdbench.priors.learned.unet import UNetConfig

    ident = _identity_of(teacher)
    u = ident["unet"]
    unet = UNetConfig(**{**u, "widths": tuple(u["widths"]), "parts": tuple(tuple(r) for r in u.get("parts", ())),
                         "part_sizes": tuple(u.get("part_sizes", ()))})  # fmt: skip
    inherited = {k: ident[k] for k in ("front_bias", "caption_drop", "variant_drop", "camera_drop") if k in ident}
    return PriorTrainConfig(
        **(inherited | {"lr": 1e-4, "warmup": 100} | kw),
        unet=unet,
        data=DataConfig.from_dict(ident["data"]),
        held_out=tuple(ident.get("held_out", ())),
        teacher=str(model_path(teacher).resolve()),
        teacher_guidance=float(scale),
    )
