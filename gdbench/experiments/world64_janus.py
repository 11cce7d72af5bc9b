"""The janus setting on the 64 px one-call front model, described (the prior issue's fifth item;
docs/learned_prior.md, "The janus setting on the 64 px model"): gd and gd-no-sn on v3's 31 janus
prompts at seeds 0-1, labelled blind by two passes of raters, and the judge as shipped read on the
same results in both modes (the prior issue's "labelled set of its own, read by the judge as it
stands"). A description, not a verdict: no claim is tested.

    python -m gdbench.experiments.world64_janus --runs OUT/janus --to docs/results/learned_prior/world64/janus

Without ``--runs`` the results are read from the committed sheets alone (six views; no run-folder
mode, GT PSNR or Gaussians), so any machine can read the set with a new judge.

Writes ``judged.csv`` (a row per result: the raters' labels, the consensus, the judge's in each
mode, GT PSNR, Gaussians), ``agreement.csv`` (the judge against the raters by mode and arm, with
the judge issue's thresholds), ``by_arm.csv`` (each label's share by arm and reader, GT PSNR and
Gaussians), ``by_prompt.csv`` and ``summary.md`` (with the three sheets chosen by rule: the
prompts of the highest, the median and the lowest mean GT PSNR over their four results).
"""

from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

HERE = Path("docs/results/learned_prior/world64/janus_labels")
"""The committed sheets (WebP) and key of the set."""
LABELS = {"rater1": Path("fixtures/labels/world64_rater1.csv"), "rater2": Path("fixtures/labels/world64_rater2.csv")}
BATCH = "world64"
ARMS = ("gd", "gd-no-sn")
CLASSES = ("front_everywhere", "second_face", "blob", "fine")


def labelled_results(root: Path = Path(".")):
    """The set's results from the committed sheets, with both passes' labels."""
    from gdbench.metrics.judge.sheets import attach_labels, read_batch

    root = Path(root)
    results = read_batch(root / HERE / "sheets", root / HERE / "key.json", batch=BATCH)
    return attach_labels(results, {k: root / v for k, v in LABELS.items()})


def judged_rows(runs: Path | None, root: Path = Path("."), judge_folder: Path | None = None) -> list[dict]:
    """Every result judged from its sheet's six views and from its run folder under ``runs`` (the
    janus.sh sweep's janus/ folder: the key's run path below ``cells/``), with its cells.csv row's
    GT PSNR and Gaussians; ``runs`` None: the six views alone (the run-folder columns empty)."""
    from gdbench.core.provenance import code_commit
    from gdbench.metrics.judge.judge import load_judge
    from gdbench.metrics.judge.sheets import SHEET_AZIMUTHS

    cells = {}
    if runs is not None:
        runs = Path(runs)
        cells_csv = runs / "cells.csv"
        if not cells_csv.is_file():
            raise FileNotFoundError(f"runs: no cells.csv in {runs} (the janus.sh sweep's janus/ folder)")
        with open(cells_csv, newline="") as f:
            cells = {r["run_id"]: r for r in csv.DictReader(f)}
    judge, commit = load_judge(str(judge_folder) if judge_folder else None), code_commit()
    rows = []
    for r in labelled_results(root):
        parts = Path(r.run).parts
        six, whole = judge.views(r.views, SHEET_AZIMUTHS, r.caption), {"label": "", "confidence": ""}
        if runs is not None:
            folder = runs.joinpath(*parts[parts.index("cells") :])
            if not (folder / "scene.ply").is_file():
                raise FileNotFoundError(f"runs: {folder} has no scene.ply (sheet number {r.number})")
            whole = judge.run(folder)
        cell = cells.get(r.run_id, {})
        rows.append({
            "number": r.number, "run_id": r.run_id, "caption": r.caption, "block": parts[-2], "seed": parts[-1],
            "rater1": r.labels.get("rater1", ""), "rater2": r.labels.get("rater2", ""), "consensus": r.consensus or "",
            "six_views": six["label"], "six_views_confidence": six["confidence"],
            "run_folder": whole["label"], "run_folder_confidence": whole["confidence"],
            "gt_psnr": cell.get("gt_psnr", ""), "gaussians": cell.get("gaussians", ""),
            "judge": judge.version, "commit": commit,
        })  # fmt: skip
    return rows


def _mean(xs) -> float | None:
    xs = [float(x) for x in xs if x not in ("", None)]
    return statistics.fmean(xs) if xs else None


