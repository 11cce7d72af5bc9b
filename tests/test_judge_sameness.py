"""The judge's sameness reading (gdbench/metrics/judge/sameness.py): its templates drawn and kept,
its numbers against closed forms, and the judge folder's parts checked against its head."""

from __future__ import annotations

import shutil
from types import SimpleNamespace

import pytest
import torch

from gdbench.metrics.judge.sameness import BINS, SAMENESS, SHEET, Templates, sameness_features, sheet_picks

SIX = torch.tensor(SHEET)


def _fake_data(n_per: int = 90, captions=("a", "b"), variants: int = 2, seed: int = 0):
    """A stand-in for the eye's data: random crops at random cameras, elevations 0-30."""
    g = torch.Generator().manual_seed(seed)
    n = n_per * len(captions) * variants
    caption = torch.arange(len(captions)).repeat_interleave(n_per * variants)
    variant = torch.arange(variants).repeat_interleave(n_per).repeat(len(captions))
    crops = torch.rand(n, 3, 32, 32, generator=g)
    return crops, SimpleNamespace(
        captions=tuple(captions), caption=caption, variant=variant,
        azimuth=torch.rand(n, generator=g) * 360, elevation=torch.rand(n, generator=g) * 30,
    )  # fmt: skip


def test_templates_are_the_renders_nearest_each_azimuth_and_read_back(tmp_path):
    crops, data = _fake_data()
    t = Templates.from_data(crops, data)
    for ci, cap in enumerate(data.captions):
        assert t.crops[cap].shape == (BINS * 2, 3, 32, 32) and t.crops[cap].dtype == torch.uint8
        for k in range(len(t.azimuth[cap])):
            target = (k % BINS) * 360.0 / BINS
            sel = (data.caption == ci) & (data.variant == t.variant[cap][k])
            d = ((data.azimuth[sel] - target + 180) % 360 - 180).abs() + (data.elevation[sel] - 15).abs()
            i = int(d.argmin())  # brute force over every render of that caption and variant
            assert float(t.azimuth[cap][k]) == float(data.azimuth[sel][i])
            want = (crops[sel][i] * 255).round().to(torch.uint8)
            assert torch.equal(t.crops[cap][k], want)
    t.save(tmp_path / "t.safetensors", {"commit": "x"})
    back = Templates.load(tmp_path / "t.safetensors")
    for kind in ("crops", "azimuth", "variant"):
        for cap in data.captions:
            assert torch.equal(getattr(back, kind)[cap], getattr(t, kind)[cap])


def _asset_views(t: Templates, cap: str, azimuths) -> torch.Tensor:
    """The templates' own crops nearest ``azimuths`` (variant 0), as floats in [0, 1]."""
    a = t.azimuth[cap]
    pick = [int((((a - x + 180) % 360 - 180).abs() + 1000 * t.variant[cap]).argmin()) for x in azimuths]
    return t.crops[cap][pick].float() / 255.0


def _blob_crops(n: int, g: torch.Generator) -> torch.Tensor:
    """White crops with a coloured disc off centre at a random place: an object, a silhouette."""
    yy, xx = torch.meshgrid(torch.arange(32.0), torch.arange(32.0), indexing="ij")
    out = torch.ones(n, 3, 32, 32)
    for i in range(n):
        cy, cx = (torch.rand(2, generator=g) * 12 + 10).tolist()
        r = float(torch.rand((), generator=g) * 5 + 5)
        disc = ((yy - cy) ** 2 + (xx - cx) ** 2) <= r * r
        out[i][:, disc] = torch.rand(3, 1, generator=g) * 0.6
    return out


def _one_variant_templates(seed: int) -> tuple[torch.Tensor, Templates]:
    """(crops, templates) of one caption "a" with one variant: a disc crop every 10 degrees at the
    turntables' elevation, so that each template is exactly one crop."""
    crops = _blob_crops(BINS, torch.Generator().manual_seed(seed))
    data = SimpleNamespace(captions=("a",), caption=torch.zeros(BINS, dtype=torch.long),
                           variant=torch.zeros(BINS, dtype=torch.long),
                           azimuth=torch.arange(BINS) * 360.0 / BINS, elevation=torch.full((BINS,), 15.0))  # fmt: skip
    return crops, Templates.from_data(crops, data)


