"""How the eighth judge's head was chosen: the regression, the boosted trees and their blends over
the seventh's 50 numbers and the 57 with the front reading (``marking.FRONT``), each read two ways
on the spent labelled sheets (six views each, the shipped judge's eye and templates):

- **v3 leave-kind-out** (the issue's bar, as ``judge_build evaluate`` reads it): every kind held out
  in turn, the head fitted on v3's other kinds' consensus results;
- **leave-set-out**: each spent fresh set judged by a head fitted on v3's and the other sets'
  consensus results (what a fresh set measures: new results of kinds the labels taught).

A blend averages the regression's and the trees' probabilities (``trees_share`` the trees'); fine's
probability is then weighed by ``fine_odds`` and normalised (``blend.Blend``: the shipped head is
the regression and the trees at equal shares, odds ``blend.FINE_ODDS``). Each row gives the
agreement with the consensus, the share of consensus-fine results warned and the bars that fail
(``evaluate.THRESHOLDS``; at most 1 in 10 warned).

    python scripts/judge_front_study.py --out docs/results/judge/eighth [--judge DIR]

Writes ``front_study.csv``. The trees take most of the time (five forests a fold, 28 folds for
each set of numbers: about 15 minutes on two idle cores).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

SHARES = (0.0, 0.25, 0.5, 1.0)
"""The trees' shares of a blend read (0: the regression alone; 1: the trees alone)."""
ODDS = (1.0, 1.5, 2.0)
"""The fine odds read."""
NUMBERS = {"the 50 (the seventh's)": 50, "the 57 (with the front reading)": 57}


def main(argv=None) -> int:
    from gdbench.assets.library import PARTS, has_front
    from gdbench.core.io import write_csv
    from gdbench.core.provenance import code_commit
    from gdbench.experiments.judge_build import SPENT, sheet_features
    from gdbench.experiments.judge_fresh import FINE_WARNED_MAX
    from gdbench.metrics.judge.evaluate import agreement, passes
    from gdbench.metrics.judge.head import decide, fit_head
    from gdbench.metrics.judge.judge import load_judge
    from gdbench.metrics.judge.sheets import labelled_results

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--judge", type=Path, default=None, help="a judge folder (default: the shipped judge)")
    ap.add_argument("--out", type=Path, required=True, help="where front_study.csv goes")
    args = ap.parse_args(argv)
    judge, commit = load_judge(str(args.judge) if args.judge else None), code_commit()
    results, source = labelled_results(sets=SPENT)
    x = sheet_features(judge.eye, judge.curves, results, judge.templates)
    if x.shape[1] < max(NUMBERS.values()):
        ap.error(f"--judge: its readings give {x.shape[1]} numbers, the study reads {max(NUMBERS.values())}")
    truth = [r.consensus for r in results]
    kinds = [PARTS[r.caption][0] for r in results]
    fronts = [has_front(r.caption) for r in results]
    v3 = [i for i in range(len(results)) if source[i] == "v3"]
    fresh = [i for i in range(len(results)) if source[i] != "v3"]
    folds = {
        "v3 leave-kind-out": [([i for i in v3 if kinds[i] != k], [i for i in v3 if kinds[i] == k])
                              for k in sorted({kinds[i] for i in v3})],
        "leave-set-out": [([i for i in range(len(results)) if source[i] != s], [i for i in fresh if source[i] == s])
                          for s in SPENT],
    }  # fmt: skip
    out = []
    for numbers, n in NUMBERS.items():
        xn = x[:, :n]
        for read, parts in folds.items():
            p = {kind: torch.zeros(len(results), 3, dtype=torch.float64) for kind in ("linear", "trees")}
            for fit_on, mine in parts:
                fit_on = [i for i in fit_on if truth[i]]
                for kind in p:
                    head = fit_head(xn[fit_on], [truth[i] for i in fit_on], kind)
                    p[kind][mine] = head.probabilities(xn[mine]).double()
            idx = [i for _, mine in parts for i in mine if truth[i]]
            for share in SHARES:
                for odds in ODDS:
                    q = (1 - share) * p["linear"] + share * p["trees"]
                    q = q * torch.tensor([1.0, 1.0, odds], dtype=q.dtype)
                    q = (q / q.sum(1, keepdim=True)).float()
                    label = {i: decide(q[i], xn[i], fronts[i])[0] for i in idx}
                    a = agreement([truth[i] for i in idx], [label[i] for i in idx])
                    fine = [i for i in idx if truth[i] == "fine"]
                    warned = sum(label[i] != "fine" for i in fine) / len(fine)
                    ok = passes(a) | {"fine_warned": warned <= FINE_WARNED_MAX}
                    out.append({"numbers": numbers, "read": read, "trees_share": share, "fine_odds": odds,
                                **{k: v for k, v in a.items() if k != "confusion"}, "fine_warned": warned,
                                "fails": ";".join(k for k, v in ok.items() if not v),
                                "judge": judge.version, "commit": commit})  # fmt: skip
                    print(f"{numbers:32s} {read:18s} trees {share:4.2f} odds {odds:3.1f}: kappa {a['kappa_janus']:.3f} "
                          f"(Janus) {a['kappa_four']:.3f} (four) blob {a['recall_blob']:.2f} warned {warned:.3f} "
                          f"fails: {out[-1]['fails'] or 'none'}", flush=True)  # fmt: skip
    write_csv(out, args.out / "front_study.csv")
    print(f"-> {args.out / 'front_study.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
