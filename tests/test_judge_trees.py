"""The fourth judge's head (boosted trees) and its look numbers, against independent oracles: a
brute-force split search, the Newton step's closed form, a row-by-row walk of the trees, and the
look of drawn images whose numbers are known by construction."""

from __future__ import annotations

import itertools

import pytest
import torch

from gdbench.metrics.judge.look import LOOK, PER_VIEW, look_numbers
from gdbench.metrics.judge.trees import Forest, _best_split, fit_forest


def _brute_split(x, r, w):
    """Every feature, every midpoint between distinct sorted values, Friedman's improvement in
    plain Python floats."""
    best = (None, None, -1.0)
    rows = list(zip(x.tolist(), r.tolist(), w.tolist()))
    for f in range(x.shape[1]):
        values = sorted({row[0][f] for row in rows})
        for a, b in itertools.pairwise(values):
            t = (a + b) / 2
            left = [(ri, wi) for xi, ri, wi in rows if xi[f] <= t]
            right = [(ri, wi) for xi, ri, wi in rows if xi[f] > t]
            wl, wr = sum(wi for _, wi in left), sum(wi for _, wi in right)
            ml, mr = sum(ri * wi for ri, wi in left) / wl, sum(ri * wi for ri, wi in right) / wr
            gain = wl * wr / (wl + wr) * (ml - mr) ** 2
            if gain > best[2] + 1e-12:
                best = (f, t, gain)
    return best


def test_best_split_matches_brute_force():
    g = torch.Generator().manual_seed(3)
    for _ in range(5):
        x = torch.randint(0, 9, (40, 3), generator=g).double()  # ties on purpose
        r = torch.randn(40, generator=g, dtype=torch.float64)
        w = torch.rand(40, generator=g, dtype=torch.float64) + 0.1
        f, t, gain = _best_split(x, r, w)
        bf, bt, bgain = _brute_split(x, r, w)
        assert gain == pytest.approx(bgain, rel=1e-9)
        assert (f, t) == (bf, bt)


def test_no_split_of_constant_features():
    assert _best_split(torch.ones(10, 2, dtype=torch.float64), torch.randn(10, dtype=torch.float64),
                       torch.ones(10, dtype=torch.float64)) is None  # fmt: skip


def test_one_round_of_stumps_is_the_newton_step():
    """depth 0 (a single leaf), one round, every row: each class's score moves by rate times
    (K-1)/K sum w r / sum w p (1 - p) from the log shares of the weighted classes."""
    g = torch.Generator().manual_seed(0)
    y = torch.randint(0, 3, (30,), generator=g)
    w = torch.rand(30, generator=g, dtype=torch.float64) + 0.5
    x = torch.randn(30, 2, generator=g)
    forest = fit_forest(x, y, w, rounds=1, depth=0, rate=0.3, subsample=1.0)
    share = torch.stack([(w * (y == k)).sum() for k in range(3)]) / w.sum()
    want = []
    for k in range(3):
        p, r = share[k], (y == k).double() - share[k]
        want.append(share[k].log() + 0.3 * (2 / 3) * (w * r).sum() / (w * p * (1 - p)).sum())
    got = forest.scores(x[:1])[0]
    assert torch.allclose(got.double(), torch.stack(want), atol=1e-6)


def _walk(d: dict, row: list[float]) -> list[float]:
    """A forest's class scores for one row, walking each tree node by node (no tensors)."""
    classes = len(d["init"])
    out = list(d["init"])
    for t in range(len(d["feature"])):
        node = 0
        while d["feature"][t][node] >= 0:
            f = d["feature"][t][node]
            node = d["left"][t][node] if row[f] <= d["threshold"][t][node] else d["right"][t][node]
        out[t % classes] += d["rate"] * d["value"][t][node]
    return out


def test_forest_learns_steps_and_its_dict_walks_alike():
    g = torch.Generator().manual_seed(1)
    x = torch.rand(300, 4, generator=g)
    y = (x[:, 2] > 0.35).long() + (x[:, 2] > 0.7).long()  # the third feature alone decides
    forest = fit_forest(x, y, torch.ones(300, dtype=torch.float64), rounds=60, seed=2)
    test = torch.rand(200, 4, generator=g)
    truth = (test[:, 2] > 0.35).long() + (test[:, 2] > 0.7).long()
    near = ((test[:, 2] - 0.35).abs() < 0.02) | ((test[:, 2] - 0.7).abs() < 0.02)
    assert bool((forest.probabilities(test).argmax(1) == truth)[~near].all())
    assert set(forest.feature[:30, 0].tolist()) == {2}  # the first ten rounds' roots split where the classes do
    d = forest.to_dict()
    back = Forest.from_dict(d)
    scores = back.scores(test[:20])
    for i in range(20):
        assert scores[i].tolist() == pytest.approx(_walk(d, test[i].double().tolist()), abs=1e-5)


def test_same_seed_same_forest_other_seed_other():
    g = torch.Generator().manual_seed(4)
    x, y = torch.randn(120, 5, generator=g), torch.randint(0, 3, (120,), generator=g)
    w = torch.ones(120, dtype=torch.float64)
    a, b = fit_forest(x, y, w, rounds=10, seed=7), fit_forest(x, y, w, rounds=10, seed=7)
    c = fit_forest(x, y, w, rounds=10, seed=8)
    assert a.to_dict() == b.to_dict()
    assert not torch.equal(a.threshold, c.threshold)


def test_forest_bad_shapes_say_which():
    with pytest.raises(ValueError, match=r"x, y, weight"):
        fit_forest(torch.zeros(5, 2), torch.zeros(4, dtype=torch.long), torch.ones(5))


