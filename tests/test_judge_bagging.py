"""The random-forest head (``metrics/judge/bagging.py``, compared for the sixth judge, not shipped)
against independent oracles: a brute-force Gini split search in plain Python, hand-placed splits
under the leaf bound, the bootstrap's class shares where no node may split, a row-by-row walk of
the trees, and a rule whose best accuracy is known."""

from __future__ import annotations

import itertools
import json

import numpy as np
import pytest
import torch

from gdbench.metrics.judge.bagging import Bagged, _gini_split, fit_bagged
from gdbench.metrics.judge.head import fit_head, head_kind, load_head


def _brute_gini(x, yw, min_leaf):
    """Every feature, every midpoint between distinct sorted values with at least ``min_leaf`` rows
    on either side: the fall of the weighted Gini impurity, W gini(parent) - W_l gini(l) - W_r gini(r)."""

    def gini_mass(rows):
        w = [sum(c) for c in zip(*rows)]
        total = sum(w)
        return total * (1 - sum((v / total) ** 2 for v in w))

    rows = list(zip(x.tolist(), yw.tolist()))
    parent = gini_mass([c for _, c in rows])
    best = (None, None, -1.0)
    for f in range(x.shape[1]):
        values = sorted({r[0][f] for r in rows})
        for a, b in itertools.pairwise(values):
            t = (a + b) / 2
            left = [c for xi, c in rows if xi[f] <= t]
            right = [c for xi, c in rows if xi[f] > t]
            if len(left) < min_leaf or len(right) < min_leaf:
                continue
            gain = parent - gini_mass(left) - gini_mass(right)
            if gain > best[2] + 1e-12:
                best = (f, t, gain)
    return best


@pytest.mark.parametrize("min_leaf", [1, 3])
def test_gini_split_matches_brute_force(min_leaf):
    rng = np.random.default_rng(4)
    for _ in range(6):
        x = rng.integers(0, 7, (30, 3)).astype(np.float64)  # ties on purpose
        y = rng.integers(0, 3, 30)
        yw = np.eye(3)[y] * (rng.random(30)[:, None] + 0.2)
        f, t, gain = _gini_split(x, yw, min_leaf)
        bf, bt, bgain = _brute_gini(x, yw, min_leaf)
        assert gain == pytest.approx(bgain, rel=1e-9)
        assert (f, t) == (bf, bt)


def test_the_leaf_bound_holds_on_either_side():
    """Ten sorted rows, the last two of the other class: the best split (after row 8) would leave 2
    rows on its right; with at least 3 a side the split falls after row 7 (threshold 6.5), and
    mirrored (the first two rows the other class) before row 3 (threshold 2.5)."""
    x = np.arange(10.0)[:, None]
    assert _gini_split(x, np.eye(2)[[0] * 8 + [1] * 2], 1)[1] == 7.5
    assert _gini_split(x, np.eye(2)[[0] * 8 + [1] * 2], 3)[1] == 6.5
    assert _gini_split(x, np.eye(2)[[1] * 2 + [0] * 8], 3)[1] == 2.5


def test_every_leaf_keeps_the_fewest_rows_and_nodes_draw_their_features():
    """Every leaf holds at least ``min_leaf`` distinct rows of its tree's bootstrap, so walking all
    the rows reaches each leaf at least that often; and with one feature drawn per node the roots
    split on several features across the trees."""
    g = torch.Generator().manual_seed(9)
    x = torch.randn(200, 5, generator=g)
    y = (x[:, 0] + 0.5 * x[:, 1] > 0).long()
    forest = fit_bagged(x, y, torch.ones(200), trees=20, min_leaf=6, max_features=0.2, seed=1)
    assert len({int(f) for f in forest.feature[:, 0]}) >= 3
    from gdbench.metrics.judge.trees import leaf_nodes

    node = leaf_nodes(forest.feature, forest.threshold, forest.left, forest.right, x)  # [T, N]
    for t in range(node.shape[0]):
        counts = torch.bincount(node[t], minlength=forest.feature.shape[1])
        leaves = (forest.feature[t] < 0) & (forest.value[t].sum(-1) > 0)
        reached = counts[leaves]
        assert int(reached[reached > 0].min()) >= 6


def test_no_split_below_twice_the_leaf_or_on_constant_features():
    yw = np.eye(2)[[0, 1, 0, 1, 0, 1]]
    assert _gini_split(np.arange(6.0)[:, None], yw, 4) is None
    assert _gini_split(np.ones((6, 2)), yw, 1) is None


def test_unsplittable_trees_hold_the_bootstraps_class_shares():
    """min_leaf larger than half the rows: every tree is one leaf whose shares are its bootstrap's
    weighted class shares; the draws are replayed from the seed (one randint per tree, then one
    randperm for the root that is not pure)."""
    n, seed = 20, 7
    y = torch.tensor([0] * 8 + [1] * 7 + [2] * 5)
    w = torch.linspace(0.5, 1.5, n, dtype=torch.float64)
    x = torch.randn(n, 3, generator=torch.Generator().manual_seed(0))
    forest = fit_bagged(x, y, w, trees=4, min_leaf=n, seed=seed)
    g = torch.Generator().manual_seed(seed)
    expect = torch.zeros(3, dtype=torch.float64)
    for _ in range(4):
        counts = torch.bincount(torch.randint(n, (n,), generator=g), minlength=n).double()
        mass = torch.stack([(counts * w * (y == k)).sum() for k in range(3)])
        expect += mass / mass.sum() / 4
        if int((mass > 0).sum()) >= 2:
            torch.randperm(3, generator=g)
    got = forest.probabilities(torch.randn(5, 3))
    assert torch.allclose(got.double(), expect.expand(5, 3), atol=1e-6)


