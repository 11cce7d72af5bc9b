"""Building the Janus judge (``gdbench train-judge``) and judging it against v3's labels.

1. **The eye's data**: every caption of the catalogue (the learned prior's held-out combinations
   and the hamburger included), each variant at ``views`` cameras about the turntables' elevation
   (``EYE_DATA``), rendered by pyrender as the learned prior's data is (cached the same way).
2. **The eye**: ``metrics/judge/train.py`` on those renders alone: no label of any result.
3. **The templates**: each caption's renders from the same data (``sameness.Templates``), which
   the sameness, front marking and outline readings compare views with.
4. **The head** (``HEAD``: the regression and boosted trees over the 57 numbers, their
   probabilities averaged, fine weighed against a false warning, ``blend.py``): fitted on the
   consensus results (both passes agree) of v3's committed sheets and the spent fresh sets'
   (``fit_results``); the leave-kind-out evaluation (every kind held out in turn) and the next
   fresh set say how it does out of sample. The seventh judge's references and the ground truth's
   fixtures (``reference.py``, ``fixtures.py``) are not read by the eighth's head.

Writes ``out/eye.safetensors`` (the eye's weights in float16, its settings, the data's key and the
commit as metadata), ``out/templates.safetensors``, ``out/head.json`` (the head and where it was
fitted) and, beside them,
``out/provenance.json``; ``evaluate_v3`` writes the agreement tables.
"""

from __future__ import annotations

import json
import time
from dataclasses import replace
from pathlib import Path

import torch

EYE_VIEWS = 256
"""Cameras per (caption, variant) of the eye's data."""
HEAD = "blend"
"""The head's kind (``head.HEADS``): the regression and the trees averaged from the eighth judge
(the first three: the regression; the fourth to the seventh: boosted trees)."""


def eye_data_config(views: int = EYE_VIEWS):
    """The eye's data: the catalogue's every caption, elevations about the turntables' 15 degrees."""
    from gdbench.assets.library import CAPTIONS
    from gdbench.priors.learned.data import DataConfig

    return DataConfig(views=views, captions=tuple(CAPTIONS), elevation_range=(-15.0, 45.0), seed=1)


def eye_crops(views: int = EYE_VIEWS, workers: int = 1, progress: bool = True):
    """(crops [N, 3, SIZE, SIZE], the data set) of the eye's data, rendered on first use."""
    from gdbench.metrics.judge.net import crop_views
    from gdbench.priors.learned.data import load_dataset

    data = load_dataset(eye_data_config(views), progress=progress, workers=workers)
    crops = torch.cat([crop_views(data.images[i : i + 2048]) for i in range(0, len(data), 2048)])
    return crops, data


def sheet_features(judge_eye, curves: dict, results, templates=None) -> torch.Tensor:
    """[R, F] features (``reading.result_features``) of sheet results, six views each."""
    from gdbench.metrics.judge.reading import result_features
    from gdbench.metrics.judge.sheets import SHEET_AZIMUTHS

    az = torch.tensor(SHEET_AZIMUTHS)
    return torch.stack(
        [result_features(judge_eye, curves, torch.from_numpy(r.views), az, r.caption, templates)[0] for r in results]
    )


def data_curves(data) -> dict:
    """The assets' elongation by azimuth (``reading.aspect_curves``) from the eye's data, at
    elevations within 15 degrees of the turntables'."""
    from gdbench.metrics.judge.reading import aspect_curves, log_aspect

    near = ((data.elevation - 15.0).abs() <= 15.0).nonzero().flatten()
    aspect = torch.cat([log_aspect(data.images[near[i : i + 4096]]) for i in range(0, len(near), 4096)])
    return aspect_curves(aspect, data.caption[near], data.azimuth[near], data.captions)


