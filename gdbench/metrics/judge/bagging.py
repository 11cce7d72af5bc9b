"""A random forest head (Breiman's bagging of deep classification trees) over the turntable features
and the look numbers, for the head's three classes (Janus, blob, fine): the alternative to the
boosted trees (``trees.py``) that ``scripts/judge_leave_set_out.py`` holds each spent set out with.

Each of ``TREES`` trees is grown on a bootstrap draw of the rows (a row drawn k times weighs k times
its weight), as deep as the rows allow: a node splits where some feature, among a random share
``MAX_FEATURES`` of them drawn afresh at every node, has a threshold that lowers the weighted Gini
impurity and leaves at least ``MIN_LEAF`` distinct rows on either side. A leaf holds its rows'
weighted class shares; the forest's probabilities are the mean of the leaves a row reaches. The
rows are weighted so that each class weighs the same (as the other heads, ``head.class_weights``).
Everything random takes the fit's seed: the same rows and seed give the same trees, bit for bit, on
CPU.

Why it is there: one boosted forest read blob unevenly across the held-out sets (recall 0.54-0.76),
and a random forest is the usual remedy for a learner's variance; held out the same way over the
five spent sets it reads them about as the five averaged boosted forests do, not better (the Janus
split 0.76-0.90 against 0.77-0.88, blob 0.68-0.77 against 0.68-0.77;
docs/results/judge/sixth/leave_set_out.csv), so it is not the shipped head.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from gdbench.metrics.judge.trees import leaf_nodes

TREES = 300
MIN_LEAF = 5
MAX_FEATURES = 0.3
"""The forest's settings: trees, the fewest distinct rows a leaf keeps, the share of the features
each node may split on."""
SHARE_DIGITS = 6
"""A leaf's class shares are kept to this many decimals (the head's file stays small; the forest
fitted and the forest loaded are the same)."""


@dataclass
class Bagged:
    """Trees as flat node arrays [T, M]: a node splits on ``feature`` at ``threshold`` (x <= t goes
    ``left``) or, where ``feature`` is -1, is a leaf whose class shares are ``value`` [T, M, C]."""

    feature: Tensor
    threshold: Tensor
    """float64, so that a row on the fit's side of a threshold stays there."""
    left: Tensor
    right: Tensor
    value: Tensor
    n_features: int

    @property
    def classes(self) -> int:
        return self.value.shape[-1]

    def probabilities(self, x: Tensor) -> Tensor:
        """[N, F] features -> [N, C] the mean over the trees of the class shares of each row's leaf."""
        if x.ndim != 2 or x.shape[1] != self.n_features:
            raise ValueError(f"x: expected [N, {self.n_features}] features, got {tuple(x.shape)}")
        node = leaf_nodes(self.feature, self.threshold, self.left, self.right, x)
        t, n = node.shape
        shares = self.value.gather(1, node[..., None].expand(t, n, self.classes))  # [T, N, C]
        return shares.mean(0).float()

    def to_dict(self) -> dict:
        """Each tree's nodes without the padding (``nodes``: how many), as JSON-ready lists."""
        real = ((self.feature >= 0) | (self.value.sum(-1) > 0)).sum(1).tolist()
        arrays = {k: [row[:m] for row, m in zip(getattr(self, k).tolist(), real)]
                  for k in ("feature", "threshold", "left", "right", "value")}  # fmt: skip
        return {"kind": "bagged", "n_features": self.n_features, "nodes": real, **arrays}

    @classmethod
    def from_dict(cls, d: dict) -> Bagged:
        m, classes = max(d["nodes"]), len(d["value"][0][0])
        pad = {"feature": -1, "threshold": 0.0, "left": -1, "right": -1, "value": [0.0] * classes}
        arrays = {k: [row + [v] * (m - len(row)) for row in d[k]] for k, v in pad.items()}
        ints = {k: torch.tensor(arrays[k], dtype=torch.long) for k in ("feature", "left", "right")}
        floats = {k: torch.tensor(arrays[k], dtype=torch.float64) for k in ("threshold", "value")}
        return cls(n_features=int(d["n_features"]), **ints, **floats)


