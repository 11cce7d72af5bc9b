"""The 64 px one-call uniform model against the shipped 32 px uniform model on text to 3D (the
prior issue's item 4; docs/learned_prior.md): one row per caption from the two sweeps of
``docs/results/learned_prior/world64/sweep.sh`` (GT PSNR, Gaussians and the judge's label of
each, the difference in PSNR), the target read from the rows (the new model's median at least
1 dB above the shipped one's), and the duck's seeds on the new model.

    python -m gdbench.experiments.prior64 --runs OUT --to docs/results/learned_prior/world64 --model MODEL

Writes ``table.csv`` (a row per caption, with both cells' run ids and commits), ``duck.csv``,
``table.md`` and, with ``--model``, ``model.json`` (the weights' sha256 and training metadata: a
weights file can change under its path, and a sweep's run id names the path). The turntables
are read by eye from blinded sheets before this table is read:

    python -m gdbench.metrics.label_sheets --runs OUT/shipped OUT/world64 OUT/duck --out SHEETS --key KEY

and ``--eye DIR`` (the key as key.json, each rater's labels as rater*.csv: number,
reads_as_caption, features_drawn) puts the raters' readings beside each cell and counts them.
"""

from __future__ import annotations

import argparse
import csv
import statistics
from pathlib import Path

TARGET_DB = 1.0
"""The issue's target: the median GT PSNR over the 38 captions at least this far above the shipped
model's median (a difference of medians; the median of the captions' own gains is reported beside
it)."""
CAPTIONS = 38
"""Captions the table must have from both sweeps (fewer: named in the summary as missing)."""


def read_cells(sweep: Path) -> dict[tuple[str, int], dict]:
    """(prompt, seed) -> the row of a sweep's cells.csv; a missing file is an error naming it."""
    path = Path(sweep) / "cells.csv"
    if not path.is_file():
        raise FileNotFoundError(f"runs: no cells.csv in {sweep} (has its sweep run?)")
    with open(path) as f:
        return {(r["prompt"], int(r["seed"])): r for r in csv.DictReader(f)}


def _num(v: str | None) -> float | None:
    try:
        return float(v) if v not in (None, "") else None
    except ValueError:
        return None


def table_rows(shipped: dict, world64: dict, held_out: tuple[str, ...] = ()) -> list[dict]:
    """One row per prompt both sweeps have at seed 0: each model's GT PSNR, Gaussians and judge
    label, and the difference new - shipped."""
    rows = []
    for prompt, seed in sorted(k for k in shipped if k in world64 and k[1] == 0):
        a, b = shipped[(prompt, seed)], world64[(prompt, seed)]
        pa, pb = _num(a.get("gt_psnr")), _num(b.get("gt_psnr"))
        rows.append({
            "prompt": prompt, "held_out": prompt in held_out,
            "psnr_shipped": pa, "psnr_world64": pb,
            "psnr_gain": None if pa is None or pb is None else pb - pa,
            "gaussians_shipped": a.get("gaussians"), "gaussians_world64": b.get("gaussians"),
            "judge_shipped": a.get("judge_label", ""), "judge_world64": b.get("judge_label", ""),
            "run_shipped": a.get("run_id"), "run_world64": b.get("run_id"),
            "commit_shipped": a.get("train_commit"), "commit_world64": b.get("train_commit"),
        })  # fmt: skip
    return rows


def summary(rows: list[dict]) -> dict:
    """The medians, the median gain against ``TARGET_DB`` and the count of captions that gain."""
    both = [r for r in rows if r["psnr_gain"] is not None]
    if not both:
        raise ValueError("rows: no caption has a GT PSNR in both sweeps")
    old = statistics.median(r["psnr_shipped"] for r in both)
    new = statistics.median(r["psnr_world64"] for r in both)
    return {
        "captions": len(both),
        "missing": CAPTIONS - len(both),
        "median_shipped": old,
        "median_world64": new,
        "median_gain": new - old,
        "median_of_gains": statistics.median(r["psnr_gain"] for r in both),
        "gain_meets_target": new - old >= TARGET_DB and len(both) == CAPTIONS,
        "captions_gaining": sum(r["psnr_gain"] > 0 for r in both),
        "commits": sorted({r[k] for r in rows for k in ("commit_shipped", "commit_world64") if r[k]}),
    }


