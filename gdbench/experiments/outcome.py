"""Where a verdict's Janus outcome comes from: rater labels when they are given (attached to the
cells by run id, as v3's report reads them), otherwise the shipped judge; the claims on the outcome
read the one at hand, and the tables say which."""

from __future__ import annotations

from gdbench.experiments.claims import Claim

OUTCOMES = {"janus": ("label_janus", "judge_janus"), "failure": ("label_failure", "judge_failure")}
"""A claim's outcome metric by its generic name: (read from labels, read from the judge)."""


def attach_labels(rows: list[dict], files: list) -> list[dict]:
    """``rows`` with ``label_janus`` and ``label_failure`` (the share of the label ``files`` that
    call the result Janus, or not fine) where every file labels the row's run id; files are
    labels by run id (``gdbench.metrics.label_sheets --unblind``)."""
    from gdbench.metrics.agreement import JANUS, read_labels

    raters = [{r["run_id"]: r["label"] for r in read_labels(f)} for f in files]
    out = []
    for r in rows:
        got = [lab.get(r.get("run_id")) for lab in raters]
        if raters and all(got):
            r = r | {"label_janus": sum(g in JANUS for g in got) / len(got),
                     "label_failure": sum(g != "fine" for g in got) / len(got)}  # fmt: skip
        out.append(r)
    return out


def read_outcome(claims, labelled: bool) -> tuple[Claim, ...]:
    """``claims`` with their outcome read from labels (``labelled``) or from the judge: the generic
    metrics 'janus' and 'failure' become label_* or judge_*, and with labels a claim on judge_*
    reads label_* (labels, when given, are the primary outcome)."""
    from dataclasses import replace

    out = []
    for c in claims:
        m = c.metric
        if m in OUTCOMES:
            m = OUTCOMES[m][0 if labelled else 1]
        elif labelled and m.startswith("judge_"):
            m = "label_" + m.removeprefix("judge_")
        text = c.text + (" (read from rater labels)" if labelled and m.startswith("label_") and m != c.metric else "")
        out.append(replace(c, metric=m, text=text) if m != c.metric else c)
    return tuple(out)


def outcome_note(rows: list[dict], labels) -> str:
    """One line for the tables: what the Janus outcome was read from."""
    if labels:
        n = sum(isinstance(r.get("label_janus"), float) and r["label_janus"] == r["label_janus"] for r in rows)
        names = ", ".join(str(f) for f in labels)
        return (f"The Janus outcome is read from rater labels ({len(labels)} file(s): {names}; "
                f"{n} of {len(rows)} cells labelled).")  # fmt: skip
    from gdbench.metrics.judge.judge import judge_version

    return f"The Janus outcome is read from the shipped judge ({judge_version()}): no labels were given (--labels)."
