"""An experiment for the judge's next reading (not part of the judge): a network-free reading by
templates. Each view, cropped as the eye crops it and blurred, is correlated in colour with the
asset's own renders at every azimuth bin (the eye's training crops near the sheets' elevation);
the softmax over bins is a second 'eye' whose turntable features join the twenty. Prints the
head's agreement leave-kind-out and in sample on v3's sheets and pooled with the fresh set's
(docs/judge_versions.md, "The next reading, explored", gives the numbers of 2026-12-05).

    python scripts/judge_template_reading.py [TEMPERATURE 0.05] [BLUR_PX 1.5] [L2]
    RELATIVE=1 python scripts/judge_template_reading.py 0.05 1.5 0.01      # + relative sameness
    RELATIVE=1 SHEETNET=/tmp/sheetnet_probs_3000_1.pt python scripts/judge_template_reading.py 0.05 1.5 0.01
"""

import os
import sys
import time
from pathlib import Path

import torch
import torch.nn.functional as F

from gdbench.assets.library import PARTS, has_front
from gdbench.experiments.judge_build import eye_crops, sheet_features
from gdbench.experiments.judge_fresh import arm_agreements, block_and_arm, fresh_results
from gdbench.metrics.judge.judge import load_judge
from gdbench.metrics.judge.net import BINS, crop_views
from gdbench.metrics.judge.reading import turntable_features
from gdbench.metrics.judge.sheets import SHEET_AZIMUTHS, v3_results

TEMP = float(sys.argv[1]) if len(sys.argv) > 1 else 0.05
BLUR = float(sys.argv[2]) if len(sys.argv) > 2 else 1.5
if len(sys.argv) > 3:  # the head's L2 penalty (default: head.L2)
    import functools

    from gdbench.metrics.judge import evaluate as _evaluate
    from gdbench.metrics.judge.head import fit as _fit

    _evaluate.fit = functools.partial(_fit, l2=float(sys.argv[3]))
t0 = time.time()
crops, data = eye_crops(256, 1, False)
print("crops", crops.shape, time.time() - t0)