def build_judge(out: Path, *, steps: int = 3000, views: int = EYE_VIEWS, workers: int = 1, seed: int = 0,
                root: Path = Path("."), progress: bool = True, eye_from: Path | None = None) -> dict:  # fmt: skip
    """Train the eye (or take ``eye_from``'s, byte for byte), draw the sameness templates, fit the
    head on the labelled sheets (``fit_results``), write the three to ``out``; returns the provenance.
    With ``eye_from`` a judge folder that has templates (the second judge's on), its templates and
    the assets' elongation curves are taken as they are too (they are drawn from the same renders,
    so drawing them again gives the same numbers): the eye's data is not rendered at all."""
    from gdbench.core.io import atomic_write, write_json
    from gdbench.core.provenance import code_commit
    from gdbench.metrics.judge.head import fit_head
    from gdbench.metrics.judge.sameness import Templates
    from gdbench.metrics.judge.train import EyeTrainConfig, train_eye
    from gdbench.priors.learned.data import data_key

    t0 = time.perf_counter()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    meta, log, came_from = {"data_key": data_key(eye_data_config(views))}, [], None
    if eye_from is not None and (Path(eye_from) / "templates.safetensors").is_file():
        from gdbench.metrics.judge.judge import Judge

        src = Judge(Path(eye_from))
        came_from = source_of(src, Path(eye_from))
        eye, curves, templates = src.eye, src.curves, src.templates
        meta["data_key"] = src.meta.get("data_key", meta["data_key"])  # the data the eye was trained on
        for name in ("eye.safetensors", "templates.safetensors"):
            blob = (Path(eye_from) / name).read_bytes()
            atomic_write(out / name, lambda f, b=blob: f.write(b))
        prov_from = Path(eye_from) / "provenance.json"
        n_views = json.loads(prov_from.read_text()).get("eye_views") if prov_from.is_file() else None
        t_data = t_eye = 0.0
    else:
        crops, data = eye_crops(views, workers, progress)
        n_views = len(data)
        t_data = time.perf_counter() - t0
        cfg = replace(EyeTrainConfig(), steps=steps, seed=seed)
        if eye_from is not None:  # a folder without templates: its eye alone
            from gdbench.metrics.judge.judge import Judge

            eye_bytes = (Path(eye_from) / "eye.safetensors").read_bytes()
            src = Judge(Path(eye_from))
            eye, came_from = src.eye, source_of(src, Path(eye_from))
            atomic_write(out / "eye.safetensors", lambda f: f.write(eye_bytes))
        else:
            eye, log = train_eye(crops, data.caption, data.azimuth, data.elevation, data.captions, cfg,
                                 progress=progress)  # fmt: skip
            from safetensors.torch import save

            meta |= {"config": json.dumps(eye.config.to_dict()), "train": json.dumps(cfg.to_dict()),
                     "commit": code_commit()}  # fmt: skip
            state = {k: v.detach().to(torch.float16).contiguous() for k, v in eye.state_dict().items()}
            blob = save(state, metadata=meta)
            atomic_write(out / "eye.safetensors", lambda f: f.write(blob))
        t_eye = time.perf_counter() - t0 - t_data
        curves = data_curves(data)
        templates = Templates.from_data(crops, data)
        templates.save(out / "templates.safetensors", {"data_key": meta["data_key"], "commit": code_commit()})
    results, where = fit_results(root)
    x = sheet_features(eye, curves, results, templates)
    fit_on = [i for i, r in enumerate(results) if r.consensus is not None]
    head = fit_head(x[fit_on], [results[i].consensus for i in fit_on], HEAD, seed=seed)
    head_info = {"head": head.to_dict(), "fitted_on": f"{where}: {len(fit_on)} consensus results",
                 "commit": code_commit(), "aspect_curves": curves}  # fmt: skip
    write_json(head_info, out / "head.json")
    prov = {"commit": code_commit(), "eye_data_key": meta["data_key"], "eye_views": n_views, "steps": steps,
            "seed": seed, "eye_from": came_from,
            "final_loss": log[-1]["loss"] if log else None, "seconds_data": round(t_data, 1),
            "seconds_eye": round(t_eye, 1), "seconds": round(time.perf_counter() - t0, 1),
            "threads": torch.get_num_threads()}  # fmt: skip
    write_json(prov, out / "provenance.json")
    return prov


def source_of(judge, folder: Path) -> dict:
    """What ``--eye-from`` took its eye from, for the provenance: the source judge's version and its
    eye file's SHA-256 (12 hex digits), never a path of the machine that built it."""
    import hashlib

    return {
        "judge": judge.version,
        "eye_sha256": hashlib.sha256((folder / "eye.safetensors").read_bytes()).hexdigest()[:12],
    }


def fit_results(root: Path = Path(".")) -> tuple[list, str]:
    """The labelled results the shipped head is fitted on, and what they are: v3's committed sheets
    (batches C-F) and the spent fresh sets' (``SPENT``: docs/judge_fresh.md to judge_fresh8.md).
    A fresh set registered after this judge is never among them."""
    from gdbench.metrics.judge.sheets import labelled_results

    return labelled_results(root, SPENT)[0], "v3 sheets C-F and the sheets of the fresh sets " + ", ".join(SPENT)


