"""A diagnostic of the judge's head, after its third fresh set was read (every set here is spent):
do its features point the same way on both priors' results?

    python scripts/judge_prior_split.py [--out docs/results/judge/third]

Over the three fresh sets' consensus results, for every feature of the shipped judge: how far the
raters' front_everywhere results sit from their blobs (the difference of means in pooled standard
deviations), on the empirical prior's block and on the learned prior's janus block apart
(``prior_split.csv``). Then the head refitted leave-kind-out over v3's and the three fresh sets'
consensus results with the fixtures, as shipped and with every feature also multiplied by an
*oracle* indicator of the empirical block (``prior_split_lko.csv``): how far a head that knew
which prior drew a result could go. The judge is never told the prior; the indicator is an upper
bound on what a reading of the result's style could give, not a judge.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch


def main(argv=None) -> int:
    from gdbench.assets.library import PARTS, has_front
    from gdbench.core.io import write_csv
    from gdbench.core.provenance import code_commit
    from gdbench.experiments.judge_build import sheet_features
    from gdbench.experiments.judge_fresh import block_and_arm
    from gdbench.metrics.judge.evaluate import agreement, judge_extra, leave_kind_out
    from gdbench.metrics.judge.judge import load_judge
    from gdbench.metrics.judge.sheets import labelled_results

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=Path("docs/results/judge/third"))
    args = ap.parse_args(argv)
    judge, commit = load_judge(), code_commit()
    results, _ = labelled_results(sets=("fresh", "fresh2", "fresh3"))
    block = [block_and_arm(r.run)[0] or "v3" for r in results]
    x = judge.head_rows(sheet_features(judge.eye, judge.curves, results, judge.templates), [r.caption for r in results])
    truth = [r.consensus for r in results]
    rows = []
    for k, name in enumerate(judge.feature_names()):
        row = {"feature": name}
        for b in ("empirical-janus", "learned-janus"):
            fe = x[[i for i in range(len(x)) if block[i] == b and truth[i] == "front_everywhere"], k]
            bl = x[[i for i in range(len(x)) if block[i] == b and truth[i] == "blob"], k]
            pooled = torch.cat([fe - fe.mean(), bl - bl.mean()]).std().clamp(min=1e-9)
            row[f"{b}: front_everywhere - blob (sd)"] = round(float((fe.mean() - bl.mean()) / pooled), 3)
        rows.append(row | {"judge": judge.version, "commit": commit})
    write_csv(rows, args.out / "prior_split.csv")
    kinds, fronts = [PARTS[r.caption][0] for r in results], [has_front(r.caption) for r in results]
    fx, fy = judge_extra(judge)
    emp = torch.tensor([float(b == "empirical-janus") for b in block])[:, None]
    lko_rows = []
    for variant in ("as shipped", "oracle empirical indicator"):
        xs, fxs = x, fx
        if variant != "as shipped":
            xs, fxs = torch.cat([x, x * emp, emp], 1), torch.cat([fx, torch.zeros_like(fx), torch.zeros(len(fx), 1)], 1)
        label = [lab for lab, _ in leave_kind_out(xs, results, kinds, fronts, (fxs, list(fy)))]
        for part in ("all", "v3", "learned-janus", "learned-uniform", "empirical-janus"):
            idx = [i for i in range(len(x)) if truth[i] and part in ("all", block[i])]
            a = agreement([truth[i] for i in idx], [label[i] for i in idx])
            lko_rows.append({"head": variant, "part": part, **{k: v for k, v in a.items() if k != "confusion"},
                             "judge": judge.version, "commit": commit})  # fmt: skip
            print(f"{variant:28s} {part:16s} n {a['n']:3d}: kappa {a['kappa_janus']:.2f} (Janus split), "
                  f"{a['kappa_four']:.2f} (four), recall blob {a['recall_blob']:.2f}")  # fmt: skip
    write_csv(lko_rows, args.out / "prior_split_lko.csv")
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
