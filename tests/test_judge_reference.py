"""The judge's readings against the asset's own fixtures (gdbench/metrics/judge/reference.py, the
seventh judge's): the differences against a closed form, the seventh's references against a fresh
reading of the fixtures they stand for, and a judge folder whose head and references disagree
refused. The seventh is made again from the shipped eye and templates and its kept head
(``judge.with_head``), and must come out as the version its fresh sets recorded."""

from __future__ import annotations

import json
import shutil

import pytest
import torch

from gdbench.metrics.judge.reference import REFERENCE, against, names
from gdbench.metrics.judge.sameness import SHEET

SIX = torch.tensor(SHEET)


def test_the_differences_are_the_numbers_less_each_reference():
    g = torch.Generator().manual_seed(0)
    x = torch.randn(3, 5, generator=g, dtype=torch.float64)
    refs = {"a duck": torch.randn(len(REFERENCE), 5, generator=g, dtype=torch.float64).tolist()}
    out = against(x, ["a duck", "a hamburger", "a duck"], refs)
    assert out.shape == (3, 5 * (1 + len(REFERENCE)))
    assert torch.equal(out[:, :5], x)
    for k in range(len(REFERENCE)):
        block = out[:, 5 * (k + 1) : 5 * (k + 2)]
        for i in (0, 2):  # x[i] - ref[k], element by element
            assert block[i].tolist() == [a - b for a, b in zip(x[i].tolist(), refs["a duck"][k])]
        assert torch.count_nonzero(block[1]) == 0  # no references: no front, no difference
    assert names(["p", "q"])[:2] == ["p", "q"] and names(["p", "q"])[2:4] == ["vs_asset_p", "vs_asset_q"]
    assert len(names(["p"] * 5)) == out.shape[1]
    with pytest.raises(ValueError, match="x: expected"):
        against(x, ["a duck"], refs)
    with pytest.raises(ValueError, match="references: none for 'a yellow duck'"):
        against(x, ["a duck", "a hamburger", "a yellow duck"], refs)  # a front, no references: never zeros
    with pytest.raises(ValueError, match=r"shape \(3, 4\)"):
        against(x, ["a duck", "a hamburger", "a duck"], {"a duck": [r[:4] for r in refs["a duck"]]})


SEVENTH = "c18485a29831"
"""The seventh judge's version, as its fresh sets' agreement.csv record it."""


@pytest.fixture(scope="module")
def seventh(tmp_path_factory):
    from gdbench.metrics.judge.judge import SEVENTH_HEAD, Judge, with_head

    judge = Judge(with_head(SEVENTH_HEAD, tmp_path_factory.mktemp("seventh")))
    assert judge.version == SEVENTH and judge.references is not None
    return judge


def test_the_seventh_references_are_the_fixtures_read_afresh(seventh):
    """The duck's references (kept in head.json though the duck is never fitted on) are its asset,
    front-everywhere and blob fixtures read as a sheet shows them: the judge reading the duck's
    asset fixture finds itself at zero from the asset and, from the blob, the difference of the
    two fixtures' readings, each computed here from the renders."""
    from gdbench.metrics.judge.fixtures import HELD_OUT, fixture_views
    from gdbench.metrics.judge.reading import result_features

    judge = seventh
    caption = HELD_OUT[0]
    assert caption in judge.references and all(f"{caption}/" not in n for n in judge.head_info["fixture_rows"]["names"])
    x, _ = judge.features(fixture_views(caption, "asset"), SIX, caption)
    f = len(x) // (1 + len(REFERENCE))

    def read(kind: str) -> torch.Tensor:  # the readings a reference holds: the first f (the 50)
        views = fixture_views(caption, kind)
        return result_features(judge.eye, judge.curves, views, SIX, caption, judge.templates)[0][:f]

    asset, blob = read("asset"), read("blob")
    assert float(x[:f].abs().sum()) > 1  # the numbers themselves are not empty
    assert torch.allclose(x[f : 2 * f], torch.zeros(f), atol=1e-4)
    k = REFERENCE.index("blob") + 1
    assert torch.allclose(x[k * f : (k + 1) * f], asset - blob, atol=1e-4)
    assert float((asset - blob).abs().max()) > 0.05  # the blob reads otherwise than the asset


def test_a_folder_whose_head_and_references_disagree_is_refused(tmp_path, seventh):
    from gdbench.metrics.judge.head import fit
    from gdbench.metrics.judge.judge import SEVENTH_HEAD, WEIGHTS, Judge

    for name in ("eye.safetensors", "templates.safetensors"):
        shutil.copy(WEIGHTS / name, tmp_path / name)
    info = json.loads(SEVENTH_HEAD.read_text())
    without = {k: v for k, v in info.items() if k != "references"}
    (tmp_path / "head.json").write_text(json.dumps(without))
    with pytest.raises(ValueError, match=r"reads 200 features.*references that head\.json does not keep"):
        Judge(tmp_path)  # a head over the differences with nothing to take them from
    (tmp_path / "head.json").write_text(json.dumps(info | {"reference_kinds": list(reversed(REFERENCE))}))
    with pytest.raises(ValueError, match="keeps references of"):
        Judge(tmp_path)  # references in another order would be read against the wrong fixtures
    g = torch.Generator().manual_seed(0)
    info["head"] = fit(torch.randn(60, 50, generator=g), ["front_everywhere", "blob", "fine"] * 20).to_dict()
    (tmp_path / "head.json").write_text(json.dumps(info))
    with pytest.raises(ValueError, match="reads 50 features"):
        Judge(tmp_path)  # references kept for a head that does not read them
