"""The fourth judge's head: gradient-boosted regression trees over the turntable features and the
look numbers (``look.py``), for the head's three classes (Janus, blob, fine).

Friedman's multiclass boosting (the deviance of a softmax over the classes): each round fits, for
every class, a small regression tree (depth ``DEPTH``, splits chosen by Friedman's improvement) to
that class's residual (indicator minus probability) on a random share of the rows, and sets each
leaf by one Newton step; the class's score moves by ``RATE`` times the tree. The rows are weighted
so that each class weighs the same (as the linear head, ``head.fit``). Everything random takes the
fit's seed: the same rows and seed give the same trees, bit for bit, on CPU.

Why trees: the linear head reads an outline's confidence one way for the empirical prior's results
and the other for the learned prior's (docs/scoring.md, the prior split); a tree can read the look
numbers first (how sharp, how coloured, how soft the result is) and the turntable's after them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

ROUNDS = 150
DEPTH = 2
RATE = 0.05
SUBSAMPLE = 0.8
"""The boosting's settings: rounds, tree depth, learning rate, share of rows each round sees."""
SEEDS = 5
"""The head's forests, one per seed of the rows' draws, averaged (``average``; from the fifth judge:
the fourth's one forest read the held-out sets less evenly)."""
OFFSETS = (0.0, math.log(1.25), 0.0)
"""Added to the classes' scores (Janus, blob, fine) of the averaged forest, from the fifth judge: a
result is read blob where its blob probability is 4/5 of what the forest says. Chosen with the
number of seeds by holding each spent fresh set out in turn (docs/scoring.md, the fifth judge)."""


@dataclass
class Forest:
    """Trees as flat node arrays [T, M]: a node splits on ``feature`` at ``threshold`` (x <= t goes
    ``left``) or, where ``feature`` is -1, is a leaf worth ``value``; tree t adds to class
    ``t % classes``."""

    init: Tensor
    """[C] the classes' starting scores (log shares of the weighted rows); float64 throughout, so
    that a row on the fit's side of a threshold stays there."""
    feature: Tensor
    threshold: Tensor
    left: Tensor
    right: Tensor
    value: Tensor
    rate: float
    n_features: int
    """How many features the trees read (the columns of ``x``)."""

    @property
    def classes(self) -> int:
        return len(self.init)

    def scores(self, x: Tensor) -> Tensor:
        """[N, F] -> [N, C] the classes' scores (logits)."""
        node = leaf_nodes(self.feature, self.threshold, self.left, self.right, x)
        leaf_values = self.value.gather(1, node)  # [T, N]
        per_class = leaf_values.reshape(-1, self.classes, x.shape[0]).sum(0)  # [C, N]
        return (self.init[None] + self.rate * per_class.T).float()

    def probabilities(self, x: Tensor) -> Tensor:
        """[N, F] features -> [N, C] probabilities."""
        return torch.softmax(self.scores(x), -1)

    def to_dict(self) -> dict:
        keys = ("init", "feature", "threshold", "left", "right", "value")
        arrays = {k: getattr(self, k).tolist() for k in keys}
        return {"kind": "trees", "rate": self.rate, "n_features": self.n_features, **arrays}

    @classmethod
    def from_dict(cls, d: dict) -> Forest:
        ints = {k: torch.tensor(d[k], dtype=torch.long) for k in ("feature", "left", "right")}
        floats = {k: torch.tensor(d[k], dtype=torch.float64) for k in ("init", "threshold", "value")}
        return cls(rate=float(d["rate"]), n_features=int(d["n_features"]), **ints, **floats)


def leaf_nodes(feature: Tensor, threshold: Tensor, left: Tensor, right: Tensor, x: Tensor) -> Tensor:
    """[T, N] the leaf each row of ``x`` [N, F] reaches in each of T trees stored as flat node arrays
    [T, M] (``Forest``'s layout: a node splits on ``feature`` at ``threshold``, x <= t going
    ``left``; ``feature`` -1 marks a leaf); compared in float64."""
    x = x.double()
    t, n = feature.shape[0], x.shape[0]
    node = torch.zeros(t, n, dtype=torch.long)
    rows = torch.arange(n)[None].expand(t, n)
    for _ in range(feature.shape[1]):  # no tree is deeper than its node count
        f = feature.gather(1, node)
        leaf = f < 0
        if bool(leaf.all()):
            break
        go_left = x[rows, f.clamp(min=0)] <= threshold.gather(1, node)
        node = torch.where(leaf, node, torch.where(go_left, left.gather(1, node), right.gather(1, node)))
    return node


