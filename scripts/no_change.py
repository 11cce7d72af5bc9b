"""Proof that a change of structure changed no behaviour: record what a checkout computes, then
compare two records.

    PYTHONPATH=OLD python scripts/no_change.py record --checkout OLD --out old.json [--v3 /work/runs/v3]
    PYTHONPATH=NEW python scripts/no_change.py record --checkout NEW --out new.json [--v3 /work/runs/v3]
    python scripts/no_change.py compare old.json new.json

``record`` runs the checkout's own code (put it first on PYTHONPATH; this file imports nothing of
gdbench at its top, so it works from any checkout) and stores:

- ``params``: the SHA-256 of the parameters after ``--steps`` (150) steps of every preset on both
  CPU priors ('a yellow duck', seed 0);
- ``run_ids``: the run id of every preset on the three priors, and of every stored run.json in
  fixtures/runs/ converted by the checkout's reader (beside the id the file records);
- ``sweep``: a two-cell sweep's cells.csv (gd, sjc-gs; 60 steps; no COLMAP) without its timing
  and provenance columns;
- ``v3``, with ``--v3 FOLDER`` (the unpacked cells, docs/decisive_v3.md "To re-run the report"):
  the SHA-256 of every file v3's report writes, run with the commit it names fixed (its tables and
  its plots' titles name it) and the checkout's commit strings blanked.

``compare`` prints every key that differs and exits 1 when any does. Both records must come from
the same machine: the same code gives other bits on another host (docs/log/2026-11-27.md).
"""

from __future__ import annotations

import argparse
import csv
import hashlib
import io
import json
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path

SWEEP_DROP = ("cell_s", "train_time_s", "train_commit", "score_commit", "commit")
"""cells.csv columns that name when and by which commit, not what was computed."""


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def params_hash(params: dict) -> str:
    h = hashlib.sha256()
    for k in sorted(params):
        t = params[k].detach().cpu().contiguous()
        h.update(k.encode() + str(tuple(t.shape)).encode() + t.numpy().tobytes())
    return h.hexdigest()


def record_params(steps: int, priors: list[str], tmp: Path) -> dict[str, str]:
    from gdbench.train.config import PRESETS, preset
    from gdbench.train.trainer import init_state, make_context, train_step

    out = {}
    for prior in priors:
        for name in PRESETS:
            cfg = preset(name, prompt="a yellow duck", prior=prior, steps=steps, progress=False,
                         out=tmp / f"{prior}-{name}")  # fmt: skip
            ctx = make_context(cfg)
            state = init_state(ctx)
            for _ in range(steps):
                train_step(state, ctx)
            out[f"{prior}/{name}"] = params_hash(state.params)
            print(f"  params {prior}/{name}: {out[f'{prior}/{name}'][:16]}", flush=True)
    return out


def record_run_ids(checkout: Path) -> dict[str, str]:
    from gdbench.train.config import PRESETS, config_from_dict, preset
    from gdbench.train.run import run_id

    out = {}
    for prior in ("empirical", "learned", "sd"):
        for name in PRESETS:
            out[f"{prior}/{name}"] = run_id(preset(name, prompt="a yellow duck", prior=prior))
    for f in sorted((checkout / "fixtures" / "runs").glob("*.run.json")):
        d = json.loads(f.read_text())
        out[f"fixture/{f.name}"] = f"{run_id(config_from_dict(d['config']))} (file: {d['run_id']})"
    return out


def record_sweep(checkout: Path, tmp: Path) -> list[dict]:
    folder = tmp / "sweep"
    cmd = [sys.executable, "-m", "gdbench.app.cli", "sweep", "--presets", "gd", "sjc-gs", "--steps", "60",
           "--no-colmap", "--workers", "1", "--out", str(folder)]  # fmt: skip
    r = subprocess.run(
        cmd, cwd=checkout, env=dict(os.environ, PYTHONPATH=str(checkout)), capture_output=True, text=True
    )
    if r.returncode:
        raise SystemExit(f"sweep failed (exit {r.returncode}):\n{r.stdout[-2000:]}{r.stderr[-2000:]}")
    rows = list(csv.DictReader(io.StringIO((folder / "cells.csv").read_text())))
    return [{k: v for k, v in row.items() if k not in SWEEP_DROP} for row in rows]