def blur(x, s=BLUR):
    k = int(3 * s) * 2 + 1
    g = torch.exp(-((torch.arange(k) - k // 2) ** 2) / (2 * s * s))
    g = g / g.sum()
    x = F.conv2d(F.pad(x, (k // 2,) * 4, mode="replicate"), g.view(1, 1, 1, k).expand(3, 1, 1, k), groups=3)
    return F.conv2d(x, g.view(1, 1, k, 1).expand(3, 1, k, 1), groups=3)


def norm(x):
    x = x.flatten(1)
    x = x - x.mean(1, keepdim=True)
    return x / x.norm(dim=1, keepdim=True).clamp(min=1e-6)


near = (data.elevation - 15.0).abs() <= 15.0
refs = {}
for ci, cap in enumerate(data.captions):
    sel = (data.caption == ci) & near
    refs[cap] = (norm(blur(crops[sel])), data.azimuth[sel])
print("refs", time.time() - t0)


def template_reading(views, cap):
    r, az = refs[cap]
    v = norm(blur(crop_views(views)))
    sim = v @ r.T  # [V, R]
    b = ((az % 360) / (360 / BINS)).long() % BINS
    best = torch.full((v.shape[0], BINS), -1.0)
    best = best.scatter_reduce(1, b.expand(v.shape[0], -1), sim, reduce="amax")
    return torch.softmax(best / TEMP, 1)


judge = load_judge()
fresh = fresh_results(Path("."))
results = v3_results(Path(".")) + fresh
source = ["v3"] * (len(results) - len(fresh)) + [block_and_arm(r.run)[0] for r in fresh]
x0 = sheet_features(judge.eye, judge.curves, results)
az = torch.tensor(SHEET_AZIMUTHS)


def extra_features(views, cap):
    """Readings that go through no azimuth: how alike the views are (mean pairwise colour
    correlation), how alike their silhouettes are, and how much more the views match the asset's
    front (within 30 degrees) than its sides (60-120 degrees either way), in colour and in silhouette."""
    r, az = refs[cap]
    c = blur(crop_views(views))
    v = norm(c)
    m = norm((c.mean(1, keepdim=True) < 0.9).float().expand(-1, 3, -1, -1))
    n = v.shape[0]
    off = ~torch.eye(n, dtype=torch.bool)
    same = (v @ v.T)[off].mean()
    same_sil = (m @ m.T)[off].mean()
    a = (az % 360 + 180) % 360 - 180
    front, side = a.abs() <= 30, (a.abs() >= 60) & (a.abs() <= 120)
    sim = v @ r.T
    rs = sils[cap]
    ssim = m @ rs.T
    out = [same, same_sil, (sim[:, front].amax(1) - sim[:, side].amax(1)).mean(),
           (ssim[:, front].amax(1) - ssim[:, side].amax(1)).mean()]  # fmt: skip
    if os.environ.get("RELATIVE"):  # the asset's own sameness at the sheet's azimuths subtracted
        pick = torch.stack([((a - t + 180) % 360 - 180).abs().argmin() for t in (0, 60, 120, 180, -120, -60)])
        ra, rsa = r[pick], rs[pick]
        own = (ra @ ra.T)[off].mean()
        own_sil = (rsa @ rsa.T)[off].mean()
        out += [same - own, same_sil - own_sil]
    if os.environ.get("OUTLINE"):  # the outline's fit at 48 px: each view's best IoU with the asset's
        vm = (crop_views(views, 48).min(1).values < 0.9).float().flatten(1)
        rm = outlines[cap]
        inter = vm @ rm.T
        iou = inter / (vm.sum(1, keepdim=True) + rm.sum(1)[None] - inter).clamp(min=1)
        best = iou.amax(1)
        out += [best.mean(), best.amin()]
    if os.environ.get("DETAIL"):  # the features drawn: the best template's match less its smeared twin's
        best = sim.argmax(1)
        gain = sim.gather(1, best[:, None])[:, 0] - (v * smeared[cap][best]).sum(1)
        out += [gain.amax(), gain.mean()]
    return torch.stack(out)


smeared = {}
for ci, cap in enumerate(data.captions):
    sel = (data.caption == ci) & near
    c = crops[sel]
    ink = ((1 - c.min(1, keepdim=True).values) > 0.1).float()
    mean = (c * ink).sum((2, 3), keepdim=True) / ink.sum((2, 3), keepdim=True).clamp(min=1)
    smeared[cap] = norm(blur(c + ink * (mean - c)))
outlines = {}
if os.environ.get("OUTLINE"):
    for ci, cap in enumerate(data.captions):
        sel = ((data.caption == ci) & near).nonzero().flatten()
        outlines[cap] = (crop_views(data.images[sel], 48).min(1).values < 0.9).float().flatten(1)
sils = {}
for ci, cap in enumerate(data.captions):
    sel = (data.caption == ci) & near
    sils[cap] = norm((blur(crops[sel]).mean(1, keepdim=True) < 0.9).float().expand(-1, 3, -1, -1))

xt = torch.stack([turntable_features(template_reading(torch.from_numpy(r.views), r.caption), az) for r in results])
print("features", time.time() - t0)
kinds = [PARTS[r.caption][0] for r in results]
fronts = [has_front(r.caption) for r in results]
nv3 = len(results) - len(fresh)
xe = torch.stack([extra_features(torch.from_numpy(r.views), r.caption) for r in results])
if os.environ.get("SYNTH"):  # each feature against the asset's own synthetic results of each class
    from dataclasses import replace

    from gdbench.metrics.judge.reading import result_features
    from gdbench.metrics.judge.train import EyeTrainConfig, degrade

    g = torch.Generator().manual_seed(0)
    cam = torch.arange(6) * 60.0
    base = EyeTrainConfig(smear=0.0)

    def synth_views(ci, kind):
        sel = ((data.caption == ci) & (data.variant == 0) & near).nonzero().flatten()
        off = float(torch.rand((), generator=g)) * 360
        front = torch.where(torch.rand(6, generator=g) < 0.25, 180.0, 0.0)
        t = {"fine": off + cam, "profile": off + cam, "front": front, "shapeless": torch.rand(6, generator=g) * 360}
        t = t[kind] + torch.randn(6, generator=g) * 8
        d = ((data.azimuth[sel][None] - t[:, None] + 180) % 360 - 180).abs()
        x = crops[sel[d.argmin(1)]]
        cfg = replace(base, blobify=1.0, blob_blur=3.0) if kind == "shapeless" else replace(base, blobify=0.4)
        x = degrade(x, cfg, g)
        ink = ((1 - x.min(1, keepdim=True).values) > 0.1).float()
        mean = (x * ink).sum((2, 3), keepdim=True) / ink.sum((2, 3), keepdim=True).clamp(min=1)
        sm = {"fine": 0.3, "profile": 1.0, "front": float(torch.rand((), generator=g)), "shapeless": 1.0}[kind]
        return (x + ink * sm * (mean - x)).permute(0, 2, 3, 1).contiguous()

    KINDS = ("fine", "profile", "front", "shapeless")
    feats = {}
    for ci, cap in enumerate(data.captions):
        for kind in KINDS:
            fs = []
            for _ in range(int(os.environ.get("SYNTH_N", "6"))):
                v = synth_views(ci, kind)
                f0 = result_features(judge.eye, judge.curves, v, az, cap)[0]
                fs.append(torch.cat([f0, extra_features(v, cap)]))
            feats[(cap, kind)] = torch.stack(fs)
    sd = torch.stack([f - f.mean(0) for f in feats.values()]).flatten(0, 1).std(0).clamp(min=1e-3)
    xr = torch.cat([x0, xe], 1)
    xs = torch.stack([
        torch.stack([(((xr[i] - feats[(r.caption, k)].mean(0)) / sd) ** 2).mean().log() for k in KINDS])
        for i, r in enumerate(results)
    ])  # fmt: skip
    print("synth", time.time() - t0)
ARMS = {
    "eye only": x0,
    "template only": torch.cat([xt, x0[:, 10:]], 1),
    "eye + template": torch.cat([x0, xt], 1),
    "eye + sameness": torch.cat([x0, xe], 1),
    "eye + template + sameness": torch.cat([x0, xt, xe], 1),
}
if os.environ.get("SYNTH"):
    ARMS["eye + sameness + synth"] = torch.cat([x0, xe, xs], 1)
if os.environ.get("RELATIVE"):  # the twenty features less the asset's own (its clean six views)
    from gdbench.metrics.judge.reading import result_features

    xa = {}
    for ci, cap in enumerate(data.captions):
        sel = ((data.caption == ci) & (data.variant == 0)).nonzero().flatten()
        d = ((data.azimuth[sel][None] - az[:, None] + 180) % 360 - 180).abs() + (data.elevation[sel][None] - 15).abs()
        xa[cap] = result_features(judge.eye, judge.curves, data.images[sel[d.argmin(1)]], az, cap)[0]
    xrel = x0 - torch.stack([xa[r.caption] for r in results])
    ARMS["eye + rel + sameness"] = torch.cat([x0, xrel, xe], 1)
    ARMS["rel + sameness"] = torch.cat([xrel[:, :0], x0[:, :0], xrel, xe], 1)
if os.environ.get("SHEETNET"):  # a sheet network's probabilities (scripts/judge_sheet_net.py)
    saved = torch.load(os.environ["SHEETNET"])
    assert saved["run_ids"] == [r.run_id for r in results]
    lp = saved["probs"].clamp(min=1e-4).log()
    ARMS = {k: v for k, v in ARMS.items() if "rel" in k} | {
        "eye + sameness": ARMS["eye + sameness"],
        "eye + net": torch.cat([x0, lp], 1),
        "eye + sameness + net": torch.cat([x0, xe, lp], 1),
    }
for name, x in ARMS.items():
    for scope, part, a, b in arm_agreements(x, results, kinds, fronts, source, nv3):
        if os.environ.get("CONFUSION") and part == "all":
            print(a["confusion"])
        print(
            f"{name:26s} {scope:6s} {part:16s} n {a['n']:3d} LKO kJ {a['kappa_janus']:.2f} "
            f"k4 {a['kappa_four']:.2f} rec fe {a['recall_front_everywhere']} blob {a['recall_blob']} "
            f"fine {a['recall_fine']} | in-sample kJ {b['kappa_janus']:.2f}"
        )
