"""The eighth judge's blended head (gdbench/metrics/judge/blend.py): its probabilities against the
parts' computed by hand, its round trip through head.json's form, and bad settings refused."""

from __future__ import annotations

import json

import pytest
import torch

from gdbench.metrics.judge.blend import FINE_ODDS, PARTS, Blend
from gdbench.metrics.judge.head import fit_head, head_kind, load_head

LABELS = ["front_everywhere", "blob", "fine"] * 20


@pytest.fixture(scope="module")
def fitted():
    """(features [60, 5], the blend fitted on them): each class shifted along its own feature."""
    g = torch.Generator().manual_seed(0)
    y = torch.tensor([0, 1, 2] * 20)
    x = torch.randn(60, 5, generator=g) + torch.nn.functional.one_hot(y, 5).float() * 2.0
    return x, fit_head(x, LABELS, "blend")


def test_the_blend_is_the_parts_mean_with_fine_weighed_by_its_odds(fitted):
    x, blend = fitted
    assert head_kind(blend) == "blend" and blend.kinds == PARTS and blend.fine_odds == FINE_ODDS
    parts = [fit_head(x, LABELS, kind) for kind in PARTS]  # fitted alone: the same fits
    mean = sum(p.probabilities(x).double() for p in parts) / len(parts)
    want = mean * torch.tensor([1.0, 1.0, FINE_ODDS], dtype=torch.float64)
    want = want / want.sum(1, keepdim=True)
    got = blend.probabilities(x)
    assert torch.allclose(got.double(), want, atol=1e-6)
    assert torch.allclose(got.sum(1), torch.ones(60), atol=1e-5)
    # the odds move a result toward fine only: where fine already wins it still wins
    plain = Blend(blend.parts, blend.kinds, 1.0).probabilities(x)
    assert bool((got[:, 2] >= plain[:, 2] - 1e-6).all()) and bool((got[:, 2] > plain[:, 2]).any())


def test_the_blend_reads_back_from_its_dict_as_the_same_numbers(fitted):
    x, blend = fitted
    again = load_head(json.loads(json.dumps(blend.to_dict())))
    assert isinstance(again, Blend) and again.kinds == blend.kinds and again.n_features == 5
    assert torch.allclose(again.probabilities(x), blend.probabilities(x), atol=1e-6)


@pytest.mark.parametrize("odds", [0.0, -1.0, float("nan"), float("inf")])
def test_bad_odds_and_mismatched_parts_are_refused(odds, fitted):
    _, blend = fitted
    with pytest.raises(ValueError, match="fine_odds"):
        Blend(blend.parts, blend.kinds, odds)
    with pytest.raises(ValueError, match="parts"):
        Blend(blend.parts[:1], blend.kinds)
    narrow = fit_head(torch.randn(60, 3, generator=torch.Generator().manual_seed(2)), LABELS, "linear")
    with pytest.raises(ValueError, match="parts"):
        Blend([blend.parts[0], narrow], blend.kinds)  # heads over different features
    with pytest.raises(ValueError, match="fine_odds"):
        load_head({k: v for k, v in blend.to_dict().items() if k != "fine_odds"})
