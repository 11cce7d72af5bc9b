"""The judge's readings against the asset's own fixtures (the seventh judge's; the eighth reads none).

A result's numbers (``reading.result_features``) say how its views read; what they should read
depends on the asset: its outline, colours and shape set what its whole, its front everywhere and
its blob look like. The ground truth gives each asset's own yardsticks for
free: its fixtures (``fixtures.py``) read the same way, six views each. The head reads a result's
numbers and, beside them, the same numbers less each ``REFERENCE`` fixture's of its asset
(``against``): how far the result is from the asset whole, from its front everywhere and from its
spun blob.

The fixtures' numbers (``reference_rows``) are kept in head.json (``references``), every asset
with a front, the tests' duck included (its rows are never fitted on: ``fixtures.HELD_OUT``). An
asset without a front has no front to repeat and no fixtures: its differences are zero, and
``head.decide`` gives it blob or fine only.
"""

from __future__ import annotations

import torch
from torch import Tensor

REFERENCE = ("asset", "front-everywhere", "blob")
"""The fixtures a result is read against (``fixtures.RULE_CLASSES``' kinds): fine, front_everywhere
and blob as the ground truth makes them."""


def reference_rows(eye, curves: dict, templates, captions, known: dict | None = None) -> dict[str, list[list[float]]]:
    """{caption: [len(REFERENCE)] rows of numbers} of every caption with a front: the ``REFERENCE``
    fixtures' features (six sheet views, ``fixtures.fixture_views``), taken from ``known``
    ({"caption/kind": row}, the fixture rows already read) where they are there."""
    from gdbench.assets.library import has_front
    from gdbench.metrics.judge.fixtures import fixture_reading

    return {
        caption: [fixture_reading(eye, curves, templates, caption, kind, known).tolist() for kind in REFERENCE]
        for caption in captions
        if has_front(caption)
    }


def against(x: Tensor, captions: list[str], references: dict) -> Tensor:
    """Features [N, F] of results of ``captions`` -> [N, (1 + len(REFERENCE)) F]: the numbers, then
    the numbers less each reference fixture's of the result's asset (zeros for an asset without a
    front, which has none). An asset with a front but no references, or references of another
    shape, is an error, never a silent zero."""
    from gdbench.assets.library import has_front

    if x.ndim != 2 or len(x) != len(captions):
        raise ValueError(f"x: expected [N, F] features of the {len(captions)} captions, got {tuple(x.shape)}")
    shape = (len(REFERENCE), x.shape[1])
    diffs = []
    for xi, c in zip(x, captions):
        if c not in references:
            if has_front(c):
                raise ValueError(f"references: none for {c!r}, an asset with a front")
            diffs.append(x.new_zeros(shape))
            continue
        ref = torch.tensor(references[c], dtype=x.dtype)
        if tuple(ref.shape) != shape:
            raise ValueError(f"references: {c!r} has rows of shape {tuple(ref.shape)}, the readings need {shape}")
        diffs.append(xi[None] - ref)
    return torch.cat([x, *torch.stack(diffs).unbind(1)], 1)


def names(features: list[str]) -> list[str]:
    """The names of ``against``'s numbers: ``features``, then ``vs_<kind>_<feature>`` per reference."""
    return [*features, *(f"vs_{k.replace('-', '_')}_{f}" for k in REFERENCE for f in features)]