def _walk(forest: Bagged, row):
    shares = []
    for t in range(forest.feature.shape[0]):
        node = 0
        while int(forest.feature[t, node]) >= 0:
            f = int(forest.feature[t, node])
            go_left = float(row[f]) <= float(forest.threshold[t, node])
            node = int(forest.left[t, node] if go_left else forest.right[t, node])
        shares.append(forest.value[t, node])
    return torch.stack(shares).mean(0)


def test_probabilities_are_the_mean_of_each_trees_leaf():
    g = torch.Generator().manual_seed(1)
    x = torch.randn(120, 4, generator=g)
    y = ((x[:, 0] > 0).long() + (x[:, 1] > 0.5).long()).clamp(max=2)
    forest = fit_bagged(x, y, torch.ones(120), trees=7, min_leaf=2, seed=3)
    assert int((forest.feature >= 0).sum()) > 7  # the trees did split
    probe = torch.randn(15, 4, generator=g)
    p = forest.probabilities(probe)
    for i in range(len(probe)):
        assert torch.allclose(p[i].double(), _walk(forest, probe[i].double()), atol=1e-6)
    assert torch.allclose(p.sum(1), torch.ones(15), atol=1e-5)


def test_reaches_the_bayes_rate_of_a_known_rule():
    """Class 1 where x0 > 0.3 and x1 > -0.5, each label flipped with probability 0.1, two noise
    features: the best accuracy is 0.9; the forest must come within 0.05 of it on fresh rows."""
    g = torch.Generator().manual_seed(5)

    def draw(n):
        x = torch.randn(n, 4, generator=g)
        y = ((x[:, 0] > 0.3) & (x[:, 1] > -0.5)).long()
        flip = torch.rand(n, generator=g) < 0.1
        return x, torch.where(flip, 1 - y, y)

    x, y = draw(600)
    forest = fit_bagged(x, y, torch.ones(600), trees=60, seed=0)
    xt, yt = draw(2000)
    accuracy = float((forest.probabilities(xt).argmax(1) == yt).float().mean())
    assert accuracy >= 0.85


def test_seeded_and_round_trips():
    g = torch.Generator().manual_seed(2)
    x, y = torch.randn(80, 3, generator=g), torch.randint(0, 3, (80,), generator=g)
    a = fit_bagged(x, y, torch.ones(80), trees=5, seed=11)
    b = fit_bagged(x, y, torch.ones(80), trees=5, seed=11)
    c = fit_bagged(x, y, torch.ones(80), trees=5, seed=12)
    assert all(torch.equal(getattr(a, k), getattr(b, k)) for k in ("feature", "threshold", "value"))
    assert not torch.equal(a.threshold, c.threshold)
    d = json.loads(json.dumps(a.to_dict()))
    assert [len(row) for row in d["feature"]] == d["nodes"]  # stored without the padding
    back = load_head(d)
    assert head_kind(back) == "bagged"
    assert torch.equal(back.probabilities(x), a.probabilities(x))
    with pytest.raises(ValueError, match="kind: expected a head of one of"):
        load_head({"kind": "forest"})
    with pytest.raises(ValueError, match="head: expected a fitted head"):
        head_kind(object())


def test_fit_head_bagged_weighs_the_classes_alike():
    """90 fine, 10 blob and 10 front_everywhere rows on uninformative features: with the classes
    weighed alike the unsplittable forest reads the three as equally likely (within the bootstrap's
    noise)."""
    labels = ["fine"] * 90 + ["blob"] * 10 + ["front_everywhere"] * 10
    x = torch.zeros(110, 2)
    head = fit_head(x, labels, "bagged")
    p = head.probabilities(x[:1])[0]
    assert head_kind(head) == "bagged"
    assert abs(float(p[1] - p[2])) < 0.15 and abs(float(p[0] - p[2])) < 0.15


def test_bad_input_names_the_argument():
    with pytest.raises(ValueError, match="x, y, weight"):
        fit_bagged(torch.zeros(3, 2), torch.zeros(4, dtype=torch.long), torch.ones(3))
    with pytest.raises(ValueError, match="y: expected class indices"):
        fit_bagged(torch.zeros(3, 2), torch.zeros(3), torch.ones(3))
    with pytest.raises(ValueError, match="weight: expected non-negative"):
        fit_bagged(torch.zeros(3, 2), torch.zeros(3, dtype=torch.long), -torch.ones(3))
    forest = fit_bagged(torch.randn(6, 2), torch.tensor([0, 1] * 3), torch.ones(6), trees=2)
    with pytest.raises(ValueError, match=r"x: expected \[N, 2\] features"):
        forest.probabilities(torch.zeros(4, 3))
    with pytest.raises(ValueError, match="max_features"):
        fit_bagged(torch.zeros(3, 2), torch.zeros(3, dtype=torch.long), torch.ones(3), max_features=0.0)
