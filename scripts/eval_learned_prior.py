"""The learned prior against its oracles: the tables and figures of docs/learned_prior.md.

    python scripts/eval_learned_prior.py --out docs/results/learned_prior --figures docs/figures \
        --runs runs/prior-uniform runs/prior-front

Writes, with the code commit in every file: loss.csv summary (where each curve flattens),
camera.csv (the estimates' PSNR with the right camera and with its azimuth turned 90 and 180 deg),
denoising_error.csv (the model against the exact posterior mean of its training views, per
noise level), off_grid.csv (learned vs the runtime empirical prior between the bank's cameras),
samples.csv (DDIM samples matched to ground-truth renders), mechanism.csv (structured vs
independent noise, per prior), guided_error.csv (with --students: each one-call model against its
teacher's two-call guidance, per noise level), summary.json; figures learned_prior_{loss,denoising,off_grid,
samples_uniform,samples_front,mechanism}.png. About 10 minutes on 2 cores.
"""

from __future__ import annotations

import argparse
import csv
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def write_csv(path: Path, rows: list[dict], commit: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(rows[0]) + ["commit"]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, names)
        w.writeheader()
        for r in rows:
            w.writerow({**{k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in r.items()}, "commit": commit})


def flattening(log_csv: Path) -> dict:
    """Where a loss curve flattens: the first step whose running mean (a tenth of the run) is within
    5% of the final one, and the final loss."""
    rows = list(csv.DictReader(open(log_csv)))
    steps = np.array([float(r["step"]) for r in rows])
    loss = np.array([float(r["loss"]) for r in rows])
    k = max(1, len(loss) // 10)
    smooth = np.convolve(loss, np.ones(k) / k, mode="valid")
    final = smooth[-1]
    at = steps[k - 1 :][np.argmax(smooth <= 1.05 * final)]
    return {"final_loss": float(final), "flat_at_step": int(at), "steps": int(steps[-1]),
            "seconds": float(rows[-1]["seconds"])}  # fmt: skip


def plot_losses(runs: dict[str, Path], out: Path) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.6))
    for name, run in runs.items():
        rows = list(csv.DictReader(open(run / "loss.csv")))
        s = np.array([float(r["step"]) for r in rows])
        v = np.array([float(r["loss"]) for r in rows])
        k = max(1, len(v) // 20)
        ax.plot(s, v, lw=0.5, alpha=0.35)
        ax.plot(s[k - 1 :], np.convolve(v, np.ones(k) / k, mode="valid"), lw=1.6, label=f"{name} (running mean)")
    ax.set(xlabel="step (batch 32)", ylabel="loss (v MSE)", yscale="log", title="learned prior: training loss")
    ax.legend()
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def plot_denoising(rows: list[dict], out: Path) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 3.8))
    for model, style in (("uniform", "-"), ("front", "--")):
        sel = [r for r in rows if r["model"] == model]
        if not sel:
            continue
        sig = sorted({r["sigma"] for r in sel})
        mean = lambda k, sel=sel, sig=sig: [np.mean([r[k] for r in sel if r["sigma"] == s]) for s in sig]  # noqa: E731
        ax.plot(sig, mean("mse_learned_exact"), style, marker="o", label=f"{model}: learned vs exact posterior mean")
        ax.plot(sig, mean("mse_exact_x0"), style, color="grey", lw=1, label=f"{model}: exact posterior vs clean view")
    ax.set(xscale="log", yscale="log", xlabel="sigma (VE)", ylabel="MSE (images in [-1, 1])",
           title="denoising error against the optimal denoiser of the training views")  # fmt: skip
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def show(img) -> np.ndarray:
    return ((img.clamp(-1, 1) + 1) / 2).numpy()


