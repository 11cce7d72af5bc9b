"""The Janus judge on a fresh set (docs/judge_fresh.md, docs/judge_fresh2.md): results no rule or
head was fitted on, labelled blind by two passes of raters before the judge read them, read in both
of the judge's modes against the registered thresholds.

    python -m gdbench.experiments.judge_fresh [--set fresh2] [--runs OUT] [--out DIR]

- **six views**: each result's row of the committed sheets (``Judge.views`` at azimuths 0, 60,
  ..., 300), so this mode recomputes from the repository alone;
- **run folder**: each run's scene on the turntable's 36 frames (``Judge.run``, what ``gdbench
  judge OUT`` reads), where the sweep's folders are at hand (``--runs``: the key names each run's
  folder under the sweep folder it was drawn from); without them the committed ``judged.csv``
  keeps this mode's labels and ``agreement.csv`` is recomputed from it.

Writes ``judged.csv`` (a row per result: block, arm, both modes' labels and confidences, both
passes' labels, the consensus), ``agreement.csv`` (a row per mode, truth and block: kappas,
recalls, counts, the share of consensus-fine results warned, which thresholds pass) and prints the
summary. The block and arm come from the key's run folder, read after judging.
"""

from __future__ import annotations

import csv
from pathlib import Path

from gdbench.metrics.judge.sheets import FRESH_SETS, fresh_results

LABELS = FRESH_SETS["fresh"].labels
"""The first fresh set's two passes' label files."""
BLOCKS = ("learned-janus", "learned-uniform", "empirical-janus")
MODES = ("six views", "run folder")
FINE_WARNED_MAX = 0.1
"""At most this share of the consensus-fine results may get a failure warning (a label but fine)."""


def block_and_arm(run: str) -> tuple[str, str]:
    """(block, preset) of a run folder the key names: ``<OUT>/<block>/cells/<setting>/<prompt>/<preset>/seed<k>``."""
    parts = Path(run).parts
    block = next((b for b in BLOCKS if b in parts), "")
    return block, parts[-2]


def judge_fresh(root: Path = Path("."), runs: Path | None = None, which: str = "fresh",
                judge_dir: Path | None = None) -> list[dict]:  # fmt: skip
    """Every result of the fresh set ``which`` (``sheets.FRESH_SETS``) judged by the judge in
    ``judge_dir`` (default: the shipped one) in the six-view mode, and in the run-folder mode where
    ``runs`` (the sweep folder the sheets were drawn from) holds the runs; a row per result."""
    from gdbench.core.provenance import code_commit
    from gdbench.metrics.judge.judge import load_judge
    from gdbench.metrics.judge.sheets import SHEET_AZIMUTHS

    judge, commit = load_judge(str(judge_dir) if judge_dir else None), code_commit()
    rows = []
    for r in fresh_results(root, which):
        six = judge.views(r.views, SHEET_AZIMUTHS, r.caption)
        block, arm = block_and_arm(r.run)
        rel, folder = Path(r.run).parts, None
        if runs is not None and block in rel:
            folder = Path(runs).joinpath(*rel[rel.index(block) :])
        whole = judge.run(folder) if folder is not None and (folder / "scene.ply").is_file() else None
        rows.append({
            "number": r.number, "run_id": r.run_id, "caption": r.caption, "block": block, "preset": arm,
            "six_views": six["label"], "six_views_confidence": six["confidence"],
            "run_folder": whole["label"] if whole else "",
            "run_folder_confidence": whole["confidence"] if whole else "",
            "rater1": r.labels.get("rater1", ""), "rater2": r.labels.get("rater2", ""),
            "consensus": r.consensus or "", "judge": judge.version, "commit": commit,
        })  # fmt: skip
    return rows


