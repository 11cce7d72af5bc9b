"""The front marking (gdbench/metrics/judge/marking.py) against hand-made assets whose answer is
known in closed form, and on the shipped templates against the assets' own renders."""

from __future__ import annotations

import pytest
import torch

from gdbench.metrics.judge.marking import (
    CLIP,
    FLOOR,
    LEVELS,
    MARKING,
    colour_index,
    front_colours,
    marked_share,
    marking_features,
    scaled,
)

BLUE, RED, WHITE = (0.1, 0.2, 0.9), (0.9, 0.1, 0.1), (1.0, 1.0, 1.0)


def _crop(body, patch=None, patch_px: int = 0, size: int = 16) -> torch.Tensor:
    """[3, size, size]: white, a body square of ``body`` colour (8 x 8 at the centre), its top
    ``patch_px`` rows of ``patch`` colour."""
    x = torch.tensor(WHITE)[:, None, None].repeat(1, size, size)
    x[:, 4:12, 4:12] = torch.tensor(body)[:, None, None]
    if patch is not None and patch_px:
        x[:, 4 : 4 + patch_px, 4:12] = torch.tensor(patch)[:, None, None]
    return x


def _index(c) -> int:
    q = [min(int(v * (LEVELS - 1e-4)), LEVELS - 1) for v in c]
    return q[0] * LEVELS * LEVELS + q[1] * LEVELS + q[2]


def _asset(patch_px: int = 2):
    """A blue asset with a red patch (``patch_px`` of its 8 rows) at the front (azimuths within 30
    degrees of 0) and none elsewhere: renders every 30 degrees."""
    az = torch.arange(12) * 30.0
    off = (az + 180) % 360 - 180
    crops = torch.stack([_crop(BLUE, RED, patch_px) if abs(a) <= 30 else _crop(BLUE) for a in off.tolist()])
    return crops, az


class _Templates:
    def __init__(self, crops, az):
        self.crops, self.azimuth = {"toy": (crops * 255).round().byte()}, {"toy": az}


def test_colour_index_and_ink_by_hand():
    x = torch.stack([_crop(BLUE, RED, 2)])
    colour, ink = colour_index(x)
    assert int(ink.sum()) == 64  # the 8 x 8 body; white is not ink
    assert int((colour[ink > 0] == _index(RED)).sum()) == 16 and int((colour[ink > 0] == _index(BLUE)).sum()) == 48


def test_the_front_colour_is_the_patch_and_the_shares_are_closed_form():
    crops, az = _asset(patch_px=2)
    mask, front, other = front_colours(crops, az)
    assert bool(mask[_index(RED)]) and not bool(mask[_index(BLUE)])
    assert int(mask.sum()) == 1
    assert front == pytest.approx(16 / 64) and other == pytest.approx(0.0)


def test_an_asset_with_no_front_colour_marks_nothing():
    az = torch.arange(12) * 30.0
    crops = torch.stack([_crop(BLUE) for _ in az])
    mask, front, other = front_colours(crops, az)
    assert int(mask.sum()) == 0 and front == 0.0 and other == 0.0


@pytest.mark.parametrize(
    "views, expected",
    [
        ("front everywhere", (1.0, 1.0, 1.0, 1.0)),
        ("whole", (1 / 6, 1.0, 0.0, 1 / 6)),
        ("blob", (0.0, 0.0, 0.0, 0.0)),
    ],
)
def test_the_four_numbers_of_a_front_everywhere_a_whole_result_and_a_blob(views, expected):
    crops, az = _asset(patch_px=2)
    templates = _Templates(crops, az)
    front, plain = _crop(BLUE, RED, 2), _crop(BLUE)
    six = {"front everywhere": [front] * 6, "whole": [front] + [plain] * 5, "blob": [plain] * 6}[views]
    got = marking_features(torch.stack(six), templates, "toy")
    scale = (16 / 64) / (16 / 64 + FLOOR)  # a front view scaled: the floor keeps it just under 1
    want = torch.tensor(expected) * torch.tensor([scale, scale, scale, 1.0])
    assert len(got) == len(MARKING)
    assert torch.allclose(got, want, atol=1e-6)


def test_scaling_and_its_clip():
    s = scaled(torch.tensor([0.0, 0.1, 0.2, 5.0]), front=0.2, other=0.0)
    assert torch.allclose(s, torch.tensor([0.0, 0.1 / 0.22, 0.2 / 0.22, CLIP[1]]))
    assert float(scaled(torch.tensor([-9.0]), 0.2, 0.1)[0]) == CLIP[0]