SPENT = ("fresh", "fresh2", "fresh3", "fresh4", "fresh5", "fresh6", "fresh7", "fresh8")
"""The fresh sets whose labels the head is fitted on: each was read by the judge before it (the
first by the first judge, the second and third by the second and third, the fourth to the sixth by
the fourth to the sixth, the seventh and eighth by the seventh) and is spent as a test. The eighth
judge is the first fitted on the seventh and eighth."""


def evaluate_v3(folder: Path, out: Path, root: Path = Path(".")) -> list[dict]:
    """The judge in ``folder`` against v3's committed labels: the head refitted leave-kind-out (the
    eye as it is: it never saw a label) and in sample, both against the consensus and against each
    pass. Writes ``out/agreement.csv`` (a row per fit and truth), ``out/by_kind.csv`` and
    ``out/v3_judged.csv`` (every result's labels: run id, batch, caption, the out-of-sample label and
    its confidence, the in-sample one, the raters'); returns the agreement rows."""
    from gdbench.assets.library import PARTS, has_front
    from gdbench.core.io import write_csv
    from gdbench.core.provenance import code_commit
    from gdbench.metrics.judge.evaluate import agreement, in_sample, judge_extra, leave_kind_out, passes
    from gdbench.metrics.judge.head import head_kind
    from gdbench.metrics.judge.judge import Judge
    from gdbench.metrics.judge.sheets import v3_results

    judge = Judge(Path(folder))
    results = v3_results(root)
    x = judge.head_rows(sheet_features(judge.eye, judge.curves, results, judge.templates), [r.caption for r in results])
    kinds = [PARTS[r.caption][0] for r in results]
    fronts = [has_front(r.caption) for r in results]
    extra = judge_extra(judge)
    fits = {"leave-kind-out": leave_kind_out(x, results, kinds, fronts, extra, head_kind(judge.head)),
            "in sample": in_sample(x, results, fronts, extra, head_kind(judge.head))}  # fmt: skip
    rows, commit = [], code_commit()
    for fit_name, judged in fits.items():
        labels = [lab for lab, _ in judged]
        for truth in ("consensus", "rater1", "rater2"):
            idx = [i for i, r in enumerate(results) if (r.consensus if truth == "consensus" else r.labels.get(truth))]
            t = [results[i].consensus if truth == "consensus" else results[i].labels[truth] for i in idx]
            a = agreement(t, [labels[i] for i in idx])
            ok = passes(a)
            rows.append({"fit": fit_name, "truth": truth, **{k: v for k, v in a.items() if k != "confusion"},
                         "passes": ";".join(k for k, v in ok.items() if v),
                         "fails": ";".join(k for k, v in ok.items() if not v),
                         "judge": judge.version, "commit": commit})  # fmt: skip
    loko = fits["leave-kind-out"]
    by_kind = []
    for kind in sorted(set(kinds)):
        idx = [i for i, k in enumerate(kinds) if k == kind and results[i].consensus]
        a = agreement([results[i].consensus for i in idx], [loko[i][0] for i in idx])
        by_kind.append({"kind": kind, "n": a["n"], "agree": a["agree"], "kappa_janus": a["kappa_janus"],
                        "confusion": str(a["confusion"]), "judge": judge.version, "commit": commit})  # fmt: skip
    per = [{"batch": r.batch, "number": r.number, "run_id": r.run_id, "caption": r.caption,
            "judge_loko": loko[i][0], "confidence_loko": round(loko[i][1], 4),
            "judge_in_sample": fits["in sample"][i][0],
            "rater1": r.labels.get("rater1"), "rater2": r.labels.get("rater2"), "consensus": r.consensus or "",
            "judge": judge.version, "commit": commit}
           for i, r in enumerate(results)]  # fmt: skip
    out = Path(out)
    write_csv(rows, out / "agreement.csv")
    write_csv(by_kind, out / "by_kind.csv")
    write_csv(per, out / "v3_judged.csv")
    return rows


V3_PRIMARY = (("gd", "gd-no-sn"), ("gd", "gd-redraw-step"), ("gd", "gd-pose-locked"))
"""v3's primary family: gd against each control on the share of results labelled Janus."""