def eye_readings(folder: Path) -> dict[str, dict[str, tuple[str, str]]]:
    """run id -> rater -> (reads_as_caption, features_drawn), from a blind reading's folder (key.json:
    sheet number -> run id; rater*.csv: number, reads_as_caption, features_drawn). A number the key
    lacks is an error naming the file."""
    import json

    folder = Path(folder)
    key = json.loads((folder / "key.json").read_text())
    out: dict[str, dict[str, tuple[str, str]]] = {}
    raters = sorted(folder.glob("rater*.csv"))
    if not raters:
        raise FileNotFoundError(f"eye: no rater*.csv in {folder}")
    for path in raters:
        with open(path, newline="") as f:
            for row in csv.DictReader(f):
                if row["number"] not in key:
                    raise ValueError(f"eye: {path} labels sheet number {row['number']}, which key.json lacks")
                run = key[row["number"]]["run_id"]
                out.setdefault(run, {})[path.stem] = (row["reads_as_caption"], row["features_drawn"])
    return out


def eye_summary(rows: list[dict], duck: list[dict], eye: dict) -> dict:
    """Per rater: captions read as their caption on each model (all, held out), the duck's seeds
    with its features drawn."""
    raters = sorted({r for v in eye.values() for r in v})
    out = {}
    for rater in raters:

        def yes(run, i, rater=rater):
            return eye.get(run, {}).get(rater, ("", ""))[i] == "yes"

        out[rater] = (
            {f"reads_{arm}": sum(yes(r[f"run_{arm}"], 0) for r in rows) for arm in ("shipped", "world64")}
            | {
                f"held_out_reads_{arm}": sum(yes(r[f"run_{arm}"], 0) for r in rows if r["held_out"])
                for arm in ("shipped", "world64")
            }
            | {"duck_features_drawn": sum(yes(d.get("run_id"), 1) for d in duck), "duck_seeds": len(duck)}
        )
    return out