def _gini_split(x: np.ndarray, yw: np.ndarray, min_leaf: int) -> tuple[int, float, float] | None:
    """(column, threshold, gain) of the split of rows ``x`` [n, F] with weighted one-hot classes
    ``yw`` [n, C] (float64 arrays) that lowers the weighted Gini impurity most, with at least
    ``min_leaf`` rows on either side; the gain is sum_c L_c^2 / L + sum_c R_c^2 / R - sum_c T_c^2 / T
    (the impurity's fall times the node's weight). None where no split gains."""
    n = x.shape[0]
    if n < 2 * min_leaf:
        return None
    order = np.argsort(x, axis=0, kind="stable")
    xs = np.take_along_axis(x, order, 0)
    left = np.cumsum(yw[order], axis=0)[:-1]  # [n-1, F, C]
    total = yw.sum(0)
    right = total - left
    wl, wr = left.sum(-1), right.sum(-1)
    with np.errstate(divide="ignore", invalid="ignore"):
        gain = (left**2).sum(-1) / wl + (right**2).sum(-1) / wr - (total**2).sum() / total.sum()
    count = np.arange(1, n)[:, None]
    ok = (xs[1:] > xs[:-1]) & (count >= min_leaf) & (n - count >= min_leaf) & (wl > 0) & (wr > 0)
    gain = np.where(ok, gain, -1.0)
    i, f = np.unravel_index(int(np.argmax(gain)), gain.shape)
    if gain[i, f] <= 1e-12:
        return None
    return int(f), float((xs[i, f] + xs[i + 1, f]) / 2), float(gain[i, f])


def _grow(x: np.ndarray, yw: np.ndarray, g: torch.Generator, min_leaf: int, max_features: int) -> dict[str, list]:
    """One tree on rows ``x`` [n, F] with weighted one-hot classes ``yw`` [n, C] (float64 arrays)."""
    nodes: dict[str, list] = {"feature": [], "threshold": [], "left": [], "right": [], "value": []}
    classes = yw.shape[1]

    def new(idx: np.ndarray) -> int:
        me = len(nodes["feature"])
        w = yw[idx].sum(0)
        for k, v in (("feature", -1), ("threshold", 0.0), ("left", -1), ("right", -1)):
            nodes[k].append(v)
        share = (w / w.sum()).tolist() if w.sum() > 0 else [1.0 / classes] * classes
        nodes["value"].append([round(v, SHARE_DIGITS) for v in share])
        return me

    everything = np.arange(len(x))
    stack = [(new(everything), everything)]
    while stack:
        me, idx = stack.pop()
        if int((yw[idx].sum(0) > 0).sum()) < 2:
            continue  # pure
        cols = torch.randperm(x.shape[1], generator=g)[:max_features].numpy()
        split = _gini_split(x[np.ix_(idx, cols)], yw[idx], min_leaf)
        if split is None:
            continue
        c, t, _ = split
        f = int(cols[c])
        go = x[idx, f] <= t
        nodes["feature"][me], nodes["threshold"][me] = f, t
        nodes["value"][me] = [0.0] * classes
        nodes["left"][me], nodes["right"][me] = new(idx[go]), new(idx[~go])
        stack += [(nodes["left"][me], idx[go]), (nodes["right"][me], idx[~go])]
    return nodes


def fit_bagged(x: Tensor, y: Tensor, weight: Tensor, *, trees: int = TREES, min_leaf: int = MIN_LEAF,
               max_features: float = MAX_FEATURES, seed: int = 0, classes: int | None = None) -> Bagged:  # fmt: skip
    """A random forest of class indices ``y`` [N] (0 .. C-1) on features ``x`` [N, F] with row
    weights ``weight`` [N]; ``classes`` C (default: the largest index plus one: give it where a
    class may have no row, so that the forest still scores every class)."""
    if x.ndim != 2 or len(x) != len(y) or len(y) != len(weight):
        raise ValueError(f"x, y, weight: expected [N, F], [N], [N], got {tuple(x.shape)}, {tuple(y.shape)}, "
                         f"{tuple(weight.shape)}")  # fmt: skip
    if y.is_floating_point() or not len(y) or int(y.min()) < 0:
        raise ValueError(f"y: expected class indices 0 .. C-1 (integers) of at least one row, got {y.dtype} "
                         f"{tuple(y.shape)}")  # fmt: skip
    if bool((weight < 0).any()) or not float(weight.sum()) > 0:
        raise ValueError("weight: expected non-negative row weights with a positive sum")
    if trees < 1 or min_leaf < 1 or not 0 < max_features <= 1:
        raise ValueError(f"trees, min_leaf, max_features: expected >= 1, >= 1, (0, 1], got {trees}, {min_leaf}, "
                         f"{max_features}")  # fmt: skip
    from gdbench.metrics.judge.trees import class_count

    classes = class_count(y, classes)
    xn = x.double().numpy()
    yw = (torch.nn.functional.one_hot(y, classes).double() * weight.double()[:, None]).numpy()
    k = max(1, round(max_features * x.shape[1]))
    g = torch.Generator().manual_seed(seed)
    grown = []
    for _ in range(trees):
        counts = torch.bincount(torch.randint(len(x), (len(x),), generator=g), minlength=len(x))
        rows = counts.nonzero().flatten().numpy()
        grown.append(_grow(xn[rows], yw[rows] * counts.numpy()[rows, None], g, min_leaf, k))
    return Bagged.from_dict({"n_features": x.shape[1], "nodes": [len(t["feature"]) for t in grown],
                             **{key: [t[key] for t in grown] for key in grown[0]}})  # fmt: skip
