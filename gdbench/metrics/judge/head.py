"""The judge's head: the turntable features (``reading.result_features``) -> one of the labelling rule's
classes, by a multinomial logistic regression over three classes (Janus, blob, fine), fitted to
results that both rater passes label alike (``fit``), then Janus split into front_everywhere and
second_face by where the front is read (``SECOND_FACE``).

A regression of twenty numbers is the "small head" the labels may train: it is fitted and judged
leave-kind-out (every kind held out in turn, ``judge/evaluate.py``), and the shipped head is fitted
once on every consensus result of v3's committed sheets.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from gdbench.metrics.agreement import JANUS

CLASSES3 = ("janus", "blob", "fine")
"""The head's classes: the rule's front_everywhere and second_face together, blob, fine."""
SECOND_FACE = (0.5, 0.5)
"""A Janus result is a second_face when some view reads as a profile (``profile_max`` at least the
first number: it has sides) and the views that see its back read the front (``back_reads_front``
at least the second); otherwise front_everywhere."""
L2 = 1e-2
"""Ridge penalty of the regression (on standardised features)."""


@dataclass
class Head:
    mean: Tensor
    scale: Tensor
    weight: Tensor
    """[F, 3]."""
    bias: Tensor
    """[3]."""

    def probabilities(self, x: Tensor) -> Tensor:
        """[N, F] features -> [N, 3] probabilities of ``CLASSES3``."""
        return torch.softmax(((x - self.mean) / self.scale) @ self.weight + self.bias, -1)

    @property
    def n_features(self) -> int:
        return self.weight.shape[0]

    def to_dict(self) -> dict:
        return {k: getattr(self, k).tolist() for k in ("mean", "scale", "weight", "bias")}

    @classmethod
    def from_dict(cls, d: dict) -> Head:
        return cls(**{k: torch.tensor(d[k], dtype=torch.float32) for k in ("mean", "scale", "weight", "bias")})


def to3(label: str) -> int:
    """A rule's label -> its index in ``CLASSES3``."""
    return 0 if label in JANUS else CLASSES3.index(label)


def fit(x: Tensor, labels: list[str], l2: float = L2) -> Head:
    """The regression of ``labels`` (rule labels) on features ``x`` [N, F], classes weighted
    equally (each class's results weigh 1 / its count), so that the rare class (fine) counts."""
    y = torch.tensor([to3(lab) for lab in labels])
    mean, scale = x.mean(0), x.std(0).clamp(min=1e-6)
    z = (x - mean) / scale
    counts = torch.bincount(y, minlength=3).float().clamp(min=1)
    w_row = (1.0 / counts)[y]
    w_row = w_row / w_row.sum()
    weight = torch.zeros(x.shape[1], 3, requires_grad=True)
    bias = torch.zeros(3, requires_grad=True)
    opt = torch.optim.LBFGS([weight, bias], lr=1, max_iter=500, line_search_fn="strong_wolfe")

    def closure():
        opt.zero_grad()
        logp = torch.log_softmax(z @ weight + bias, -1)
        loss = -(w_row * logp[torch.arange(len(y)), y]).sum() + l2 * weight.pow(2).sum()
        loss.backward()
        return loss

    opt.step(closure)
    return Head(mean, scale, weight.detach(), bias.detach())


def class_weights(labels: list[str]) -> tuple[Tensor, Tensor]:
    """(class indices [N] of ``CLASSES3``, row weights [N] summing to 1 with each class weighing the
    same) of rule labels."""
    y = torch.tensor([to3(lab) for lab in labels])
    counts = torch.bincount(y, minlength=3).double().clamp(min=1)
    w = (1.0 / counts)[y]
    return y, w / w.sum()


HEADS = ("linear", "trees", "bagged", "blend")
"""The kinds of head: the regression (``fit``; the first three judges), boosted trees over the
features and the look numbers (``trees.fit_trees``: the fourth judge one forest, the fifth to
seventh five averaged with the blob offset), a random forest over the same (``bagging.fit_bagged``:
compared for the sixth judge by holding each spent set out, not shipped) and the regression and the
trees averaged, fine weighed against a false warning (``blend.Blend``: the eighth judge)."""


def fit_head(x: Tensor, labels: list[str], kind: str = "linear", seed: int = 0):
    """A head of ``kind`` (``HEADS``) fitted to ``labels`` on features ``x`` [N, F], classes
    weighted equally."""
    if kind == "linear":
        return fit(x, labels)
    if kind == "blend":  # the regression and the trees, fitted on the same rows (blend.py)
        from gdbench.metrics.judge.blend import PARTS, Blend

        return Blend([fit_head(x, labels, part, seed=seed) for part in PARTS], PARTS)
    if kind == "trees":
        from gdbench.metrics.judge.trees import fit_trees as fit_kind
    elif kind == "bagged":
        from gdbench.metrics.judge.bagging import fit_bagged as fit_kind
    else:
        raise ValueError(f"kind: expected one of {HEADS}, got {kind!r}")
    y, w = class_weights(labels)
    return fit_kind(x, y, w, seed=seed, classes=len(CLASSES3))


def load_head(d: dict):
    """A head from its ``to_dict``: a ``Head`` (no kind, or linear), a ``trees.Forest`` (trees), a
    ``bagging.Bagged`` (bagged) or a ``blend.Blend`` (blend)."""
    kind = d.get("kind", "linear")
    if kind == "blend":
        from gdbench.metrics.judge.blend import Blend

        if "fine_odds" not in d or not d.get("parts"):
            raise ValueError(f"head: a blend needs its fine_odds and parts, got the keys {sorted(d)}")
        parts = d["parts"]
        kinds = tuple(p.get("kind", "linear") for p in parts)
        return Blend([load_head(p) for p in parts], kinds, float(d["fine_odds"]))
    if kind == "bagged":
        from gdbench.metrics.judge.bagging import Bagged

        return Bagged.from_dict(d)
    if kind == "trees":
        from gdbench.metrics.judge.trees import Forest

        return Forest.from_dict(d)
    if kind == "linear":
        return Head.from_dict(d)
    raise ValueError(f"kind: expected a head of one of {HEADS}, got {kind!r}")


def head_kind(head) -> str:
    """The ``HEADS`` kind of a fitted head."""
    from gdbench.metrics.judge.bagging import Bagged
    from gdbench.metrics.judge.blend import Blend
    from gdbench.metrics.judge.trees import Forest

    for kind, cls in (("linear", Head), ("trees", Forest), ("bagged", Bagged), ("blend", Blend)):
        if isinstance(head, cls):
            return kind
    raise ValueError(f"head: expected a fitted head of one of {HEADS}, got {type(head).__name__}")


def decide(probabilities: Tensor, features: Tensor, has_front: bool) -> tuple[str, float]:
    """One result's (label, confidence) from its head probabilities [3] and features [F]
    (``reading.FEATURES`` order). An asset without a front gets blob or fine only (its Janus
    probability counts as blob's)."""
    from gdbench.metrics.judge.reading import FEATURES

    p = probabilities.clone()
    if not has_front:
        p = torch.stack([torch.tensor(0.0), p[0] + p[1], p[2]])
    k = int(p.argmax())
    if k == 0:
        f = dict(zip(FEATURES, features.tolist()))  # the eye's (the first block of features)
        sides, back = SECOND_FACE
        label = "second_face" if f["profile_max"] >= sides and f["back_reads_front"] >= back else "front_everywhere"
    else:
        label = CLASSES3[k]
    return label, float(p[k])