def markdown(rows: list[dict], s: dict, duck: list[dict]) -> str:
    f = lambda v: "" if v is None else f"{v:.2f}"  # noqa: E731
    verdict = "met" if s["gain_meets_target"] else "not met"
    if s["missing"]:
        verdict += f", {s['missing']} captions missing"
    m = s.get("model")
    out = [
        *(
            [
                f"The 64 px model: {m['path']} (sha256 {m['sha256'][:16]}, trained at {m['commit']}, {m['steps']} "
                f"steps, distilled at guidance {m['teacher_guidance']}).",
                "",
            ]
            if m
            else []
        ),
        f"Text to 3D on {s['captions']} captions, seed 0, at the defaults (commit {', '.join(s['commits'])}): "
        f"median GT PSNR {s['median_shipped']:.2f} dB (shipped 32 px) -> {s['median_world64']:.2f} dB (64 px one "
        f"call): {s['median_gain']:+.2f} dB (target {TARGET_DB:+.1f} over all {CAPTIONS}: {verdict}); the "
        f"median of the captions' own gains {s['median_of_gains']:+.2f} dB; {s['captions_gaining']} captions gain.",
        "",
        *(
            [
                f"By eye ({rater}, blind): read as the caption {e['reads_shipped']} of {len(rows)} (shipped) and "
                f"{e['reads_world64']} (64 px); held out {e['held_out_reads_shipped']} and "
                f"{e['held_out_reads_world64']} "
                f"of {sum(r['held_out'] for r in rows)}; the duck's front features drawn in {e['duck_features_drawn']} "
                f"of its {e['duck_seeds']} seeds on the 64 px model."
                for rater, e in s.get("eye", {}).items()
            ]
            + [""]
            if s.get("eye")
            else []
        ),
        "| caption | shipped dB | 64 px dB | gain | Gaussians shipped / 64 px | judge shipped / 64 px "
        "| eye shipped / 64 px |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        name = r["prompt"] + (" (held out)" if r["held_out"] else "")
        counts = f"{r['gaussians_shipped']} / {r['gaussians_world64']}"
        judged = f"{r['judge_shipped']} / {r['judge_world64']}"
        seen = f"{r.get('eye_shipped', '')} / {r.get('eye_world64', '')}"
        out.append(
            f"| {name} | {f(r['psnr_shipped'])} | {f(r['psnr_world64'])} | {f(r['psnr_gain'])} | {counts} | {judged} "
            f"| {seen} |"
        )
    if duck:
        out += ["", "| the duck, 64 px one call: seed | GT PSNR | judge | eye: features drawn |", "|---|---|---|---|"]
        out += [f"| {d['seed']} | {f(_num(d.get('gt_psnr')))} | {d.get('judge_label', '')} | {d.get('eye', '')} |"
                for d in duck]  # fmt: skip
    return "\n".join(out) + "\n"


def main(argv=None) -> int:
    from gdbench.core.io import atomic_write, write_csv, write_json

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--runs", type=Path, required=True, help="the OUT of sweep.sh (shipped/, world64/, duck/)")
    p.add_argument("--to", type=Path, required=True, help="where table.csv, duck.csv and table.md go")
    p.add_argument(
        "--model",
        default=None,
        help="the 64 px model the world64 sweep ran (its sha256 and "
        "training metadata go into model.json and the table; a weights file can change under its path)",
    )
    p.add_argument("--eye", type=Path, default=None, help="a blind reading's folder (key.json, rater*.csv): the "
                   "raters' readings beside each cell")  # fmt: skip
    p.add_argument("--held-out", nargs="*", default=None, help="captions held out of training (default: the "
                   "shipped uniform model's)")  # fmt: skip
    a = p.parse_args(argv)
    held = tuple(a.held_out) if a.held_out is not None else _held_out()
    rows = table_rows(read_cells(a.runs / "shipped"), read_cells(a.runs / "world64"), held)
    s = summary(rows)
    duck_cells = read_cells(a.runs / "duck") if (a.runs / "duck" / "cells.csv").is_file() else {}
    duck = [dict(r, seed=k[1]) for k, r in sorted(duck_cells.items())]
    if a.eye:
        eye = eye_readings(a.eye)
        for r in rows:
            for arm in ("shipped", "world64"):
                r[f"eye_{arm}"] = "/".join(v[0] for _, v in sorted(eye.get(r[f"run_{arm}"], {}).items()))
        for d in duck:
            d["eye"] = "/".join(v[1] for _, v in sorted(eye.get(d.get("run_id"), {}).items()))
        s["eye"] = eye_summary(rows, duck, eye)
    a.to.mkdir(parents=True, exist_ok=True)
    write_csv(rows, a.to / "table.csv")
    if duck:
        write_csv([{k: d.get(k) for k in ("prompt", "seed", "gt_psnr", "gaussians", "judge_label", "eye", "run_id",
                                          "train_commit")} for d in duck], a.to / "duck.csv")  # fmt: skip
    if a.model:
        s["model"] = model_identity(a.model)
        write_json(s["model"], a.to / "model.json")
    text = markdown(rows, s, duck)
    atomic_write(a.to / "table.md", lambda f: f.write(text.encode()))
    print(text)
    return 0


def model_identity(model: str) -> dict:
    """A model's file, sha256 and training metadata (commit, steps, final loss, distilled scale)."""
    import json

    from gdbench.core.io import sha256_file
    from gdbench.priors.learned.prior import load_model, model_path

    path = model_path(model)
    meta = load_model(path)[1]
    train = json.loads(meta.get("train", "{}"))
    return {"path": str(path), "sha256": sha256_file(path),
            **{k: meta.get(k) for k in ("commit", "steps", "final_loss")},
            "teacher_guidance": train.get("teacher_guidance")}  # fmt: skip


def _held_out() -> tuple[str, ...]:
    from gdbench.priors.learned.prior import LearnedPrior

    return tuple(LearnedPrior("uniform").held_out)


if __name__ == "__main__":
    raise SystemExit(main())