def agreement_rows(judged: list[dict], blocks: tuple[str, ...] = BLOCKS) -> list[dict]:
    """Per mode, truth (the consensus, each pass) and block (all, then each of ``blocks``): the
    judge's agreement (``evaluate.agreement``), the thresholds it passes, and the share of
    consensus-fine results it warns on; then the two passes against each other."""
    from gdbench.metrics.judge.evaluate import agreement, passes

    rows = []
    commit = judged[0]["commit"] if judged else ""
    version = judged[0]["judge"] if judged else ""
    for mode in MODES:
        col = mode.replace(" ", "_")
        for truth in ("consensus", "rater1", "rater2"):
            for block in ("all", *blocks):
                sel = [r for r in judged if r[truth] and r[col] and block in ("all", r["block"])]
                if not sel:
                    continue
                a = agreement([r[truth] for r in sel], [r[col] for r in sel])
                fine = [r for r in sel if r[truth] == "fine"]
                warned = sum(r[col] != "fine" for r in fine) / len(fine) if fine else None
                ok = passes(a) | {"fine_warned": warned is not None and warned <= FINE_WARNED_MAX}
                rows.append({"mode": mode, "truth": truth, "block": block,
                             **{k: v for k, v in a.items() if k != "confusion"}, "fine_warned": warned,
                             "second_face_judged": sum(r[col] == "second_face" for r in sel),
                             "passes": ";".join(k for k, v in ok.items() if v),
                             "fails": ";".join(k for k, v in ok.items() if not v),
                             "confusion": str(a["confusion"]), "judge": version, "commit": commit})  # fmt: skip
    both = [r for r in judged if r["rater1"] and r["rater2"]]
    a = agreement([r["rater1"] for r in both], [r["rater2"] for r in both])
    rows.append({"mode": "rater2 against rater1", "truth": "rater1", "block": "all",
                 **{k: v for k, v in a.items() if k != "confusion"}, "confusion": str(a["confusion"]),
                 "judge": version, "commit": commit})  # fmt: skip
    return rows


def pooled(root: Path = Path("."), which: str = "fresh", judge_dir: Path | None = None,
           head: str | None = None) -> list[dict]:  # fmt: skip
    """After the fresh set was read (it is spent as a test): would more labelled results, the fresh
    set's pooled with v3's, let the head meet the bar? The head refitted leave-kind-out and in sample
    over the union (six views; the eye as shipped), a row per fit and source (v3, each fresh block).
    A diagnostic of the head's data against its features, not a test of a judge. ``judge_dir``: the
    judge whose eye and features are read (default: the shipped one); ``head``: the kind of head
    refitted (``head.HEADS``; default: the judge's own)."""
    from gdbench.assets.library import PARTS, has_front
    from gdbench.core.provenance import code_commit
    from gdbench.experiments.judge_build import sheet_features
    from gdbench.metrics.judge.evaluate import agreement, in_sample, judge_extra, leave_kind_out
    from gdbench.metrics.judge.head import head_kind
    from gdbench.metrics.judge.judge import load_judge
    from gdbench.metrics.judge.sheets import v3_results

    judge = load_judge(str(judge_dir) if judge_dir else None)
    fresh = fresh_results(root, which)
    results = v3_results(root) + fresh
    source = ["v3"] * (len(results) - len(fresh)) + [block_and_arm(r.run)[0] for r in fresh]
    x = judge.head_rows(sheet_features(judge.eye, judge.curves, results, judge.templates), [r.caption for r in results])
    kinds = [PARTS[r.caption][0] for r in results]
    fronts = [has_front(r.caption) for r in results]
    rows = []
    extra, kind = judge_extra(judge), head or head_kind(judge.head)
    for fit, judged in (("leave-kind-out", leave_kind_out(x, results, kinds, fronts, extra, kind)),
                        ("in sample", in_sample(x, results, fronts, extra, kind))):  # fmt: skip
        for part in ("all", "v3", *BLOCKS):
            idx = [i for i, r in enumerate(results) if r.consensus and part in ("all", source[i])]
            a = agreement([results[i].consensus for i in idx], [judged[i][0] for i in idx])
            rows.append({"fit": f"{fit}, pooled", "source": part, **{k: v for k, v in a.items() if k != "confusion"},
                         "judge": judge.version, "commit": code_commit()})  # fmt: skip
    return rows


