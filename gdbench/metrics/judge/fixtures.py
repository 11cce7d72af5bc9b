"""Results with a known class, made from the ground truth: the renderable failure fixtures
(``metrics/failures3d.py``) of every asset with a front, labelled by the labelling rule's letter,
as extra rows for the judge's head (the judge issue's "use the ground truth, not only the labels").

Which fixture is which class (``RULE_CLASSES``): the asset whole or turned about the vertical axis
is fine; its front wedge repeated around it (a face from every side) and its end-on outline from
every side in one colour (the sharpened rule: a frontal outline at the sides is front_everywhere,
face or no face) are front_everywhere; a front and its mirror image behind is second_face; the
asset spun into a single-coloured solid of revolution (no front, no profile) is blob.
``back-everywhere`` (the back from every side) is left out: by the rule it is a blob where its
sides look like a side and front_everywhere where they look like the front's outline, and which
depends on the asset. The chimeras, the blurred asset and the floaters are not failures of the rule.

Each fixture is read as a label sheet shows a result: six views at azimuths 0, 60, ..., 300 on the
run turntable's orbit. ``HELD_OUT`` assets give no rows, so that the tests' fixtures (the duck's)
stay out of the head's fit (their readings are still kept as the duck's references,
``reference.py``, which the head reads against but was never fitted on).
"""

from __future__ import annotations

import torch
from torch import Tensor

RULE_CLASSES = {
    "asset": "fine",
    "turned-90": "fine",
    "turned-180": "fine",
    "front-everywhere": "front_everywhere",
    "outline-everywhere": "front_everywhere",
    "two-faced": "second_face",
    "blob": "blob",
}
"""Fixture kind -> its class by the labelling rule."""
HELD_OUT = ("a yellow duck",)
"""Assets whose fixtures are never fitted on (the tests judge the duck's)."""


def fixture_views(caption: str, kind: str, size: int = 128) -> Tensor:
    """[6, size, size, 3] uint8: the fixture's six sheet views on the run turntable's orbit."""
    from gdbench.metrics.failures3d import failure_scene
    from gdbench.metrics.judge.judge import turntable_frames

    return torch.from_numpy(turntable_frames(failure_scene(caption, kind), size, frames=6))


def fixture_reading(eye, curves: dict, templates, caption: str, kind: str, known: dict | None = None) -> Tensor:
    """[F] features (``reading.result_features``) of the fixture ``kind`` of ``caption`` read from its
    six sheet views, or taken from ``known`` ({"caption/kind": features}: rows read before by the
    same eye, curves and templates) where it is there."""
    x = (known or {}).get(f"{caption}/{kind}")
    if x is None:
        from gdbench.metrics.judge.reading import result_features
        from gdbench.metrics.judge.sameness import SHEET

        x = result_features(eye, curves, fixture_views(caption, kind), torch.tensor(SHEET), caption, templates)[0]
    return torch.as_tensor(x, dtype=torch.float32)


def fixture_rows(eye, curves: dict, templates, captions, progress: bool = False,
                 known: dict | None = None) -> tuple[Tensor, list[str], list[str]]:  # fmt: skip
    """(features [N, F], labels [N], names [N] "caption/kind") of every fixture of ``RULE_CLASSES``
    for the ``captions`` that have a front and are not ``HELD_OUT`` (``fixture_reading``, from
    ``known`` where there)."""
    from gdbench.assets.library import has_front

    rows, labels, names = [], [], []
    todo = [c for c in captions if has_front(c) and c not in HELD_OUT]
    for i, caption in enumerate(todo):
        for kind, label in RULE_CLASSES.items():
            rows.append(fixture_reading(eye, curves, templates, caption, kind, known))
            labels.append(label)
            names.append(f"{caption}/{kind}")
        if progress:
            print(f"  judge fixtures: {i + 1}/{len(todo)} assets", flush=True)
    return torch.stack(rows), labels, names