def by_arm(judged: list[dict]) -> list[dict]:
    """Per arm and reader (each pass, the consensus, the judge in each mode): each class's share
    of the results that reader labels, with GT PSNR and Gaussians (means over the arm)."""
    out = []
    for arm in ARMS:
        mine = [r for r in judged if r["block"] == arm]
        for reader in ("rater1", "rater2", "consensus", "six_views", "run_folder"):
            labelled = [r[reader] for r in mine if r[reader]]
            if not labelled:  # no run folders read
                continue
            out.append({"arm": arm, "reader": reader, "results": len(labelled),
                        **{c: sum(x == c for x in labelled) / len(labelled) for c in CLASSES},
                        "janus": sum(x in ("front_everywhere", "second_face") for x in labelled) / len(labelled),
                        "gt_psnr": _mean(r["gt_psnr"] for r in mine), "gaussians": _mean(r["gaussians"] for r in mine),
                        "judge": mine[0]["judge"], "commit": mine[0]["commit"]})  # fmt: skip
    return out


def by_prompt(judged: list[dict]) -> list[dict]:
    """Per prompt: the mean GT PSNR of its four results, each arm's consensus labels and the judge's."""
    out, mode = [], "run_folder" if any(r["run_folder"] for r in judged) else "six_views"
    for caption in sorted({r["caption"] for r in judged}):
        mine = [r for r in judged if r["caption"] == caption]
        row = {"prompt": caption, "gt_psnr": _mean(r["gt_psnr"] for r in mine)}
        for arm in ARMS:
            a = sorted((r for r in mine if r["block"] == arm), key=lambda r: r["seed"])
            row[f"consensus_{arm}"] = " ".join(r["consensus"] or "-" for r in a)
            row[f"judge_{arm}"] = " ".join(r[mode] for r in a)
        out.append(row)
    return out


def sheets_by_rule(prompts: list[dict]) -> dict[str, str]:
    """The prompts of the highest, the median and the lowest mean GT PSNR (the median: the lower
    middle of an even count); none where no GT PSNR was read."""
    ranked = sorted((p for p in prompts if p["gt_psnr"] is not None), key=lambda p: -p["gt_psnr"])
    if not ranked:
        return {}
    return {"highest": ranked[0]["prompt"], "median": ranked[(len(ranked) - 1) // 2]["prompt"],
            "lowest": ranked[-1]["prompt"]}  # fmt: skip


def main(argv=None) -> int:
    from gdbench.core.io import atomic_write, write_csv
    from gdbench.experiments.judge_fresh import agreement_rows

    doc = __doc__.split("\n\n")[0]
    p = argparse.ArgumentParser(prog="python -m gdbench.experiments.world64_janus", description=doc)
    p.add_argument("--runs", type=Path, default=None,
                   help="the janus.sh sweep's janus/ folder (without it: the committed sheets' six views)")  # fmt: skip
    p.add_argument("--to", type=Path, default=Path("docs/results/learned_prior/world64/janus"))
    p.add_argument("--judge", type=Path, default=None, help="another judge's folder (default: the shipped one)")
    a = p.parse_args(argv)
    judged = judged_rows(a.runs, judge_folder=a.judge)
    agree, arms, prompts = agreement_rows(judged, ARMS), by_arm(judged), by_prompt(judged)
    a.to.mkdir(parents=True, exist_ok=True)
    for name, rows in (("judged", judged), ("agreement", agree), ("by_arm", arms), ("by_prompt", prompts)):
        write_csv(rows, a.to / f"{name}.csv")
    picks = sheets_by_rule(prompts)
    f = lambda v: "" if v is None else f"{v:.2f}"  # noqa: E731
    lines = [f"Judge {judged[0]['judge']}, commit {judged[0]['commit']}.", "",
             "| arm | reader | results | front_everywhere | second_face | blob | fine | Janus | GT PSNR | Gaussians |",
             "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {r['arm']} | {r['reader']} | {r['results']} | " + " | ".join(f(r[c]) for c in (*CLASSES, "janus"))
              + f" | {f(r['gt_psnr'])} | {'' if r['gaussians'] is None else round(r['gaussians'])} |"
              for r in arms]  # fmt: skip
    lines += ["", "| mode | block | results | kappa Janus | kappa four | recall fe | recall blob | recall fine "
              "| fine warned | fails |", "|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    lines += [f"| {r['mode']} | {r['block']} | {r['n']} | {f(r['kappa_janus'])} | {f(r['kappa_four'])} | "
              f"{f(r['recall_front_everywhere'])} | {f(r['recall_blob'])} | {f(r['recall_fine'])} | "
              f"{f(r['fine_warned'])} | {r['fails'] or 'none'} |"
              for r in agree if r["truth"] == "consensus"]  # fmt: skip
    if picks:
        lines += ["", "Sheets by rule (mean GT PSNR of the prompt's four results): "
                  + "; ".join(f"{k}: {v}" for k, v in picks.items())]  # fmt: skip
    text = "\n".join(lines) + "\n"
    atomic_write(a.to / "summary.md", lambda fh: fh.write(text.encode()))
    print(text)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