def test_sameness_against_closed_forms():
    """Six copies of one view correlate perfectly (sameness 1); a result made of the asset's own
    views, with one variant, is exactly as alike as the asset (relative sameness 0) and matches its
    front better than its sides only where it shows the front; the numbers follow the views' order
    and not their count (a turntable's 36 frames read as the six nearest the sheet's azimuths)."""
    crops, t = _one_variant_templates(3)
    same = dict(zip(SAMENESS, sameness_features(crops[:1].expand(6, -1, -1, -1), SIX, t, "a").tolist()))
    assert same["same_colour"] == pytest.approx(1.0, abs=1e-5)
    assert same["same_outline"] == pytest.approx(1.0, abs=1e-5)
    own = _asset_views(t, "a", SHEET)
    f = dict(zip(SAMENESS, sameness_features(own, SIX, t, "a").tolist()))
    assert f["same_colour_rel"] == pytest.approx(0.0, abs=1e-5)
    assert f["same_outline_rel"] == pytest.approx(0.0, abs=1e-5)
    front = sameness_features(_asset_views(t, "a", [0.0] * 6), SIX, t, "a")
    side = sameness_features(_asset_views(t, "a", [90.0] * 6), SIX, t, "a")
    assert float(front[2]) > 0 > float(side[2])  # a perfect match to a front template, or to a side one
    thirty_six = torch.arange(36) * 10.0
    frames = _asset_views(t, "a", thirty_six.tolist())
    assert torch.equal(sheet_picks(thirty_six), torch.arange(0, 36, 6))
    assert torch.allclose(sameness_features(frames, thirty_six, t, "a"), sameness_features(own, SIX, t, "a"), atol=1e-6)


def test_the_aligned_numbers_against_closed_forms():
    """The asset's own six views match it where their cameras are (aligned 1, nothing fits better,
    the front fits no better than the view's own side); six copies of the front view match the
    front template perfectly everywhere, so each side view's number is its correlation with the
    template where its camera is, less 1, checked here by brute force over the templates."""
    from gdbench.metrics.judge.sameness import ALIGNED, ALIGNED_DEG, _colour_and_outline

    _, t = _one_variant_templates(5)
    names = SAMENESS[-ALIGNED:]
    own_views = _asset_views(t, "a", SHEET)
    own = dict(zip(names, sameness_features(own_views, SIX, t, "a")[-ALIGNED:].tolist()))
    assert own["aligned"] == pytest.approx(1.0, abs=1e-5) and own["aligned_min"] == pytest.approx(1.0, abs=1e-5)
    assert own["aligned_over_best"] == pytest.approx(0.0, abs=1e-5)
    r, _ = _colour_and_outline(t.crops["a"].float() / 255.0)
    u_own, _ = _colour_and_outline(own_views)
    front_k = [k for k in range(len(r)) if abs((float(t.azimuth["a"][k]) + 180) % 360 - 180) <= ALIGNED_DEG]
    best_front = [max(float(u_own[v] @ r[k]) for k in front_k) for v in range(1, 6)]
    assert own["aligned_over_front"] == pytest.approx(sum(1.0 - b for b in best_front) / 5, abs=1e-5)
    fronts = _asset_views(t, "a", [0.0] * 6)
    got = dict(zip(names, sameness_features(fronts, SIX, t, "a")[-ALIGNED:].tolist()))
    u, _ = _colour_and_outline(fronts[:1])
    sides = []
    for view_az in SHEET[1:]:
        near = [k for k in range(len(r)) if abs((float(t.azimuth["a"][k]) - view_az + 180) % 360 - 180) <= ALIGNED_DEG]
        sides.append(max(float(u[0] @ r[k]) for k in near))
    assert got["aligned_over_front"] == pytest.approx(sum(s - 1.0 for s in sides) / 5, abs=1e-5)
    assert got["aligned_min"] == pytest.approx(min(sides), abs=1e-5) and got["aligned_over_best"] < 0
    assert got["aligned"] == pytest.approx((1.0 + sum(sides)) / 6, abs=1e-5)
    # the views' own azimuths, not the sheet's: the asset's views 20 degrees on from the sheet's,
    # at their cameras, match where they are (a reading at the sheet's azimuths would not: 20 > 15)
    on = [x + 20.0 for x in SHEET]
    shifted = sameness_features(_asset_views(t, "a", on), torch.tensor(on), t, "a")[-ALIGNED:]
    assert float(shifted[0]) == pytest.approx(1.0, abs=1e-5) and float(shifted[1]) == pytest.approx(0.0, abs=1e-5)
    keep = torch.tensor([0, 1, 2, 8, 9])  # renders at 0-20 and 80-90 degrees only: none near 180
    far = Templates({"a": t.crops["a"][keep]}, {"a": t.azimuth["a"][keep]}, {"a": t.variant["a"][keep]})
    with pytest.raises(ValueError, match="no render of the asset within 15 degrees of a view"):
        sameness_features(own_views, SIX, far, "a")
    keep = torch.tensor([0, 1])  # no side at all
    bare = Templates({"a": t.crops["a"][keep]}, {"a": t.azimuth["a"][keep]}, {"a": t.variant["a"][keep]})
    with pytest.raises(ValueError, match="no render of the asset within 30 degrees of its front or between"):
        sameness_features(own_views, SIX, bare, "a")


