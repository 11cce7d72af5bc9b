"""An experiment for the judge's next reading (not part of the judge): a sheet network trained on
synthetic sheets made from the assets' own renders, no label of any result. Each synthetic sheet
is six degraded views at the sheet's camera azimuths beside the asset's clean views at 12 azimuths
(what a rater sees: the asset's row above the result's); its class follows the labelling rule:
fine (the asset turned by any angle, features kept), front_everywhere (the front or the back from
every camera, features drawn or smeared away), second_face (a front where the back belongs), blob
(a profile with its features smeared away, or a shapeless splat). Prints the network's own
agreement with v3's and the fresh set's consensus, and the head's leave-kind-out with its three
probabilities beside the twenty features.

    python scripts/judge_sheet_net.py [STEPS 1500] [SEED 0]   # 3000 1: 20 min beside other work

Writes the network's probabilities for every sheet result to /tmp/sheetnet_probs_STEPS_SEED.pt
(``judge_template_reading.py`` reads them with SHEETNET=that file).
"""

import sys
import time
from dataclasses import replace
from pathlib import Path

import torch
import torch.nn.functional as F
from torch import nn

from gdbench.assets.library import PARTS, has_front
from gdbench.experiments.judge_build import eye_crops, sheet_features
from gdbench.experiments.judge_fresh import arm_agreements, block_and_arm, fresh_results
from gdbench.metrics.judge.evaluate import agreement
from gdbench.metrics.judge.judge import load_judge
from gdbench.metrics.judge.net import crop_views
from gdbench.metrics.judge.sheets import v3_results
from gdbench.metrics.judge.train import EyeTrainConfig, degrade

STEPS = int(sys.argv[1]) if len(sys.argv) > 1 else 1500
SEED = int(sys.argv[2]) if len(sys.argv) > 2 else 0
REF = torch.arange(12) * 30.0
CAM = torch.arange(6) * 60.0
t0 = time.time()
torch.manual_seed(SEED)
crops, data = eye_crops(256, 1, False)
near = (data.elevation - 15.0).abs() <= 15.0
pools = {}
for ci in range(len(data.captions)):
    for vi in data.variant[data.caption == ci].unique().tolist():
        sel = (near & (data.caption == ci) & (data.variant == vi)).nonzero().flatten()
        pools[(ci, vi)] = sel
keys = list(pools)


def pick(pool, targets, g, spread=6.0, elev=None):
    az = data.azimuth[pool]
    d = ((az[None] - targets[:, None] + 180) % 360 - 180).abs() + torch.rand(
        len(targets), len(pool), generator=g
    ) * spread
    if elev is not None:
        d = d + (data.elevation[pool][None] - elev).abs()
    return pool[d.argmin(1)]


def refs_of(ci, vi=0):
    pool = pools.get((ci, vi)) if (ci, vi) in pools else pools[next(k for k in keys if k[0] == ci)]
    return crops[pick(pool, REF, torch.Generator().manual_seed(0), 0.0, 15.0)]


REFS = torch.stack([refs_of(ci) for ci in range(len(data.captions))])  # [C, 12, 3, S, S]
BASE = EyeTrainConfig(smear=0.0)


def smear(x, s):
    ink = ((1 - x.min(1, keepdim=True).values) > 0.1).float()
    mean = (x * ink).sum((2, 3), keepdim=True) / ink.sum((2, 3), keepdim=True).clamp(min=1)
    return x + ink * s[:, None, None, None] * (mean - x)


def synth(n, g):
    """n synthetic sheets: (views [n, 6, 3, S, S], refs [n, 12, 3, S, S], class [n]: 0 janus, 1 blob, 2 fine)."""
    u = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    views, refs, cls, side = [], [], [], []
    for _ in range(n):
        ci, vi = keys[int(torch.randint(len(keys), (1,), generator=g))]
        pool = pools[(ci, vi)]
        front = has_front(data.captions[ci])
        r = u(())
        offset = u(()) * 360 if u(()) < 0.5 else torch.randn((), generator=g) * 15
        jitter = torch.randn(6, generator=g) * 8
        if not front:
            kind = "fine" if r < 0.5 else "shapeless"
        else:
            kind = (
                "fine"
                if r < 0.35
                else "profile"
                if r < 0.5
                else "shapeless"
                if r < 0.62
                else "front"
                if r < 0.94
                else "second"
            )
        if kind in ("fine", "profile"):
            t = offset + CAM + jitter
        elif kind == "shapeless":
            t = u(6) * 360
        elif kind == "front":
            t = torch.where(u(6) < 0.25, 180.0, 0.0) + torch.randn(6, generator=g) * 20
        else:  # second: a front at the back as well
            t = CAM + jitter
            t[3] = torch.randn((), generator=g) * 15
            if u(()) < 0.5:
                t[2 if u(()) < 0.5 else 4] = t[3] + 60 * (1 if u(()) < 0.5 else -1)
        idx = pick(pool, t % 360, g)
        x = crops[idx]
        cfg = replace(BASE, blobify=1.0, blob_blur=3.0) if kind == "shapeless" else replace(BASE, blobify=0.4)
        x = degrade(x, cfg, g)
        s = {
            "fine": 0.5 * u(6),
            "profile": 0.85 + 0.15 * u(6),
            "shapeless": 0.8 + 0.2 * u(6),
            "front": u(()).expand(6).clone(),
            "second": 0.4 * u(6),
        }[kind]
        x = smear(x, s)
        if kind == "front" and u(()) < 0.5:
            x = x.flip(-1)
        views.append(x)
        refs.append(REFS[ci])
        side.append(
            torch.full((6,), -100, dtype=torch.long)
            if kind == "shapeless"
            else (torch.round((t % 360) / 30).long() % 12)
        )
        cls.append({"fine": 2, "profile": 1, "shapeless": 1, "front": 0, "second": 0}[kind])
    return torch.stack(views), torch.stack(refs), torch.tensor(cls), torch.stack(side)