def average(forests: list[Forest], offset: Tensor | None = None) -> Forest:
    """One forest whose scores are the mean of ``forests``' scores (their trees side by side, each
    leaf divided by their count), plus ``offset`` [C] on the classes' scores where given (a
    calibration of the classes' thresholds: log 1.25 on a class reads it where its probability is
    4/5 of what it was)."""
    k = len(forests)
    if not k or len({(f.classes, f.n_features, f.rate) for f in forests}) != 1:
        raise ValueError("forests: expected one or more forests of the same classes, features and rate")
    m = max(f.feature.shape[1] for f in forests)

    def pad(t: Tensor, fill) -> Tensor:
        return torch.nn.functional.pad(t, (0, m - t.shape[1]), value=fill)

    fills = {"feature": -1, "threshold": 0.0, "left": -1, "right": -1, "value": 0.0}
    cat = {name: torch.cat([pad(getattr(f, name), fill) for f in forests]) for name, fill in fills.items()}
    cat["value"] = cat["value"] / k
    init = torch.stack([f.init for f in forests]).mean(0)
    if offset is not None:
        init = init + offset.to(init.dtype)
    return Forest(init=init, rate=forests[0].rate, n_features=forests[0].n_features, **cat)


def _best_split(x: Tensor, r: Tensor, w: Tensor) -> tuple[int, float, float] | None:
    """(feature, threshold, improvement) of the best split of rows ``x`` [n, F] with residuals
    ``r`` and weights ``w`` by Friedman's improvement W_l W_r / (W_l + W_r) (mean_l - mean_r)^2,
    None where no feature has two distinct values."""
    n = x.shape[0]
    if n < 2:
        return None
    xs, order = x.sort(dim=0, stable=True)
    ws, rs = w[order], (w * r)[order]  # [n, F]
    wl, sl = ws.cumsum(0)[:-1], rs.cumsum(0)[:-1]
    wt, st = ws.sum(0), rs.sum(0)
    wr, sr = wt - wl, st - sl
    ok = (xs[1:] > xs[:-1]) & (wl > 0) & (wr > 0)
    gain = wl * wr / (wl + wr).clamp(min=1e-12) * (sl / wl.clamp(min=1e-12) - sr / wr.clamp(min=1e-12)) ** 2
    gain = torch.where(ok, gain, torch.full_like(gain, -1.0))
    flat = int(gain.argmax())
    i, f = divmod(flat, x.shape[1])
    if float(gain[i, f]) <= 0:
        return None
    return f, float((xs[i, f] + xs[i + 1, f]) / 2), float(gain[i, f])


def _tree(x: Tensor, r: Tensor, w: Tensor, p: Tensor, depth: int, classes: int) -> dict[str, list]:
    """One regression tree on the residuals ``r`` with leaves set by a Newton step (``p``: the
    class's probability per row)."""
    nodes: dict[str, list] = {"feature": [], "threshold": [], "left": [], "right": [], "value": []}

    def leaf_value(idx: Tensor) -> float:
        num = float((w[idx] * r[idx]).sum())
        den = float((w[idx] * p[idx] * (1 - p[idx])).sum())
        return (classes - 1) / classes * num / den if den > 1e-12 else 0.0

    def grow(idx: Tensor, level: int) -> int:
        me = len(nodes["feature"])
        for k in nodes:
            nodes[k].append(-1 if k in ("feature", "left", "right") else 0.0)
        split = _best_split(x[idx], r[idx], w[idx]) if level < depth else None
        if split is None:
            nodes["value"][me] = leaf_value(idx)
            return me
        f, t, _ = split
        go = x[idx, f] <= t
        nodes["feature"][me], nodes["threshold"][me] = f, t
        nodes["left"][me] = grow(idx[go], level + 1)
        nodes["right"][me] = grow(idx[~go], level + 1)
        return me

    grow(torch.arange(len(x)), 0)
    return nodes


