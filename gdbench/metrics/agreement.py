"""Agreement of the view metrics with labels made by eye (docs/scoring.md, "The Janus classes
against labels"): each labelled result's class by the metric (``views.result_class`` of its
scores.json) against its label, as a confusion matrix, each class's recall and precision, and
Cohen's kappa over the four classes and over the Janus / not-Janus split. Results of assets
without a front (their Janus rates empty: the hamburger) are left out and counted: a person sees
a hamburger as whole or not, and the metric has no Janus class for it.

    python -m gdbench.metrics.agreement --labels LABELS.csv --runs SWEEP_DIR [...] --out DIR

The labels CSV has a ``run_id`` and a ``label`` column (one of ``LABELS``); every run id must name
a run folder under ``--runs`` (its run.json's ``run_id``) that has been scored.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

from gdbench.metrics.views import CLASSES

LABELS = CLASSES
"""The classes a result is labelled with: a view's classes, for a whole result."""
JANUS = ("front_everywhere", "second_face")


def cohen_kappa(truth: list[str], pred: list[str], labels=LABELS) -> float:
    """Cohen's kappa of two labellings: (p_o - p_e) / (1 - p_e), p_o the share that agree and p_e
    the agreement expected from the two labellings' class frequencies; 1 when p_e is 1 and they
    agree."""
    n = len(truth)
    if n == 0 or n != len(pred):
        raise ValueError(f"truth, pred: expected two labellings of the same results, got {n} and {len(pred)}")
    po = sum(t == p for t, p in zip(truth, pred)) / n
    pe = sum((truth.count(c) / n) * (pred.count(c) / n) for c in labels)
    return 1.0 if pe == 1 else (po - pe) / (1 - pe)


def confusion(truth: list[str], pred: list[str], labels=LABELS) -> dict[str, dict[str, int]]:
    """counts[label][metric's class]."""
    out = {t: {p: 0 for p in labels} for t in labels}
    for t, p in zip(truth, pred):
        out[t][p] += 1
    return out


def read_labels(path: Path) -> list[dict]:
    """The rows of a labels CSV, each checked: a run_id and a label of ``LABELS``."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"labels: no file at {path}")
    with open(path, newline="") as f:
        rows = list(csv.DictReader(f))
    for i, r in enumerate(rows, start=2):
        if not r.get("run_id") or r.get("label") not in LABELS:
            raise ValueError(f"labels: {path} line {i}: expected a run_id and a label of {list(LABELS)}, got {r}")
    return rows


def runs_by_id(roots: list[Path]) -> dict[str, Path]:
    """Run folders under ``roots`` by their run.json's run_id."""
    found = {}
    for root in roots:
        for p in sorted(Path(root).rglob("run.json")):
            rid = json.loads(p.read_text()).get("run_id")
            if rid:
                found[rid] = p.parent
    return found


def agreement(labels: list[dict], runs: dict[str, Path]) -> dict:
    """The metric's class of every labelled result against its label (module docstring)."""
    from gdbench.metrics.views import result_class

    truth, pred, rows, frontless = [], [], [], []
    for r in labels:
        run = runs.get(r["run_id"])
        if run is None:
            raise ValueError(f"labels: run id {r['run_id']} names no run folder under --runs")
        scores = run / "scores.json"
        views = json.loads(scores.read_text()).get("views") if scores.is_file() else None
        if not views:
            raise ValueError(f"labels: run {r['run_id']} ({run}) has no view scores; run `gdbench score {run}`")
        if views.get("janus_rate") is None:  # an asset without a front: no Janus classes to compare
            frontless.append(r["run_id"])
            continue
        got = result_class(views)
        truth.append(r["label"])
        pred.append(got)
        rates = {k: views.get(k) for k in ("front_everywhere_rate", "multi_face_rate", "blob_rate", "front_share")}
        rows.append({"run_id": r["run_id"], "label": r["label"], "metric": got, **rates, "run": str(run)})
    recall = {c: _share([p == c for t, p in zip(truth, pred) if t == c]) for c in LABELS}
    precision = {c: _share([t == c for t, p in zip(truth, pred) if p == c]) for c in LABELS}
    split_t = ["janus" if t in JANUS else "not" for t in truth]
    split_p = ["janus" if p in JANUS else "not" for p in pred]
    if not truth:
        raise ValueError("labels: no labelled result of an asset with a front to compare")
    return {
        "results": len(truth),
        "left_out_no_front": len(frontless),
        "kappa": cohen_kappa(truth, pred),
        "kappa_janus_split": cohen_kappa(split_t, split_p, ("janus", "not")),
        "recall": recall,
        "precision": precision,
        "confusion": confusion(truth, pred),
        "rows": rows,
    }


def _share(xs: list[bool]) -> float | None:
    return sum(xs) / len(xs) if xs else None


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m gdbench.metrics.agreement", description=__doc__.split("\n\n")[0])
    ap.add_argument("--labels", type=Path, required=True, help="CSV with run_id and label columns")
    ap.add_argument("--runs", type=Path, nargs="+", required=True, help="folders holding the labelled run folders")
    ap.add_argument("--out", type=Path, help="folder for agreement.json and agreement.csv (default: print only)")
    args = ap.parse_args(argv)
    try:
        res = agreement(read_labels(args.labels), runs_by_id(args.runs))
    except (ValueError, FileNotFoundError) as e:
        print(f"agreement: error: {e}", file=sys.stderr)
        return 2
    print(f"{res['results']} results (and {res['left_out_no_front']} of assets without a front, left out): "
          f"kappa {res['kappa']:.3f}, Janus / not-Janus kappa {res['kappa_janus_split']:.3f}")  # fmt: skip
    print("label \\ metric: " + ", ".join(LABELS))
    for t in LABELS:
        counts = " ".join(f"{res['confusion'][t][p]:4d}" for p in LABELS)
        print(f"  {t:17s} {counts}   recall {res['recall'][t]}")
    if args.out is not None:
        from gdbench.core.io import write_csv, write_json
        from gdbench.core.provenance import code_commit

        args.out.mkdir(parents=True, exist_ok=True)
        summary = {k: v for k, v in res.items() if k != "rows"} | {"commit": code_commit()}
        write_json(summary, args.out / "agreement.json")
        write_csv(res["rows"], args.out / "agreement.csv")
    return 0


if __name__ == "__main__":
    sys.exit(main())
