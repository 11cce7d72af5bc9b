"""A first look at learned models' samples beside the ground truth: DDIM samples (30 steps, the
camera given, seed 0) of four captions at azimuths 0, 90, 180, -90, one row per model (32 px models
upsampled 2 x 2), under the assets' own renders at the same cameras.

    python scripts/look_world64.py OUT.png MODEL [MODEL ...]   # e.g. runs/.../model.safetensors uniform
"""

import sys

import numpy as np
import torch
from PIL import Image, ImageDraw

from gdbench.priors.learned.evaluation import render_views
from gdbench.priors.learned.prior import LearnedPrior

CAPTIONS = ("a yellow duck", "a corgi", "a blue duck", "a red frog")
AZ = (0.0, 90.0, 180.0, -90.0)


def row(images: list[torch.Tensor]) -> np.ndarray:
    out = []
    for x in images:  # [4, h, h, 3] in [-1, 1]
        x = ((x.clamp(-1, 1) + 1) / 2 * 255).byte()
        if x.shape[1] != 64:
            x = x.repeat_interleave(64 // x.shape[1], 1).repeat_interleave(64 // x.shape[1], 2)
        out.append(np.concatenate(list(x.numpy()), 1))
    return np.concatenate(out, 1)


def main(argv: list[str]) -> int:
    out, models = argv[0], argv[1:]
    cam = torch.tensor([[a, 15.0, 55.0] for a in AZ])
    rows, names = [], []
    for m in models:
        p = LearnedPrior(m, view_mode="window")
        rows.append(row([p.sample(p.encode(c), cam, generator=torch.Generator().manual_seed(0), steps=30, n=len(AZ))
                         for c in CAPTIONS]))  # fmt: skip
        names.append(f"{m.split('/')[-2] if '/' in m else m} ({p.size} px)")
    rows.append(row([render_views(c, torch.tensor(AZ), 15.0, 55.0, size=64) for c in CAPTIONS]))
    names.append("ground truth (64 px)")
    img = np.concatenate(rows, 0)
    canvas = Image.new("RGB", (img.shape[1], img.shape[0] + 14 * len(rows)), "white")
    draw = ImageDraw.Draw(canvas)
    for i, (r, name) in enumerate(zip(rows, names)):
        draw.text((4, i * (64 + 14)), name + "   " + " | ".join(CAPTIONS), fill="black")
        canvas.paste(Image.fromarray(r), (0, i * (64 + 14) + 14))
    canvas.resize((canvas.width * 2, canvas.height * 2), Image.NEAREST).save(out)
    print(out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