def plot_off_grid(examples: dict, out: Path) -> None:
    import matplotlib.pyplot as plt

    keys = list(examples)
    fig, axes = plt.subplots(len(keys), 4, figsize=(6, 1.6 * len(keys)))
    for i, k in enumerate(keys):
        for j, (img, name) in enumerate(zip(examples[k], ("truth", "noisy", "empirical", "learned"))):
            ax = axes[i, j]
            ax.imshow(show(img), interpolation="nearest")
            ax.set_xticks([]), ax.set_yticks([])
            if i == 0:
                ax.set_title(name, fontsize=8)
            if j == 0:
                ax.set_ylabel(f"{k[0][2:]}\nsigma {k[1]:g}", fontsize=7)
    fig.suptitle("between the bank's cameras (az +2.5, el +-10, fovy off-grid); learned: guidance 1", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=130)
    plt.close(fig)


def plot_samples(grids: dict[str, torch.Tensor], captions, views, out: Path) -> None:
    """Rows: captions; columns: asked azimuths x the first 3 seeds; one panel per camera mode."""
    import matplotlib.pyplot as plt

    modes = list(grids)
    C = len(captions)  # the panel's aspect is the sheet's: 12 thumbnails wide, C high (38 for the world model)
    fig, axes = plt.subplots(1, len(modes), figsize=(6.5 * len(modes), max(6.6, 0.55 * C * 6.5 / 12 + 1.0)))
    for ax, mode in zip(np.atleast_1d(axes), modes):
        g = grids[mode][:, :, :3]  # [C, V, S, h, w, 3]
        C, V, S, h, w, _ = g.shape
        sheet = g.permute(0, 3, 1, 2, 4, 5).reshape(C * h, V * S * w, 3)
        ax.imshow(show(sheet), interpolation="nearest")
        ax.set_yticks([h * (i + 0.5) for i in range(C)], [c[2:] for c in captions], fontsize=8)
        ax.set_xticks([w * S * (i + 0.5) for i in range(V)], [f"az {a:g}" for a in views], fontsize=8)
        ax.set_title(mode, fontsize=9)
    fig.tight_layout()
    fig.savefig(out, dpi=110)
    plt.close(fig)


def plot_mechanism(summary: list[dict], out: Path) -> None:
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 0.35 * len(summary) + 1.4), sharey=True)
    y = np.arange(len(summary))
    for ax, (k, lo, hi, ref, label) in zip(axes, (
        ("ratio", "lo", "hi", 1.0, "MSE between the views' estimates (warped):\nstructured / independent noise"),
        ("corr_diff", "corr_lo", "corr_hi", 0.0, "correlation of the views' departures from the truth:\n"
         "structured - independent"),
    )):  # fmt: skip
        v = np.array([s[k] for s in summary])
        err = np.array([[s[k] - s[lo], s[hi] - s[k]] for s in summary]).T
        ax.errorbar(v, y, xerr=err, fmt="o")
        ax.axvline(ref, color="grey", lw=1)
        ax.set_xlabel(label + " (95% CI)", fontsize=8)
    axes[0].set_yticks(y, [f"{s['prior']}, {s['separation']:g} deg, sigma {s['sigma']:g}, ratio {s['noise_ratio']:g}"
                           for s in summary],
                       fontsize=7)  # fmt: skip
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)