def reread_v3(judged_csv: Path, out: Path, root: Path = Path(".")) -> list[dict]:
    """v3's three primary rows re-read: the same test (the prompt as the unit, the exact sign-flip
    p, Holm over the three, margin 0.05) on the raters' ``label_janus`` (the share of the two passes
    calling a result Janus: the registered outcome, recomputed here as a check) and on the judge's
    ``judge_janus`` from ``judged_csv`` (``evaluate_v3``'s: out of sample, leave-kind-out, and in
    sample). A re-reading, not a registration: the raters' rows stay the registered ones."""
    import csv

    import numpy as np

    from gdbench.core.io import write_csv
    from gdbench.experiments.claims import across_prompts
    from gdbench.experiments.stats import holm
    from gdbench.metrics.agreement import JANUS as janus

    arm = {}
    for b in ("C", "D", "E", "F"):
        for k in json.loads((Path(root) / f"docs/results/v3/sheets/{b}_key.json").read_text()).values():
            parts = Path(k["run"]).parts  # <batch>/runs/cells/<group>/janus/<prompt>/<preset>/seed<k>
            arm[(b, k["run_id"])] = (k["caption"], parts[-2], int(parts[-1].removeprefix("seed")))
    values: dict[str, dict] = {"raters": {}, "judge (leave-kind-out)": {}, "judge (in sample)": {}}
    for r in csv.DictReader(open(judged_csv)):
        key = arm[(r["batch"], r["run_id"])]
        values["raters"][key] = (float(r["rater1"] in janus) + float(r["rater2"] in janus)) / 2
        values["judge (leave-kind-out)"][key] = float(r["judge_loko"] in janus)
        values["judge (in sample)"][key] = float(r["judge_in_sample"] in janus)
    from gdbench.core.provenance import code_commit

    rows, commit = [], code_commit()
    for reader, v in values.items():
        family = []
        for a, b in V3_PRIMARY:
            keys = sorted((p, s) for (p, arm_, s) in v if arm_ == a and (p, b, s) in v)
            d = np.array([v[(p, a, s)] - v[(p, b, s)] for p, s in keys])
            res = across_prompts(keys, d, 0.05, test="signflip")
            family.append({"reader": reader, "comparison": f"{a} vs {b}", "pairs": len(keys),
                           "share_a": float(np.mean([v[(p, a, s)] for p, s in keys])),
                           "share_b": float(np.mean([v[(p, b, s)] for p, s in keys])), **res})  # fmt: skip
        for row, p in zip(family, holm([r["p_prompts"] for r in family])):
            row["p_prompts_holm"] = p
            row["commit"] = commit
            hi = row["prompt_ci_high"]
            row["verdict"] = ("holds" if p < 0.05 and hi < 0 else "no effect beyond +-0.05"
                              if row["p_prompts_equivalence"] < 0.05 else "undecided")  # fmt: skip
            rows.append(row)
    write_csv(rows, Path(out) / "v3_reread.csv")
    return rows


def main(argv=None) -> int:
    """``python -m gdbench.experiments.judge_build evaluate [--judge DIR] [--out DIR]``: the judge
    against v3's committed labels (``evaluate_v3``) and v3's primary rows re-read (``reread_v3``)."""
    import argparse

    from gdbench.metrics.judge.judge import WEIGHTS

    ap = argparse.ArgumentParser(prog="python -m gdbench.experiments.judge_build", description=main.__doc__)
    ap.add_argument("what", choices=["evaluate"])
    ap.add_argument("--judge", type=Path, default=WEIGHTS, help="the judge's folder (default: the shipped one)")
    ap.add_argument("--out", type=Path, default=Path("docs/results/judge"))
    args = ap.parse_args(argv)
    for r in evaluate_v3(args.judge, args.out):
        print(f"{r['fit']:15s} {r['truth']:9s} {r['n']:4d} results: kappa {r['kappa_janus']:.2f} (Janus split), "
              f"{r['kappa_four']:.2f} (four classes); fails: {r['fails'] or 'none'}")  # fmt: skip
    for r in reread_v3(args.out / "v3_judged.csv", args.out):
        print(f"{r['reader']:24s} {r['comparison']:20s} {r['prompt_mean_diff']:+.3f} "
              f"[{r['prompt_ci_low']:+.3f}, {r['prompt_ci_high']:+.3f}] {r['verdict']}")  # fmt: skip
    print(f"-> {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
