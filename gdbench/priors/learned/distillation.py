"""Guidance in one network call: a student distilled from a finished model (the teacher).

Classifier-free guidance evaluates the network twice per prediction, with the conditions and
without: ``v_u + s (v_c - v_u)``. The student, the teacher's architecture started from its weights,
learns that guided prediction at one scale ``s`` for the teacher's own training inputs (the same
views, noise levels and condition drops, so it also keeps the caption-only prediction of view
prompting 'none'):

    loss = |v_student(x_t, t, c) - (v_teacher(x_t, t, 0) + s (v_teacher(x_t, t, c) - v_teacher(x_t, t, 0)))|^2

(the combination is affine, so it is the same in epsilon or v terms). The weights record
``teacher_guidance`` in their metadata; the prior then makes one call where the teacher made two,
and refuses any other ``--learned-guidance`` in one line naming the model (``prior.LearnedPrior``).

    gdbench train-prior --teacher runs/prior-world64p4-uniform/model.safetensors --teacher-guidance 3 \\
        --steps 3000 --out runs/prior-world64p4-uniform-1call
"""

from __future__ import annotations

import json
from pathlib import Path

import torch

from gdbench.priors.learned.training import PriorTrainConfig
from gdbench.priors.learned.unet import UNet


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


def load_teacher(cfg: PriorTrainConfig, device) -> UNet:
    """The teacher of ``cfg`` (eval mode, no gradients), checked to have the student's architecture
    and data."""
    from dataclasses import asdict

    from gdbench.priors.learned.prior import load_model

    net, meta = load_model(cfg.teacher, device)
    ident = json.loads(meta.get("train", "{}"))
    if asdict(net.config) != asdict(cfg.unet) or ident.get("data") != json.loads(json.dumps(asdict(cfg.data))):
        raise ValueError(f"teacher: {cfg.teacher} has another architecture or data than this run; build the run "
                         "with distill_config (train-prior --teacher)")  # fmt: skip
    return net


@torch.no_grad()
def guided_target(teacher: UNet, b: dict[str, torch.Tensor], scale: float) -> torch.Tensor:
    """The teacher's classifier-free guided prediction at ``scale`` for the batch's inputs (its
    conditions as drawn, with their drops) in the network's own output terms, both evaluations as
    one batch: the unconditional one drops caption, variant and camera."""
    c, t, cap, var = teacher.config, b["t"], b["caption"], b["variant"]
    B = t.shape[0]
    drop = torch.cat([torch.ones(B, dtype=torch.bool, device=t.device), b["camera_drop"].bool()])
    emb = teacher.embedding(
        torch.cat([t, t]),
        torch.cat([torch.full_like(cap, c.captions), cap]),
        torch.cat([torch.full_like(var, c.variants), var]),
        torch.cat([b["camera"], b["camera"]]),
        drop,
    )
    vu, vc = teacher(torch.cat([b["x_t"], b["x_t"]]), emb).chunk(2)
    return vu + scale * (vc - vu)