def main(argv=None) -> int:
    import matplotlib

    matplotlib.use("Agg")
    from gdbench.core.provenance import code_commit
    from gdbench.priors.empirical import EmpiricalPrior, bank_config_for
    from gdbench.priors.learned.data import DataConfig, load_dataset
    from gdbench.priors.learned.evaluation import (
        denoising_error,
        mechanism,
        off_grid,
        paired_ratio,
        reference_set,
        sample_scores,
    )
    from gdbench.priors.learned.prior import LearnedPrior

    p = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    p.add_argument("--uniform", default="uniform", help="the uniform model (name or path)")
    p.add_argument("--front", default="front", help="the front-biased model (name or path)")
    p.add_argument("--runs", nargs="*", default=[], type=Path, help="train-prior run folders (their loss.csv)")
    p.add_argument("--out", type=Path, default=Path("docs/results/learned_prior"))
    p.add_argument("--figures", type=Path, default=Path("docs/figures"))
    p.add_argument("--separations", nargs="*", type=float, default=[30.0, 5.0],
                   help="azimuth separations (deg) of the mechanism's view pairs")  # fmt: skip
    p.add_argument("--students", nargs="*", default=[],
                   help="distilled one-call models of --uniform and --front, in that order (a name or path "
                        "each; their guided error against the teacher, and the samples check beside the "
                        "teachers')")  # fmt: skip
    p.add_argument("--quick", action="store_true", help="fewer queries and draws (a smoke run)")
    parts_help = "parts to run: loss camera denoising off_grid samples mechanism distillation (default: all)"
    p.add_argument("--only", nargs="*", default=[], help=parts_help)
    a = p.parse_args(argv)
    parts = set(a.only) or {"loss", "camera", "denoising", "off_grid", "samples", "mechanism", "distillation"}
    if len(a.students) > 2:
        p.error(f"--students: expected at most two (the uniform model's, then the front one's), got {len(a.students)}")
    if "distillation" in set(a.only) and not a.students:
        p.error("--only distillation: needs --students (the one-call models to check against their teachers)")
    torch.manual_seed(0)
    commit = code_commit()
    a.out.mkdir(parents=True, exist_ok=True)
    a.figures.mkdir(parents=True, exist_ok=True)
    summary: dict = {"commit": commit, "time": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())}
    models = {"uniform": a.uniform, "front": a.front}
    from gdbench.priors.learned.prior import load_model

    students = dict(zip(("uniform", "front"), a.students))
    from gdbench.priors.learned.prior import model_path

    scale_of = {}  # each student's distilled scale; its teacher must be the model given for its name
    for name, m in students.items():
        train = json.loads(load_model(m)[1]["train"])
        if "teacher" not in train:
            p.error(f"--students: {m} is not distilled (no teacher in its metadata)")
        if Path(train["teacher"]).resolve() != model_path(models[name]).resolve():
            p.error(f"--students: {m} was distilled from {train['teacher']}, not from --{name} {models[name]}")
        scale_of[f"{name}-1call"] = float(train["teacher_guidance"])
    summary["models"] = {k: {m: load_model(v)[1].get(m) for m in ("commit", "steps", "final_loss")}
                         for k, v in (models | {f"{k}-1call": v for k, v in students.items()}).items()}  # fmt: skip
    q = 2 if a.quick else 1
    t0 = time.perf_counter()

    if "loss" in parts and a.runs:
        runs = {r.name.replace("prior-", ""): r for r in a.runs}
        summary["loss"] = {k: flattening(r / "loss.csv") for k, r in runs.items()}
        plot_losses(runs, a.figures / "learned_prior_loss.png")

    if "camera" in parts:
        from gdbench.priors.learned.evaluation import camera_sensitivity

        rows = []
        for name, m in models.items():
            prior = LearnedPrior(m, guidance_scale=1.0, view_mode="window")
            rows += [{"model": name, **r} for r in camera_sensitivity(prior, list(prior.captions))]
        write_csv(a.out / "camera.csv", rows, commit)
        summary["camera"] = {
            f"{m} sigma {s:g}": {f"offset {o:g}": float(np.mean([r["psnr"] for r in rows if r["model"] == m
                                 and r["sigma"] == s and r["offset_deg"] == o])) for o in (0.0, 90.0, 180.0)}
            for m in models for s in (2.0, 5.0, 10.0)
        }  # fmt: skip
        print(f"camera done ({time.perf_counter() - t0:.0f} s)")

    if "denoising" in parts:
        rows = []
        for name, m in models.items():
            prior = LearnedPrior(m, guidance_scale=1.0, view_mode="none")
            data = load_dataset(DataConfig.from_dict(json.loads(prior.meta["train"])["data"]))  # its own views
            sig = [0.05, 0.1, 0.2, 0.5, 1.0, 2.0, 5.0, 10.0]
            rows += [{"model": name, **r} for r in denoising_error(prior, data, sig, queries=48 // q)]
        write_csv(a.out / "denoising_error.csv", rows, commit)
        plot_denoising(rows, a.figures / "learned_prior_denoising.png")
        summary["denoising"] = {
            f"{m} sigma {s:g}": {k: float(np.mean([r[k] for r in rows if r["model"] == m and r["sigma"] == s]))
                                 for k in ("mse_learned_exact", "mse_exact_x0", "mse_learned_x0")}
            for m in models for s in sorted({r["sigma"] for r in rows})
        }  # fmt: skip
        print(f"denoising error done ({time.perf_counter() - t0:.0f} s)")

    captions = list(LearnedPrior(a.uniform).captions)
    if "off_grid" in parts:
        empirical = EmpiricalPrior(view_mode="window", bank_config=bank_config_for(64, (40.0, 70.0)))
        rows, pick = [], {}
        for gs in (1.0, 3.0):  # the model's own posterior mean, and what the trainer queries by default
            learned = LearnedPrior(a.uniform, view_mode="window", guidance_scale=gs)
            r, ex = off_grid(learned, empirical, captions, [0.5, 2.0, 8.0])
            for x in r:
                x["prior"] = x["prior"] if x["prior"] == "empirical" else f"learned, guidance {gs:g}"
            rows += [x for x in r if gs == 1.0 or x["prior"] != "empirical"]
            if gs == 1.0:
                pick = {k: v for k, v in ex.items() if k[0] in ("a yellow duck", "a lego figure")}
        write_csv(a.out / "off_grid.csv", rows, commit)
        plot_off_grid(pick, a.figures / "learned_prior_off_grid.png")
        names = sorted({r["prior"] for r in rows})
        summary["off_grid"] = {
            f"{pr} sigma {s:g}": {k: float(np.mean([r[k] for r in rows if r["prior"] == pr and r["sigma"] == s]))
                                  for k in ("psnr", "sharpness")}
            for pr in names for s in (0.5, 2.0, 8.0)
        }  # fmt: skip
        print(f"off-grid done ({time.perf_counter() - t0:.0f} s)")

    if "distillation" in parts and students:
        from gdbench.priors.learned.evaluation import guided_error

        rows = []
        for name, m in students.items():
            scale = scale_of[f"{name}-1call"]
            one = LearnedPrior(m, guidance_scale=scale, view_mode="window")
            two = LearnedPrior(models[name], guidance_scale=scale, view_mode="window")
            unguided = LearnedPrior(models[name], guidance_scale=1.0, view_mode="window")
            rows += [{"model": f"{name}-1call", "guidance": scale, **r}
                     for r in guided_error(one, two, unguided, list(two.captions))]  # fmt: skip
        write_csv(a.out / "guided_error.csv", rows, commit)
        keys = ("mse_student_teacher", "mse_guided_unguided", "psnr_student", "psnr_teacher")
        summary["distillation"] = {
            f"{m} sigma {s:g}": {k: float(np.mean([r[k] for r in rows if r["model"] == m and r["sigma"] == s]))
                                 for k in keys}
            for m in sorted({r["model"] for r in rows}) for s in sorted({r["sigma"] for r in rows})
        }  # fmt: skip
        print(f"distillation done ({time.perf_counter() - t0:.0f} s)")

    if "samples" in parts:
        refs, ref_az = reference_set(captions)
        rows, views = [], (0.0, 90.0, 180.0, -90.0)
        summary["samples"] = {}
        for name, m in (models | {f"{k}-1call": v for k, v in students.items()}).items():
            prior = LearnedPrior(m, view_mode="window", guidance_scale=scale_of.get(name, 3.0))
            grids = {}
            for camera in (True, False):
                r, grid = sample_scores(prior, refs, ref_az, views=views, seeds=8 // q, camera=camera)
                r = [{**x, "held_out": x["caption"] in prior.held_out} for x in r]
                rows += [{"model": name, **x} for x in r]
                mode = "camera given" if camera else "camera dropped (view prompting none)"
                grids[mode] = grid
                share = lambda k, r=r: float(np.mean([x[k] for x in r]))  # noqa: E731
                back = [x for x in r if abs(x["asked_azimuth"]) == 180.0]
                summary["samples"][f"{name}, {mode}"] = {
                    "caption_ok": share("caption_ok"), "variant_ok": share("variant_ok"),
                    "azimuth_ok": share("azimuth_ok"), "front": share("front"), "back": share("back"),
                    "front_where_back_asked": float(np.mean([x["front"] for x in back])), "n": len(r),
                }  # fmt: skip
                if prior.held_out:  # the generalisation check: the same rates on the held-out combinations
                    held = [x for x in r if x["held_out"]]
                    summary["samples"][f"{name}, {mode}, held out"] = {
                        k: float(np.mean([x[k] for x in held])) for k in ("caption_ok", "variant_ok", "azimuth_ok")
                    } | {"n": len(held)}
            plot_samples(grids, captions, views, a.figures / f"learned_prior_samples_{name}.png")
        write_csv(a.out / "samples.csv", rows, commit)
        by = {}
        for x in rows:  # per model, caption and camera mode: the rates a caption's row of the table reads
            by.setdefault((x["model"], x["caption"], x["camera"], x["held_out"]), []).append(x)
        write_csv(a.out / "samples_by_caption.csv", [
            {"model": m, "caption": c, "camera": cam, "held_out": h, "n": len(v),
             **{k: float(np.mean([x[k] for x in v])) for k in ("caption_ok", "variant_ok", "azimuth_ok")}}
            for (m, c, cam, h), v in by.items()], commit)  # fmt: skip
        print(f"samples done ({time.perf_counter() - t0:.0f} s)")

    if "mechanism" in parts:
        emp_cfg = bank_config_for(64, (40.0, 70.0))
        priors = {
            "learned uniform, camera given": LearnedPrior(a.uniform, view_mode="window"),
            "learned uniform, camera dropped": LearnedPrior(a.uniform, view_mode="none"),
            "learned front, camera dropped": LearnedPrior(a.front, view_mode="none"),
            "empirical, window": EmpiricalPrior(view_mode="window", bank_config=emp_cfg),
            "empirical, none": EmpiricalPrior(view_mode="none", bank_config=emp_cfg),
        }
        rows, summ = [], []
        for name, prior in priors.items():
            for sep in a.separations:
                r = mechanism(prior, captions, draws=16 // q, separation=sep)
                rows += [{"prior": name, **x} for x in r]
                for s in sorted({x["sigma"] for x in r}):
                    for ratio in sorted({x["ratio"] for x in r}):
                        sel = [x for x in r if x["sigma"] == s and x["ratio"] == ratio]
                        noise = float(np.mean([x["noise_corr"] for x in sel]))
                        summ.append({"prior": name, "separation": sep, "sigma": s, "noise_ratio": ratio,
                                     "noise_corr": noise, **paired_ratio(sel)})  # fmt: skip
        write_csv(a.out / "mechanism.csv", rows, commit)
        summary["mechanism"] = summ
        plot_mechanism(summ, a.figures / "learned_prior_mechanism.png")
        print(f"mechanism done ({time.perf_counter() - t0:.0f} s)")

    summary["seconds"] = time.perf_counter() - t0
    old = json.loads((a.out / "summary.json").read_text()) if (a.out / "summary.json").is_file() else {}
    (a.out / "summary.json").write_text(json.dumps(old | summary, indent=1))
    print(json.dumps(summary, indent=1)[:4000])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
