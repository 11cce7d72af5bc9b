"""The eighth judge's head: the regression and the boosted trees, fitted on the same rows, their
probabilities averaged, and a false warning weighed ``FINE_ODDS`` times a missed failure.

Why both: held out by kind (a kind no label taught), the regression carries to the new kind and
the trees do not (they learn each kind's look); held out by set (new results of kinds the labels
taught), the trees read the empirical prior's results that the regression reads wrong. The average
keeps most of each (docs/scoring.md, "The eighth judge").

Why the odds: the issue's bar lets a judge miss three failures in ten but warn at most one fine
result in ten; reading fine unless a failure class is ``FINE_ODDS`` times as probable as fine
(``Blend.probabilities`` multiplies fine's share by it and normalises) weighs the two errors as the
bar does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

FINE_ODDS = 2.0
"""A result reads fine unless a failure class is this many times as probable as fine (before the
odds): the bar's false warnings (1 in 10) against its missed failures (3 in 10), rounded down."""
PARTS = ("linear", "trees")
"""The kinds of head averaged (``head.HEADS``), in order."""


@dataclass
class Blend:
    parts: list
    """The fitted heads (``PARTS``' kinds), each reading the same features."""
    kinds: tuple[str, ...] = PARTS
    """Each part's kind (``head.HEADS``), for ``to_dict``."""
    fine_odds: float = FINE_ODDS

    def __post_init__(self):
        if len(self.parts) != len(self.kinds) or not self.parts:
            raise ValueError(f"parts: expected one fitted head per kind of {self.kinds}, got {len(self.parts)}")
        counts = [h.n_features for h in self.parts]
        if len(set(counts)) != 1:
            raise ValueError(f"parts: expected heads that read the same features, got {counts}")
        if not math.isfinite(self.fine_odds) or self.fine_odds <= 0:
            raise ValueError(f"fine_odds: expected a positive number, got {self.fine_odds!r}")

    def probabilities(self, x: Tensor) -> Tensor:
        """[N, F] -> [N, 3] the parts' mean probabilities (Janus, blob, fine), fine's weighed by
        ``fine_odds``, normalised."""
        p = torch.stack([h.probabilities(x).double() for h in self.parts]).mean(0)
        p = p * torch.tensor([1.0, 1.0, self.fine_odds], dtype=p.dtype)
        return (p / p.sum(-1, keepdim=True)).float()

    @property
    def n_features(self) -> int:
        return self.parts[0].n_features

    def to_dict(self) -> dict:
        """The blend as ``head.load_head`` reads it (each part with its kind)."""
        return {"kind": "blend", "fine_odds": self.fine_odds,
                "parts": [{"kind": k, **h.to_dict()} for k, h in zip(self.kinds, self.parts)]}  # fmt: skip
