"""The judge judged against eyes: leave-kind-out on the committed labelled sheets, and in sample.

For every kind (the second column of ``gdbench prompts``) in turn, the head is fitted on the
consensus results (both passes give the same label) of every other kind and labels the held-out
kind's results; the eye, trained on asset renders alone, is the same throughout. The agreement
with the consensus is Cohen's kappa on the Janus split (front_everywhere or second_face against
the rest) and over the four classes, and the recall of each class; each rater pass's own agreement
with the judge is reported beside it.
"""

from __future__ import annotations

from collections import Counter

import torch
from torch import Tensor

from gdbench.metrics.agreement import JANUS, LABELS
from gdbench.metrics.judge.head import decide, fit_head

THRESHOLDS = {"kappa_janus": 0.8, "kappa_four": 0.7, "recall_front_everywhere": 0.7, "recall_blob": 0.7,
              "recall_fine": 0.7}  # fmt: skip
"""The issue's bar for the judge out of sample."""


def janus(label: str) -> int:
    return int(label in JANUS)


def agreement(truth: list[str], judged: list[str]) -> dict:
    """Kappas, recalls and counts of ``judged`` against ``truth`` (rule labels)."""
    from gdbench.metrics.agreement import cohen_kappa

    out = {
        "n": len(truth),
        "kappa_janus": cohen_kappa([str(janus(t)) for t in truth], [str(janus(j)) for j in judged], labels=("0", "1")),
        "kappa_four": cohen_kappa(truth, judged, labels=LABELS),
        "agree": sum(t == j for t, j in zip(truth, judged)) / max(len(truth), 1),
    }
    for c in LABELS:
        mine = [j == c for t, j in zip(truth, judged) if t == c]
        out[f"recall_{c}"] = sum(mine) / len(mine) if mine else None
        out[f"n_{c}"] = len(mine)
    out["confusion"] = {t: dict(Counter(j for tt, j in zip(truth, judged) if tt == t)) for t in LABELS}
    return out


def passes(row: dict) -> dict[str, bool]:
    """Which of ``THRESHOLDS`` an agreement row meets."""
    return {k: row.get(k) is not None and row[k] >= v for k, v in THRESHOLDS.items()}


def leave_kind_out(features: Tensor, results: list, kinds: list[str], fronts: list[bool],
                   extra: tuple[Tensor, list[str]] | None = None,
                   head: str = "linear") -> list[tuple[str, float]]:  # fmt: skip
    """Each result's (label, confidence) from a head of kind ``head`` (``head.HEADS``) fitted without
    its kind's results (only consensus results are fitted on), with the ``extra`` rows (features,
    labels: the fixtures made from the ground truth, ``fixtures.fixture_rows``) in every fit."""
    out: list[tuple[str, float] | None] = [None] * len(results)
    consensus = [r.consensus for r in results]
    for kind in sorted(set(kinds)):
        fit_on = [i for i, r in enumerate(results) if kinds[i] != kind and consensus[i] is not None]
        fitted = _fit(features[fit_on], [consensus[i] for i in fit_on], extra, head)
        mine = [i for i in range(len(results)) if kinds[i] == kind]
        p = fitted.probabilities(features[mine])
        for j, i in enumerate(mine):
            out[i] = decide(p[j], features[i], fronts[i])
    return out  # type: ignore[return-value]


def in_sample(features: Tensor, results: list, fronts: list[bool], extra: tuple[Tensor, list[str]] | None = None,
              head: str = "linear") -> list[tuple[str, float]]:  # fmt: skip
    """Each result's (label, confidence) from one head of kind ``head`` fitted on every consensus
    result (and the ``extra`` rows)."""
    fit_on = [i for i, r in enumerate(results) if r.consensus is not None]
    fitted = _fit(features[fit_on], [results[i].consensus for i in fit_on], extra, head)
    p = fitted.probabilities(features)
    return [decide(p[i], features[i], fronts[i]) for i in range(len(results))]


def _fit(x: Tensor, labels: list[str], extra: tuple[Tensor, list[str]] | None, head: str = "linear"):
    if extra is None or not len(extra[1]):
        return fit_head(x, labels, head)
    return fit_head(torch.cat([x, extra[0]]), labels + list(extra[1]), head)


def judge_extra(judge) -> tuple[Tensor, list[str]] | None:
    """The rows a judge's head was fitted on beside the labelled results (its fixtures, kept in
    head.json), so that an evaluation refits the head exactly as it was made; None for a judge
    fitted on labels alone."""
    rows = judge.head_info.get("fixture_rows")
    if not rows:
        return None
    x = torch.tensor(rows["features"], dtype=torch.float32)
    return judge.head_rows(x, [n.rsplit("/", 1)[0] for n in rows["names"]]), list(rows["labels"])