def _square(colour, side: int, size: int = 128) -> torch.Tensor:
    img = torch.full((size, size, 3), 255, dtype=torch.uint8)
    lo = (size - side) // 2
    img[lo : lo + side, lo : lo + side] = torch.tensor(colour, dtype=torch.uint8)
    return img


def test_look_of_flat_squares_by_construction():
    """Six views of one flat pure-red square of side 40 on white: it fills 1600 / 128^2 of the view,
    its saturation is 1, its colour does not spread, no pixel is partly covered, and the grey
    steps by 2/3 on its 4 * 40 edge pixels per direction (so q99.9 of the differences is 2/3 and
    q90 is 0); over identical views every spread is 0."""
    views = torch.stack([_square((255, 0, 0), 40)] * 6)
    look = dict(zip(LOOK, look_numbers(views).tolist()))
    assert look["look_area"] == pytest.approx(1600 / 128**2, rel=1e-6)
    assert look["look_saturation"] == pytest.approx(1.0, abs=1e-6)
    assert look["look_soft"] == 0.0
    assert look["look_spread_r"] == pytest.approx(0.0, abs=1e-6)
    assert look["look_edge_q999"] == pytest.approx(2 / 3, abs=1e-6)
    assert look["look_edge_q90"] == 0.0
    assert all(look[f"look_{k}_spread"] == pytest.approx(0.0, abs=1e-6) for k in PER_VIEW)


def test_look_spreads_and_resampling():
    """Squares of two sizes alternate: the area's spread is the sample standard deviation of the
    two areas; the same views drawn at 256 px read the same look within a few percent."""
    small, big = _square((0, 0, 200), 30), _square((0, 0, 200), 50)
    views = torch.stack([small, big] * 3)
    look = dict(zip(LOOK, look_numbers(views).tolist()))
    areas = torch.tensor([900.0, 2500.0] * 3) / 128**2
    assert look["look_area_spread"] == pytest.approx(float(areas.std()), rel=1e-5)
    large = torch.stack([_square((0, 0, 200), 60, 256), _square((0, 0, 200), 100, 256)] * 3)
    resampled = dict(zip(LOOK, look_numbers(large).tolist()))
    assert resampled["look_area"] == pytest.approx(look["look_area"], rel=0.05)
    assert resampled["look_saturation"] == pytest.approx(look["look_saturation"], rel=0.05)


def test_the_look_is_read_on_a_sheets_six_views():
    """A run turntable's 36 frames (10 degrees apart) give the frames at 0, 60, ..., 300 (indices
    0, 6, ..., 30), in sheet order however the frames are ordered; azimuths missing one of the six
    give every view."""
    from gdbench.metrics.judge.reading import sheet_views

    assert sheet_views(torch.arange(36) * 10.0).tolist() == [0, 6, 12, 18, 24, 30]
    shuffled = torch.tensor([300.0, 10.0, 0.0, 180.0, 60.4, 240.0, 120.0, 359.6])
    assert sheet_views(shuffled).tolist() == [2, 4, 6, 3, 5, 0]
    assert sheet_views(torch.tensor([0.0, 60.0, 120.0, 180.0, 240.0])).tolist() == [0, 1, 2, 3, 4]


def test_an_average_of_forests_scores_their_mean_plus_the_offset():
    from gdbench.metrics.judge.trees import average

    g = torch.Generator().manual_seed(5)
    x, y = torch.randn(90, 4, generator=g), torch.randint(0, 3, (90,), generator=g)
    w = torch.ones(90, dtype=torch.float64)
    forests = [fit_forest(x, y, w, rounds=8, depth=d, seed=s) for s, d in ((0, 2), (1, 1), (2, 2))]
    offset = torch.tensor([0.0, 0.3, -0.1])
    mean = average(forests, offset)
    test = torch.randn(25, 4, generator=g)
    want = torch.stack([f.scores(test) for f in forests]).mean(0) + offset
    assert torch.allclose(mean.scores(test), want, atol=1e-5)
    assert Forest.from_dict(mean.to_dict()).scores(test).tolist() == mean.scores(test).tolist()
    with pytest.raises(ValueError, match="forests"):
        average([])


def test_a_fit_without_a_class_still_scores_every_class():
    """Labels with no fine row (a fold that holds out every fine result): the head still scores the
    three classes, the absent one at the floor of its weighted share (log 1e-12), so never picked,
    and it reads the two present classes by the rule that made them (the first feature's sign);
    a class count below the labels' is an error."""
    from gdbench.metrics.judge.head import fit_head
    from gdbench.metrics.judge.trees import fit_trees

    g = torch.Generator().manual_seed(5)
    x = torch.randn(80, 3, generator=g)
    labels = ["front_everywhere" if v > 0 else "blob" for v in x[:, 0].tolist()]
    p = fit_head(x, labels, "trees").probabilities(x)
    assert p.shape == (80, 3)
    assert float(p[:, 2].max()) < 1e-9
    clear = x[:, 0].abs() > 0.1
    assert bool((p.argmax(1) == (x[:, 0] <= 0).long())[clear].all())
    y = (x[:, 0] <= 0).long()
    with pytest.raises(ValueError, match=r"classes: expected at least 2"):
        fit_forest(x, y, torch.ones(80, dtype=torch.float64), classes=1)
    with pytest.raises(ValueError, match=r"classes: expected at most 3"):
        fit_trees(x, y, torch.ones(80, dtype=torch.float64), classes=4)