def fit_trees(x: Tensor, y: Tensor, weight: Tensor, seed: int = 0, classes: int | None = None) -> Forest:
    """The judge's trees head: ``SEEDS`` forests (seeds ``seed``, ``seed`` + 1, ...) averaged, with
    ``OFFSETS`` on the classes' scores (``classes`` as ``fit_forest``'s)."""
    if classes is not None and classes > len(OFFSETS):
        raise ValueError(f"classes: expected at most {len(OFFSETS)} (one offset each, OFFSETS), got {classes}")
    forests = [fit_forest(x, y, weight, seed=seed + i, classes=classes) for i in range(SEEDS)]
    return average(forests, torch.tensor(OFFSETS[: forests[0].classes], dtype=torch.float64))


def fit_forest(x: Tensor, y: Tensor, weight: Tensor, *, rounds: int = ROUNDS, depth: int = DEPTH,
               rate: float = RATE, subsample: float = SUBSAMPLE, seed: int = 0,
               classes: int | None = None) -> Forest:  # fmt: skip
    """Boosted trees of class indices ``y`` [N] (0 .. C-1) on features ``x`` [N, F] with row
    weights ``weight`` [N] (float64 sums throughout); ``classes`` C (default: the largest index plus
    one: give it where a class may have no row, so that the forest still scores every class)."""
    if x.ndim != 2 or len(x) != len(y) or len(y) != len(weight):
        raise ValueError(f"x, y, weight: expected [N, F], [N], [N], got {tuple(x.shape)}, {tuple(y.shape)}, "
                         f"{tuple(weight.shape)}")  # fmt: skip
    x, w = x.double(), weight.double()
    classes = class_count(y, classes)
    onehot = torch.nn.functional.one_hot(y, classes).double()
    prior = (w[:, None] * onehot).sum(0) / w.sum()
    init = prior.clamp(min=1e-12).log()
    score = init[None].repeat(len(x), 1)
    g = torch.Generator().manual_seed(seed)
    trees = []
    take = max(2, round(subsample * len(x)))
    for _ in range(rounds):
        rows = torch.randperm(len(x), generator=g)[:take].sort().values
        p = torch.softmax(score, -1)
        for k in range(classes):
            r = onehot[:, k] - p[:, k]
            tree = _tree(x[rows], r[rows], w[rows], p[rows, k], depth, classes)
            trees.append(tree)
            score[:, k] += rate * _predict_one(tree, x)
    m = max(len(t["feature"]) for t in trees)
    pad = {"feature": -1, "threshold": 0.0, "left": -1, "right": -1, "value": 0.0}
    arrays = {k: [t[k] + [v] * (m - len(t[k])) for t in trees] for k, v in pad.items()}
    ints, floats = ("feature", "left", "right"), ("threshold", "value")
    return Forest(init=init, rate=rate, n_features=x.shape[1],
                  **{k: torch.tensor(arrays[k], dtype=torch.long) for k in ints},
                  **{k: torch.tensor(arrays[k], dtype=torch.float64) for k in floats})  # fmt: skip


def class_count(y: Tensor, classes: int | None) -> int:
    """C: ``classes``, checked to cover every index of ``y``, or ``y``'s largest index plus one."""
    top = int(y.max()) + 1
    if classes is None:
        return top
    if classes < top:
        raise ValueError(f"classes: expected at least {top} (y's largest index plus one), got {classes}")
    return classes


def _predict_one(tree: dict[str, list], x: Tensor) -> Tensor:
    """[N] one tree's leaf values for rows ``x`` (float64)."""
    out = torch.empty(len(x), dtype=torch.float64)
    stack = [(0, torch.arange(len(x)))]
    while stack:
        node, idx = stack.pop()
        f = tree["feature"][node]
        if f < 0:
            out[idx] = tree["value"][node]
            continue
        go = x[idx, f] <= tree["threshold"][node]
        stack += [(tree["left"][node], idx[go]), (tree["right"][node], idx[~go])]
    return out
