"""Why the judge's head is trees: the kinds of head on the labelled sets spent before the shipped
judge (v3's sheets and the fresh sets in ``judge_build.SPENT``), held out two ways.

    python scripts/judge_leave_set_out.py --out docs/results/judge/seventh [--judge DIR] [--heads trees:50 trees:200]

- **leave-set-out** (``leave_set_out.csv``): each fresh set in turn is judged by a head fitted on
  v3's and the other sets' consensus results and the fixtures: what a fresh set measures (new
  results of the same prompts, from a seed no head saw);
- **leave-kind-out pooled** (``leave_kind_out_pooled.csv``): every kind held out in turn over v3
  and all the spent sets: what a kind the head never saw gets.

The heads (``HEADS``) read the judge's features (``--judge``, default the shipped one): the
regression the first 30 of them (eye, outline, sameness: the third judge's head), the trees all 50
(the look too): one forest (the fourth judge's head), five averaged with the blob offset (the
fifth's and sixth's, ``trees.fit_trees``) and a random forest (``bagging.fit_bagged``); and the
five forests over the 50 and the 50 less the asset's reference fixtures' (200, the seventh judge's
head, ``reference.against``; the references the judge's own, or read from its fixtures where it
has none). Six views each, from the committed sheets; the eye as shipped.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch

HEADS = (("linear", 30), ("one forest", 50), ("trees", 50), ("bagged", 50), ("trees", 200))
"""(head, how many of the judge's features it reads; 200: the 50 against the references):
``head.fit_head``'s kinds, and the fourth judge's one forest."""


def fit(x, labels: list[str], kind: str):
    from gdbench.metrics.judge.head import class_weights, fit_head
    from gdbench.metrics.judge.trees import fit_forest

    if kind == "one forest":
        y, w = class_weights(labels)
        return fit_forest(x, y, w)
    return fit_head(x, labels, kind)


def main(argv=None) -> int:
    from gdbench.assets.library import PARTS, has_front
    from gdbench.core.io import write_csv
    from gdbench.core.provenance import code_commit
    from gdbench.experiments.judge_build import SPENT as SETS
    from gdbench.experiments.judge_build import sheet_features
    from gdbench.experiments.judge_fresh import block_and_arm
    from gdbench.metrics.judge.evaluate import agreement, leave_kind_out
    from gdbench.metrics.judge.head import decide
    from gdbench.metrics.judge.judge import load_judge
    from gdbench.metrics.judge.reference import against, reference_rows
    from gdbench.metrics.judge.sheets import labelled_results

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--judge", type=Path, default=None, help="a judge folder (default: the shipped judge)")
    names = [f"{k}:{n}" for k, n in HEADS]
    ap.add_argument("--heads", nargs="+", choices=names, default=names, metavar="HEAD:N",
                    help=f"the heads to compare (default: all of {' '.join(names)})")  # fmt: skip
    ap.add_argument("--out", type=Path, required=True,
                    help="where the two tables go (each judge keeps its own: fourth to seventh)")  # fmt: skip
    args = ap.parse_args(argv)
    judge, commit = load_judge(str(args.judge) if args.judge else None), code_commit()
    if judge.templates is None or judge.head_info.get("fixture_rows") is None:
        ap.error("--judge: expected a judge with templates and fixture rows (the fourth to the seventh)")
    results, source = labelled_results(sets=SETS)
    block = [block_and_arm(r.run)[0] or "v3" for r in results]
    x50 = sheet_features(judge.eye, judge.curves, results, judge.templates)[:, :50]  # the 50 its fixtures hold
    rows = judge.head_info["fixture_rows"]
    fx50, fy = torch.tensor(rows["features"], dtype=torch.float32), list(rows["labels"])
    known = dict(zip(rows["names"], fx50))
    refs = judge.references or reference_rows(judge.eye, judge.curves, judge.templates, sorted(judge.curves), known)
    x = against(x50, [r.caption for r in results], refs)  # the 50, then the 50 less each reference's
    fx = against(fx50, [n.rsplit("/", 1)[0] for n in rows["names"]], refs)
    truth = [r.consensus for r in results]
    fronts, kinds = [has_front(r.caption) for r in results], [PARTS[r.caption][0] for r in results]
    lso, lko, heads = [], [], [h for h in HEADS if f"{h[0]}:{h[1]}" in args.heads]
    for kind, n in heads:  # every head's leave-set-out first, written before the slower leave-kind-out
        label: list[str | None] = [None] * len(results)
        for held in SETS:
            fit_on = [i for i in range(len(results)) if source[i] != held and truth[i]]
            head = fit(torch.cat([x[fit_on, :n], fx[:, :n]]), [truth[i] for i in fit_on] + list(fy), kind)
            mine = [i for i in range(len(results)) if source[i] == held]
            p = head.probabilities(x[mine, :n])
            for j, i in enumerate(mine):
                label[i] = decide(p[j], x[i], fronts[i])[0]
        for held in SETS:
            idx = [i for i in range(len(results)) if source[i] == held and truth[i]]
            a = agreement([truth[i] for i in idx], [label[i] for i in idx])
            lso.append(row(kind, n, held, a, judge.version, commit))
            print(f"{kind:10s} {n:3d} leave-set-out {held:6s} n {a['n']:3d}: kappa {a['kappa_janus']:.2f} (Janus), "
                  f"{a['kappa_four']:.2f} (four), recall fe {a['recall_front_everywhere']:.2f} "
                  f"blob {a['recall_blob']:.2f} fine {a['recall_fine']:.2f}", flush=True)  # fmt: skip
    write_csv(lso, args.out / "leave_set_out.csv")
    for kind, n in heads:
        if kind == "one forest":  # its leave-kind-out: the fourth judge's own table, docs/results/judge/fourth
            continue
        pooled = leave_kind_out(x[:, :n], results, kinds, fronts, (fx[:, :n], list(fy)), kind)
        for part in ("all", "v3", "learned-janus", "learned-uniform", "empirical-janus"):
            idx = [i for i in range(len(results)) if truth[i] and part in ("all", block[i])]
            a = agreement([truth[i] for i in idx], [pooled[i][0] for i in idx])
            lko.append(row(kind, n, part, a, judge.version, commit))
            print(f"{kind:10s} {n:3d} leave-kind-out pooled {part:16s} n {a['n']:3d}: kappa {a['kappa_janus']:.2f} "
                  f"(Janus split), {a['kappa_four']:.2f} (four), blob {a['recall_blob']:.2f}", flush=True)  # fmt: skip
    write_csv(lko, args.out / "leave_kind_out_pooled.csv")
    print(f"-> {args.out}")
    return 0


def row(kind: str, n: int, part: str, a: dict, version: str, commit: str) -> dict:
    return {"head": kind, "features": n, "part": part, **{k: v for k, v in a.items() if k != "confusion"},
            "confusion": str(a["confusion"]), "judge": version, "commit": commit}  # fmt: skip


if __name__ == "__main__":
    raise SystemExit(main())