def record_v3(checkout: Path, cells: Path, tmp: Path) -> dict[str, str]:
    results, figures = tmp / "v3", tmp / "v3-figures"
    labels = [str(checkout / "fixtures" / "labels" / f"v3_rater{i}.csv") for i in (1, 2)]
    # the report names the commit it runs at, in its tables and in its plots' titles: a fixed name
    # here, so the two checkouts' files compare byte for byte
    fixed = ("import runpy, sys, gdbench.core.provenance as p; p.code_commit = lambda: 'c0mm1t000000'; "
             "sys.argv[0] = 'v3'; runpy.run_module('gdbench.experiments.v3', run_name='__main__')")  # fmt: skip
    cmd = [sys.executable, "-c", fixed, "report", "--out", str(cells), "--results", str(results),
           "--figures", str(figures), "--labels", *labels, "--no-progress"]  # fmt: skip
    r = subprocess.run(
        cmd, cwd=checkout, env=dict(os.environ, PYTHONPATH=str(checkout)), capture_output=True, text=True
    )
    if r.returncode:
        raise SystemExit(f"v3 report failed (exit {r.returncode}):\n{r.stdout[-2000:]}{r.stderr[-2000:]}")
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=checkout, capture_output=True, text=True).stdout.strip()
    blank = re.compile("|".join(re.escape(head[:n]) for n in (40, 12, 10, 7)).encode())
    out = {}
    for f in sorted(p for p in [*results.rglob("*"), *figures.rglob("*")] if p.is_file()):
        out[str(f.relative_to(tmp))] = _sha(blank.sub(b"<commit>", f.read_bytes()))
    return out


def record(a) -> int:
    checkout = a.checkout.resolve()
    rec: dict[str, object] = {"checkout": str(checkout), "steps": a.steps}
    rec["commit"] = subprocess.run(
        ["git", "rev-parse", "HEAD"], cwd=checkout, capture_output=True, text=True
    ).stdout.strip()
    with tempfile.TemporaryDirectory(prefix="no_change-") as t:
        tmp = Path(t)
        rec["run_ids"] = record_run_ids(checkout)
        print(f"run ids: {len(rec['run_ids'])}", flush=True)
        rec["params"] = record_params(a.steps, ["empirical", "learned"], tmp)
        rec["sweep"] = record_sweep(checkout, tmp)
        print(f"sweep: {len(rec['sweep'])} rows", flush=True)
        if a.v3 is not None:
            rec["v3"] = record_v3(checkout, a.v3, tmp)
            print(f"v3 report: {len(rec['v3'])} files", flush=True)
    a.out.write_text(json.dumps(rec, indent=1) + "\n")
    print(f"record: {a.out}")
    return 0


def compare(a) -> int:
    old, new = (json.loads(p.read_text()) for p in (a.old, a.new))
    bad = 0
    for key in ("run_ids", "params", "sweep", "v3"):
        if key not in old or key not in new:
            print(f"{key}: not in both records, not compared")
            continue
        x, y = old[key], new[key]
        if isinstance(x, dict):
            diff = sorted(k for k in x.keys() | y.keys() if x.get(k) != y.get(k))
            for k in diff:
                print(f"{key} {k}: {x.get(k)} -> {y.get(k)}")
            print(f"{key}: {len(x)} compared, {len(diff)} differ")
        else:
            diff = [i for i, (r, s) in enumerate(zip(x, y)) if r != s] + ([-1] if len(x) != len(y) else [])
            for i in diff:
                print(f"{key} row {i}: differs")
            print(f"{key}: {len(x)} rows compared, {len(diff)} differ")
        bad += len(diff)
    print("no change" if not bad else f"{bad} differences")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    sub = ap.add_subparsers(dest="what", required=True)
    r = sub.add_parser("record", help="what a checkout computes")
    r.add_argument("--checkout", type=Path, required=True, help="the checkout whose code is first on PYTHONPATH")
    r.add_argument("--out", type=Path, required=True, help="the record (JSON)")
    r.add_argument("--steps", type=int, default=150, help="training steps of every preset (default 150)")
    r.add_argument("--v3", type=Path, help="the unpacked v3 cells: also re-generate v3's report")
    c = sub.add_parser("compare", help="two records; exit 1 when they differ")
    c.add_argument("old", type=Path)
    c.add_argument("new", type=Path)
    a = ap.parse_args(argv)
    if a.what == "record":
        if not (a.checkout / ".git").exists():
            raise SystemExit(f"--checkout: {a.checkout} is not a git checkout")
        if a.steps < 1:
            raise SystemExit(f"--steps: expected an int >= 1, got {a.steps}")
        if a.v3 is not None and not a.v3.is_dir():
            raise SystemExit(f"--v3: {a.v3} is not a folder (unpack docs/results/v3/carry/cells.tar.xz there)")
        return record(a)
    return compare(a)


if __name__ == "__main__":
    raise SystemExit(main())