def test_a_judge_folder_whose_parts_do_not_fit_its_head_is_refused(tmp_path):
    """The shipped judge reads the templates' features (sameness, and from the fourth version the
    look); without its templates its head cannot read, which is one clear error; changed templates
    change the judge's version."""
    from gdbench.metrics.judge.judge import WEIGHTS, Judge

    if not (WEIGHTS / "templates.safetensors").is_file():
        pytest.fail(f"the shipped judge has no templates in {WEIGHTS}: run `gdbench train-judge`")
    for name in ("eye.safetensors", "head.json"):
        shutil.copy(WEIGHTS / name, tmp_path / name)
    with pytest.raises(ValueError, match=r"templates\.safetensors"):
        Judge(tmp_path)
    shipped = Judge(WEIGHTS)
    t = shipped.templates
    cap = next(iter(t.crops))
    t.crops[cap] = 255 - t.crops[cap]
    t.save(tmp_path / "templates.safetensors")
    changed = Judge(tmp_path)
    assert changed.version != shipped.version
    assert len(changed.feature_names()) == changed.head.n_features == shipped.n_features > 26


def test_an_earlier_judges_head_reads_the_features_it_was_fitted_on(tmp_path):
    """Regression heads over 26 and 30 features (the second and third versions' shapes) read the
    first 26 and 30 of the readings, the same numbers the shipped (eighth, 57: the look and the
    front reading too) judge's first ones are; a head over a count no version had is refused."""
    import json

    from gdbench.metrics.judge.head import fit
    from gdbench.metrics.judge.judge import WEIGHTS, Judge

    for name in ("eye.safetensors", "templates.safetensors"):
        shutil.copy(WEIGHTS / name, tmp_path / name)
    info = json.loads((WEIGHTS / "head.json").read_text())
    info.pop("references", None)  # the earlier versions (the seventh aside) read no references
    g = torch.Generator().manual_seed(0)
    labels = ["front_everywhere", "blob", "fine"] * 20
    info["head"] = fit(torch.randn(60, 30, generator=g), labels).to_dict()
    (tmp_path / "head.json").write_text(json.dumps(info))
    third = Judge(tmp_path)
    info["head"] = {k: v[:26] if k in ("mean", "scale", "weight") else v for k, v in info["head"].items()}
    (tmp_path / "head.json").write_text(json.dumps(info))
    second, shipped = Judge(tmp_path), Judge(WEIGHTS)
    assert second.n_features == 26 and third.n_features == 30 and shipped.n_features == 57
    assert second.feature_names() == shipped.feature_names()[:26]
    assert third.feature_names() == shipped.feature_names()[:30]
    g = torch.Generator().manual_seed(1)
    views = (torch.rand(6, 64, 64, 3, generator=g) * 255).to(torch.uint8)
    views[:, 16:48, 20:44] = torch.tensor([200, 150, 40], dtype=torch.uint8)
    views[:, :16] = 255
    x2, _ = second.features(views, SIX, "a yellow duck")
    x3, _ = third.features(views, SIX, "a yellow duck")
    x4, _ = shipped.features(views, SIX, "a yellow duck")
    assert x2.shape == (26,) and torch.equal(x2, x4[:26]) and torch.equal(x3, x4[:30])
    info["head"] = {k: v[:23] if k in ("mean", "scale", "weight") else v for k, v in info["head"].items()}
    (tmp_path / "head.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="reads 23 features"):
        Judge(tmp_path)