def arm_agreements(x, results: list, kinds: list[str], fronts: list[bool], source: list[str], nv3: int,
                   parts=("all", "empirical-janus")):  # fmt: skip
    """For the judge's experiments with features ``x`` [R, F] of ``results`` (v3's first ``nv3``,
    then the fresh set's, each from ``source``): over v3's results alone and pooled with the
    fresh set's, the head fitted leave-kind-out and in sample; yields (scope, part, agreement
    leave-kind-out, agreement in sample) with the consensus, per part (all, or one source)."""
    from gdbench.metrics.judge.evaluate import agreement, in_sample, leave_kind_out

    for scope in ("v3", "pooled"):
        res = results[:nv3] if scope == "v3" else results
        n = len(res)
        lko, ins = leave_kind_out(x[:n], res, kinds[:n], fronts[:n]), in_sample(x[:n], res, fronts[:n])
        for part in parts:
            idx = [i for i, r in enumerate(res) if r.consensus and part in ("all", source[i])]
            if idx:
                truth = [res[i].consensus for i in idx]
                yield (
                    scope,
                    part,
                    agreement(truth, [lko[i][0] for i in idx]),
                    agreement(truth, [ins[i][0] for i in idx]),
                )


def _read(path: Path) -> list[dict]:
    with open(path, newline="") as f:
        return list(csv.DictReader(f))


def main(argv=None) -> int:
    import argparse

    from gdbench.core.io import write_csv

    ap = argparse.ArgumentParser(prog="python -m gdbench.experiments.judge_fresh", description=__doc__.split("\n\n")[0])
    ap.add_argument("--runs", type=Path, help="the sweep folder of docs/results/judge/fresh/sweep.sh (run-folder mode)")
    sets = ", ".join(f"{k} ({v.registration})" for k, v in FRESH_SETS.items())
    ap.add_argument("--set", dest="which", choices=sorted(FRESH_SETS), default="fresh", help=f"which fresh set: {sets}")
    ap.add_argument("--out", type=Path, help="where judged.csv and agreement.csv go (default: the set's folder; "
                    "required with --judge, so another judge's reading never replaces the shipped one's)")  # fmt: skip
    ap.add_argument("--judge", type=Path, help="the judge's folder (default: the shipped one; an earlier judge's "
                    "folder reads the set as that judge did)")  # fmt: skip
    ap.add_argument("--recompute", action="store_true", help="agreement.csv from the committed judged.csv only")
    ap.add_argument("--pooled", action="store_true", help="the diagnostic: the head refitted on v3's and the fresh "
                    "set's labels together (pooled.csv); nothing else is written")  # fmt: skip
    args = ap.parse_args(argv)
    fs = FRESH_SETS[args.which]
    if args.judge is not None:
        if args.out is None:
            ap.error("--judge: give --out too (the set's folder holds the shipped judge's reading)")
        missing = [n for n in ("eye.safetensors", "head.json") if not (args.judge / n).is_file()]
        if missing:
            ap.error(f"--judge: {args.judge} holds no judge (missing {', '.join(missing)})")
    if not fs.key.is_file():
        ap.error(f"--set {args.which}: {fs.key} is missing (its sheets and labels are not committed yet: "
                 f"{fs.registration})")  # fmt: skip
    args.out = args.out or fs.folder
    if args.pooled:
        rows = pooled(which=args.which, judge_dir=args.judge)
        write_csv(rows, args.out / "pooled.csv")
        for r in rows:
            print(f"{r['fit']:26s} {r['source']:16s} n {r['n']:3d}: kappa {r['kappa_janus']:.2f} (Janus split), "
                  f"{r['kappa_four']:.2f} (four)")  # fmt: skip
        return 0
    if args.runs is not None and not args.runs.is_dir():
        ap.error(f"--runs: {args.runs} is not a folder (the fresh sweep's OUT)")
    if args.recompute:
        judged = _read(args.out / "judged.csv")
    else:
        judged = judge_fresh(runs=args.runs, which=args.which, judge_dir=args.judge)
    if not args.recompute:
        write_csv(judged, args.out / "judged.csv")
    rows = agreement_rows(judged)
    write_csv(rows, args.out / "agreement.csv")
    for r in rows:
        if (r["truth"] == "consensus" and r["block"] == "all") or r["mode"].startswith("rater2"):
            print(f"{r['mode']:22s} {r['block']:16s} n {r['n']:3d}: kappa {r['kappa_janus']:.2f} (Janus split), "
                  f"{r['kappa_four']:.2f} (four); fails: {r.get('fails') or 'none'}")  # fmt: skip
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
