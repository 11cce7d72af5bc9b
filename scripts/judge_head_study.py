"""What carries to a kind whose labels no head saw: the judge's regression head over four sets of
its numbers, fitted with and without the ground truth's fixtures (sharp, or blurred as a result is
soft), and on the fixtures alone (no label at all), read three ways on the labelled sheets. As in
``evaluate.leave_kind_out``, a held-out kind's labelled results are unseen but its fixtures (made
from the ground truth, not from labels) stay in every fit, and the 200 numbers read each result
against its own asset's reference fixtures.

    python scripts/judge_head_study.py --out docs/results/judge/head_study [--judge DIR]

- **v3 leave-kind-out** (the issue's bar, as ``judge_build evaluate`` reads it): every kind held out
  in turn, the head fitted on v3's other kinds' consensus results and the fixtures;
- **fresh sets leave-kind-out**: the same over the committed fresh sets (``SETS``), the head fitted
  on v3's and the sets' other kinds;
- **leave-set-out**: each fresh set judged by a head fitted on v3's and the other sets' results
  (what a fresh set measures: new results of kinds the head has seen).

``end_on.csv``: how the consensus labels the results the eye reads end-on, mostly the back or mostly
the front, for the fish and the teapot and for the other kinds.

A fixtures-only head is fitted once on the fixtures and reads every result: it never saw a label,
so each of its readings is out of sample for labels. The trees (the shipped head) are not refitted
here (five forests per held-out fold take hours on two cores): their rows are in each judge's own
``agreement.csv`` and ``leave_set_out.csv``. Six views each, from the committed sheets; the eye,
outline and templates of ``--judge`` (default the shipped judge).
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
import torch.nn.functional as F

SETS = ("fresh", "fresh2", "fresh3", "fresh4", "fresh5", "fresh6", "fresh7")
"""The fresh sets read: the seven spent by the seventh judge (the eighth's labels stay out)."""
COLOUR = (33, 34, 35, 36, 43, 44, 45, 46)
"""The look's colour numbers (spread of r, g, b and saturation, their means and spreads): the
numbers that name an asset's colours, and so its kind."""
FEATURES = {
    "eye, outline, sameness (30)": list(range(30)),
    "the 50": list(range(50)),
    "the 50 less colour (42)": [i for i in range(50) if i not in COLOUR],
    "the 200 (against the references)": list(range(200)),
}
BLUR_PX = 4.0
"""The blurred fixtures' Gaussian blur (pixels of the 128 px views): about a result's softness."""


def blur(views: torch.Tensor, sigma: float) -> torch.Tensor:
    """[V, H, W, 3] uint8 views blurred by a Gaussian of ``sigma`` pixels (edges replicated)."""
    x = views.permute(0, 3, 1, 2).float() / 255
    r = int(3 * sigma) + 1
    t = torch.arange(-r, r + 1, dtype=torch.float32)
    k = torch.exp(-(t**2) / (2 * sigma**2))
    k = k / k.sum()
    x = F.pad(x, (r, r, r, r), mode="replicate")
    x = F.conv2d(x, k.view(1, 1, 1, -1).repeat(3, 1, 1, 1), groups=3)
    x = F.conv2d(x, k.view(1, 1, -1, 1).repeat(3, 1, 1, 1), groups=3)
    return (x.clamp(0, 1) * 255).round().byte().permute(0, 2, 3, 1)


def blurred_fixture_rows(judge, names: list[str]) -> torch.Tensor:
    """[N, 50] the fixtures ``names`` ("caption/kind") read from their six views blurred by ``BLUR_PX``."""
    from gdbench.metrics.judge.fixtures import fixture_views
    from gdbench.metrics.judge.reading import result_features
    from gdbench.metrics.judge.sameness import SHEET

    az, rows = torch.tensor(SHEET), []
    for i, name in enumerate(names):
        caption, kind = name.rsplit("/", 1)
        views = blur(fixture_views(caption, kind), BLUR_PX)
        rows.append(result_features(judge.eye, judge.curves, views, az, caption, judge.templates)[0][:50])
        if (i + 1) % 50 == 0:
            print(f"  blurred fixtures: {i + 1}/{len(names)}", flush=True)
    return torch.stack(rows)


HARD = ("fish", "teapot")
"""The two kinds that most of the seventh judge's leave-kind-out misses on v3 are (docs/scoring.md)."""


def end_on_rows(x: torch.Tensor, truth: list, kinds: list[str], source: list[str], version: str,
                commit: str) -> list[dict]:  # fmt: skip
    """How the consensus labels results that the eye reads end-on (``end_on`` above 0.6) with the
    front's share under 0.35 (mostly the back) or at least 0.5 (mostly the front), for ``HARD``'s
    kinds and the others, over v3 and the fresh sets: what a head fitted on the other kinds learns
    such a reading means."""
    from collections import Counter

    from gdbench.metrics.agreement import LABELS
    from gdbench.metrics.judge.reading import FEATURES

    end_on, front = FEATURES.index("end_on"), FEATURES.index("front")
    reads = {"end-on, mostly the back": lambda v: v[end_on] > 0.6 and v[front] < 0.35,
             "end-on, mostly the front": lambda v: v[end_on] > 0.6 and v[front] >= 0.5}  # fmt: skip
    out = []
    for read, ok in reads.items():
        for group in ("fish and teapot", "the other kinds"):
            idx = [i for i in range(len(truth)) if truth[i] and (kinds[i] in HARD) == (group != "the other kinds")
                   and ok(x[i].tolist())]  # fmt: skip
            n = Counter(truth[i] for i in idx)
            out.append({"reading": read, "kinds": group, "results": len(idx), **{c: n[c] for c in LABELS},
                        "of_v3": sum(source[i] == "v3" for i in idx), "judge": version, "commit": commit})  # fmt: skip
    return out


def main(argv=None) -> int:
    from gdbench.assets.library import PARTS, has_front
    from gdbench.core.io import write_csv
    from gdbench.core.provenance import code_commit
    from gdbench.experiments.judge_build import sheet_features
    from gdbench.metrics.judge.evaluate import agreement, janus, leave_kind_out
    from gdbench.metrics.judge.head import decide
    from gdbench.metrics.judge.head import fit as fit_linear
    from gdbench.metrics.judge.judge import load_judge
    from gdbench.metrics.judge.reference import against
    from gdbench.metrics.judge.sheets import labelled_results

    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--judge", type=Path, default=None, help="a judge folder (default: the shipped judge)")
    ap.add_argument("--out", type=Path, required=True, help="where study.csv and end_on.csv go")
    args = ap.parse_args(argv)
    judge, commit = load_judge(str(args.judge) if args.judge else None), code_commit()
    if judge.references is None or judge.head_info.get("fixture_rows") is None:
        ap.error(
            "--judge: expected a judge with fixture rows and references: the seventh "
            "(judge.with_head(SEVENTH_HEAD, DIR) makes its folder)"
        )
    results, source = labelled_results(sets=SETS)
    captions = [r.caption for r in results]
    # the 50 numbers the seventh's references hold (the readings now give the front's seven after them)
    x = against(sheet_features(judge.eye, judge.curves, results, judge.templates)[:, :50], captions,
                judge.references)  # fmt: skip
    truth, kinds = [r.consensus for r in results], [PARTS[c][0] for c in captions]
    fronts = [has_front(c) for c in captions]
    write_csv(end_on_rows(x, truth, kinds, source, judge.version, commit), args.out / "end_on.csv")
    rows = judge.head_info["fixture_rows"]
    names, fy = list(rows["names"]), list(rows["labels"])
    fcaps = [n.rsplit("/", 1)[0] for n in names]
    sharp = against(torch.tensor(rows["features"], dtype=torch.float32), fcaps, judge.references)
    soft = against(blurred_fixture_rows(judge, names), fcaps, judge.references)
    fixtures = {"none": (sharp[:0], []), "sharp": (sharp, fy), f"blurred {BLUR_PX:g} px": (soft, fy)}

    def judged(p: torch.Tensor, idx: list[int]) -> list[str]:
        return [decide(p[j], x[i], fronts[i])[0] for j, i in enumerate(idx)]

    def fitted(fit_on: list[int], cols: list[int], fix: tuple):
        return fit_linear(torch.cat([x[fit_on][:, cols], fix[0][:, cols]]), [truth[i] for i in fit_on] + fix[1])

    def leave_set_out(cols: list[int], fix: tuple) -> list[str | None]:
        """Each fresh result read by a head fitted on the consensus results of v3 and the other
        sets, and the fixtures ``fix``."""
        label: list[str | None] = [None] * len(results)
        for s in SETS:
            mine = [i for i in fresh if source[i] == s]
            head = fitted([i for i in range(len(results)) if truth[i] and source[i] != s], cols, fix)
            for i, lab in zip(mine, judged(head.probabilities(x[mine][:, cols]), mine)):
                label[i] = lab
        return label

    def by_kind(idx: list[int], cols: list[int], fix: tuple) -> list[str | None]:
        """Each result of ``idx`` read leave-kind-out among the results ``idx`` (``evaluate``'s
        folds: a head per kind, fitted on the other kinds' consensus results and the fixtures)."""
        read = leave_kind_out(x[idx][:, cols], [results[i] for i in idx], [kinds[i] for i in idx],
                              [fronts[i] for i in idx], (fix[0][:, cols], fix[1]), "linear")  # fmt: skip
        label: list[str | None] = [None] * len(results)
        for i, (lab, _) in zip(idx, read):
            label[i] = lab
        return label

    v3 = [i for i in range(len(results)) if source[i] == "v3"]
    fresh = [i for i in range(len(results)) if source[i] != "v3"]

    def janus_misses(label: list, idx: list[int], kind: str) -> int:
        return sum(janus(label[i]) != janus(truth[i]) for i in idx if kinds[i] == kind)

    out = []
    for fname, cols in FEATURES.items():
        for fixname, fix in fixtures.items():
            reads = {
                "v3 leave-kind-out": (by_kind(v3, cols, fix), v3),
                "fresh sets leave-kind-out": (by_kind(list(range(len(results))), cols, fix), fresh),
                "leave-set-out": (leave_set_out(cols, fix), fresh),
            }
            if fixname != "none":  # the fixtures alone: one head, no label
                head = fit_linear(fix[0][:, cols], fix[1])
                alone = judged(head.probabilities(x[:, cols]), list(range(len(results))))
                reads["fixtures only, v3"], reads["fixtures only, fresh sets"] = (alone, v3), (alone, fresh)
            for read, (label, idx) in reads.items():
                idx = [i for i in idx if truth[i]]
                a = agreement([truth[i] for i in idx], [label[i] for i in idx])
                worst = sorted({kinds[i] for i in idx}, key=lambda k: (-janus_misses(label, idx, k), k))[:3]
                out.append({"head": "linear", "features": fname, "fixtures": fixname, "read": read,
                            **{k: v for k, v in a.items() if k != "confusion"},
                            "worst_kinds_janus": ";".join(worst), "judge": judge.version,
                            "commit": commit})  # fmt: skip
                print(f"{fname:34s} {fixname:14s} {read:26s} n {a['n']:4d} kappa {a['kappa_janus']:.2f} (Janus) "
                      f"{a['kappa_four']:.2f} (four) blob {a['recall_blob']:.2f} fine {a['recall_fine']:.2f}",
                      flush=True)  # fmt: skip
    write_csv(out, args.out / "study.csv")
    print(f"-> {args.out / 'study.csv'}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