class SheetNet(nn.Module):
    def __init__(self, widths=(16, 32, 64, 64), dim=96):
        super().__init__()
        layers, c = [], 3
        for w in widths:
            layers += [
                nn.Conv2d(c, w, 3, padding=1),
                nn.GroupNorm(8, w),
                nn.SiLU(),
                nn.Conv2d(w, w, 3, stride=2, padding=1),
                nn.GroupNorm(8, w),
                nn.SiLU(),
            ]
            c = w
        self.enc = nn.Sequential(*layers, nn.Flatten(), nn.Linear(c * 4, dim))
        self.scale = nn.Parameter(torch.tensor(5.0))
        self.mlp = nn.Sequential(nn.Linear(18, 64), nn.SiLU(), nn.Linear(64, 3))

    def forward(self, views, refs):
        b = len(views)
        ev = F.normalize(self.enc(1 - views.flatten(0, 1)), dim=-1).view(b, 6, -1)
        er = F.normalize(self.enc(1 - refs.flatten(0, 1)), dim=-1).view(b, 12, -1)
        s = torch.einsum("bvd,brd->bvr", ev, er) * self.scale  # [b, 6, 12]
        k = torch.arange(6)
        cyc = torch.stack([s[:, k, (2 * k + sh) % 12].mean(1) for sh in range(12)], 1)  # one turn at each offset
        cyc_sorted = cyc.sort(1, descending=True).values[:, :6]
        frontish = torch.stack(
            [s[:, :, 0].mean(1), s[:, :, 6].mean(1), torch.maximum(s[:, :, 0], s[:, :, 6]).mean(1), s.amax(2).mean(1)],
            1,
        )
        same = torch.einsum("bvd,bwd->bvw", ev, ev)
        off = ~torch.eye(6, dtype=torch.bool)
        sameness = same[:, off].mean(1, keepdim=True) * self.scale
        feats = torch.cat([cyc_sorted, s.amax(2), frontish, sameness, cyc.amax(1, keepdim=True) - frontish[:, 2:3]], 1)
        return self.mlp(feats), s


net = SheetNet()
opt = torch.optim.AdamW(net.parameters(), lr=2e-3, weight_decay=1e-4)
g = torch.Generator().manual_seed(SEED + 1)
acc = 0.0
for step in range(STEPS):
    for grp in opt.param_groups:
        grp["lr"] = 2e-3 * 0.5 * (1 + torch.cos(torch.tensor(torch.pi * step / STEPS)).item())
    v, r, c, sd = synth(32, g)
    logits, sim = net(v, r)
    loss = F.cross_entropy(logits, c) + F.cross_entropy(sim.flatten(0, 1), sd.flatten(), ignore_index=-100)
    opt.zero_grad()
    loss.backward()
    opt.step()
    acc += loss.item()
    if (step + 1) % 100 == 0:
        print(f"step {step + 1} loss {acc / 100:.3f} {time.time() - t0:.0f}s", flush=True)
        acc = 0.0
net.eval()
torch.save(net.state_dict(), f"/tmp/sheetnet_{STEPS}_{SEED}.pt")

judge = load_judge()
fresh = fresh_results(Path("."))
results = v3_results(Path(".")) + fresh
source = ["v3"] * (len(results) - len(fresh)) + [block_and_arm(r.run)[0] for r in fresh]
cap_index = {c: i for i, c in enumerate(data.captions)}
with torch.no_grad():
    probs = torch.stack(
        [
            torch.softmax(net(crop_views(torch.from_numpy(r.views))[None], REFS[cap_index[r.caption]][None])[0][0], 0)
            for r in results
        ]
    )
torch.save({"probs": probs, "run_ids": [r.run_id for r in results]}, f"/tmp/sheetnet_probs_{STEPS}_{SEED}.pt")
NAMES = ("front_everywhere", "blob", "fine")
fronts = [has_front(r.caption) for r in results]
own = [NAMES[int(p.argmax())] if f or int(p.argmax()) != 0 else "blob" for p, f in zip(probs, fronts)]
nv3 = len(results) - len(fresh)
for part in ("v3", "fresh", "empirical-janus", "learned-janus", "learned-uniform"):
    idx = [i for i, r in enumerate(results) if r.consensus and (source[i] == part or (part == "fresh" and i >= nv3))]
    a = agreement([results[i].consensus for i in idx], [own[i] for i in idx])
    print(
        f"net alone {part:16s} n {a['n']:3d} kJ {a['kappa_janus']:.2f} k4 {a['kappa_four']:.2f} rec fe "
        f"{a['recall_front_everywhere']} blob {a['recall_blob']} fine {a['recall_fine']}"
    )
x0 = sheet_features(judge.eye, judge.curves, results)
kinds = [PARTS[r.caption][0] for r in results]
lp = probs.clamp(min=1e-4).log()
for name, x in {"eye": x0, "eye + net": torch.cat([x0, lp], 1)}.items():
    for scope, part, a, b in arm_agreements(x, results, kinds, fronts, source, nv3):
        print(
            f"{name:10s} {scope:6s} {part:16s} n {a['n']:3d} kJ {a['kappa_janus']:.2f} k4 {a['kappa_four']:.2f} "
            f"rec fe {a['recall_front_everywhere']} blob {a['recall_blob']} fine {a['recall_fine']} | "
            f"in-sample kJ {b['kappa_janus']:.2f}"
        )
print("done", time.time() - t0)