def test_marked_share_of_a_crop_without_object_is_zero():
    x = torch.ones(1, 3, 8, 8)
    colour, ink = colour_index(x)
    assert float(marked_share(colour, ink, torch.ones(LEVELS**3, dtype=torch.bool))[0]) == 0.0


def test_renders_without_a_front_or_without_sides_are_refused():
    crops, _ = _asset()
    with pytest.raises(ValueError, match="azimuth"):
        front_colours(crops, torch.full((12,), 90.0))  # no front
    with pytest.raises(ValueError, match="azimuth"):
        front_colours(crops, torch.full((12,), 10.0))  # a front, no side or back


def test_another_templates_object_is_never_handed_the_first_ones_colours():
    """The per-asset answer is kept on each templates object: a second object under the same
    caption (whatever id it is given once the first is freed) reads its own asset, here one with no
    front colour, which marks nothing; an unknown caption is a clear error."""
    crops, az = _asset(patch_px=2)
    six = torch.stack([_crop(BLUE, RED, 2)] * 6)
    assert float(marking_features(six, _Templates(crops, az), "toy")[0]) > 0.5
    second = _Templates(torch.stack([_crop(BLUE)] * 12), az)  # may take the freed first's id
    assert torch.equal(marking_features(six, second, "toy"), torch.zeros(4))
    with pytest.raises(ValueError, match="caption"):
        marking_features(six, second, "no such asset")


def test_on_the_shipped_templates_the_teapots_label_marks_its_front():
    """The shipped judge's renders of the blue teapot: its front colours hold the label's yellow
    (red and green high, blue low) and not the body's blue; its own front renders read near 1 and
    its back renders near 0 (the renders themselves are the oracle: no label enters)."""
    from gdbench.metrics.judge.judge import load_judge

    judge = load_judge()
    crops, az = judge.templates.crops["a blue teapot"], judge.templates.azimuth["a blue teapot"]
    mask, front, other = front_colours(crops, az)
    i = torch.arange(LEVELS**3)
    r, g, b = i // (LEVELS * LEVELS), (i // LEVELS) % LEVELS, i % LEVELS
    yellow = (r >= LEVELS // 2) & (g >= LEVELS // 2) & (b < LEVELS // 2)
    assert bool((mask & yellow).any()) and not bool((mask & (b >= LEVELS // 2) & (r < LEVELS // 2)).any())
    assert front > 0.05 > other
    off = ((az + 180) % 360 - 180).abs()
    x = crops.float() / 255
    at_front = marking_features(x[off <= 15], judge.templates, "a blue teapot")
    at_back = marking_features(x[off >= 165], judge.templates, "a blue teapot")
    assert float(at_front[0]) > 0.7 and float(at_back[1]) < 0.2


def test_outline_matches_are_one_for_the_assets_own_renders_and_lower_for_another_shape():
    """A view that is one of the asset's renders matches it exactly (correlation 1); a view that is
    the asset's side matches the front less; a round blob matches the asset less than its renders
    do (the correlations computed here by hand from the blurred silhouettes)."""
    from gdbench.metrics.judge.marking import OUTLINE, outline_features
    from gdbench.metrics.judge.sameness import _colour_and_outline

    az = torch.arange(12) * 30.0
    off = ((az + 180) % 360 - 180).abs()
    crops = []
    for a in off.tolist():  # tall and narrow at the front and back, wide at the sides
        x = torch.ones(3, 32, 32)
        half = int(4 + 10 * abs(torch.sin(torch.deg2rad(torch.tensor(a)))))
        x[:, 6:26, 16 - half : 16 + half] = torch.tensor(BLUE)[:, None, None]
        crops.append(x)
    crops = torch.stack(crops)
    templates = _Templates(crops, az)
    own = outline_features(crops[[0, 0, 0]], templates, "toy")
    assert len(own) == len(OUTLINE) and torch.allclose(own, torch.ones(3), atol=1e-3)
    side = outline_features(crops[[3]], templates, "toy")
    assert float(side[1]) == pytest.approx(1.0, abs=1e-3) and float(side[0]) < 0.95
    yy, xx = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    ball = torch.ones(3, 32, 32)
    ball[:, ((yy - 16) ** 2 + (xx - 16) ** 2) < 36] = torch.tensor(BLUE)[:, None]
    got = outline_features(ball[None], templates, "toy")
    _, v = _colour_and_outline(ball[None])
    _, r = _colour_and_outline(templates.crops["toy"].float() / 255)
    assert float(got[1]) == pytest.approx(float((v @ r.T).max()), abs=1e-5) and float(got[1]) < 0.95
