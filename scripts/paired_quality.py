"""Issue 56's paired quality check, run end to end: the default run (gd, empirical prior) and the
learned prior's run of one prompt at each seed, from two checkouts (the old kernels and the new),
each scored, then compared seed by seed by ``paired_runs.py --check``.

    python scripts/paired_quality.py --old /work/frozen_old --new /work/frozen_new --out paired56

Each run is ``python -m gdbench.app.cli generate`` in its checkout's root (that checkout's code,
whatever this interpreter has installed), into OUT/{old,new}/{prior}/seed{s}; a run whose
scores.json exists and whose run.json names the checkout's present code is not run again, so an
interrupted check resumes, and a checkout that moved is run again. Writes
OUT/paired_{prior}.csv, OUT/checkouts.json (the two commits) and prints each prior's verdict;
the exit status is 1 when either fails.
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE.parent))  # this checkout's gdbench, without the install


def _commit(checkout: Path) -> str:
    """The code of ``checkout`` as a run made there records it in run.json (``checkout_code``)."""
    from gdbench.core.provenance import checkout_code

    if not (checkout / ".git").exists():
        raise SystemExit(f"--old/--new: {checkout} is not a git checkout")
    return checkout_code(checkout.resolve())


def run_one(checkout: Path, commit: str, out: Path, prompt: str, prior: str, seed: int, steps: int) -> float:
    """Train and score one run in ``checkout`` (skipped when its scores.json exists and its
    run.json names ``commit``, the checkout's code); seconds taken."""
    from gdbench.bench.bm_cell import cli_module

    run_json = out / "run.json"
    made_here = run_json.is_file() and json.loads(run_json.read_text()).get("commit") == commit
    if made_here and (out / "scores.json").is_file():
        return 0.0
    module = cli_module(checkout)
    if module is None:
        raise SystemExit(f"--old/--new: {checkout} holds no gdbench command line")
    cmd = [sys.executable, "-m", module, "generate", prompt, "--prior", prior, "--seed", str(seed),
           "--steps", str(steps), "--out", str(out.resolve()), "--overwrite", "--no-progress"]  # fmt: skip
    env = dict(os.environ, PYTHONPATH=str(checkout.resolve()))
    t0 = time.perf_counter()
    r = subprocess.run(cmd, cwd=checkout, env=env, capture_output=True, text=True)
    if r.returncode or not (out / "scores.json").is_file():
        raise SystemExit(f"run {out} failed (exit {r.returncode}):\n{r.stdout[-2000:]}{r.stderr[-2000:]}")
    return time.perf_counter() - t0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--old", type=Path, required=True, help="checkout with the old kernels (the reference)")
    ap.add_argument("--new", type=Path, required=True, help="checkout with the new kernels (the candidate)")
    ap.add_argument("--out", type=Path, required=True, help="folder of the runs and the tables")
    ap.add_argument("--seeds", default="0-7", help="'0-7' or '0,1,2' (default: issue 56's eight)")
    ap.add_argument("--priors", default="empirical,learned", help="comma-separated (default: both)")
    ap.add_argument("--prompt", default="a yellow duck")
    ap.add_argument("--steps", type=int, default=2000, help="training steps of every run (default: 2000)")
    args = ap.parse_args(argv)
    sys.path.insert(0, str(HERE))
    import paired_runs

    seeds = paired_runs._seeds(args.seeds)
    priors = [p for p in args.priors.split(",") if p]
    if not priors or any(p not in ("empirical", "learned") for p in priors):
        raise SystemExit(f"--priors: expected empirical and/or learned, got {args.priors!r}")
    if args.steps < 1:
        raise SystemExit(f"--steps: expected at least 1, got {args.steps}")
    arms = {"old": args.old, "new": args.new}
    args.out.mkdir(parents=True, exist_ok=True)
    record = {arm: {"checkout": str(path.resolve()), "commit": _commit(path)} for arm, path in arms.items()}
    record |= {"prompt": args.prompt, "steps": args.steps, "seeds": seeds, "priors": priors}
    (args.out / "checkouts.json").write_text(json.dumps(record, indent=1) + "\n")
    jobs = [(p, s, arm) for p in priors for s in seeds for arm in arms]
    for i, (prior, seed, arm) in enumerate(jobs, 1):  # old and new of a seed side by side: one phase
        run = args.out / arm / prior / f"seed{seed}"
        seconds = run_one(arms[arm], record[arm]["commit"], run, args.prompt, prior, seed, args.steps)
        print(f"[{i}/{len(jobs)}] {arm} {prior} seed {seed}: " + (f"{seconds:.0f} s" if seconds else "done before"))
    failed = False
    for prior in priors:
        print(f"-- {prior}")
        pattern = str(args.out / "{arm}" / prior / "seed{{s}}" / "scores.json")
        rc = paired_runs.main(["--a", pattern.format(arm="old"), "--b", pattern.format(arm="new"), "--seeds",
                               args.seeds, "--out", str(args.out / f"paired_{prior}.csv"), "--check"])  # fmt: skip
        failed |= rc != 0
    return 1 if failed else 0


if __name__ == "__main__":
    raise SystemExit(main())
