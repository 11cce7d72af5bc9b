"""Bring your own renderer (gdbench/refcheck/protocol.py, docs/references.md): a renderer written
outside the repository enters `gdbench compare` by module:function and is judged against the
float64 twin (the oracle: a dense float64 evaluation that shares no code with the renderer under
test) with PASS, FAIL or SKIP per scene; a broken one fails its cases in one line each while the
others still run."""

import sys
import textwrap

import pytest

OUTSIDE = '''
"""A renderer written outside gdbench: gsplat's torch stages behind the protocol."""
import torch


def rasterize(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *, background=None,
              outputs=("rgb", "alpha")):
    from renderers.gsplat_torch import rasterize as gs
    return gs(means, quats, scales, opacities, colors, viewmats, Ks, width, height, background=background,
              outputs=outputs)


def from_sh0(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
    assert colors.shape[1:] == (1, 3)
    return rasterize(means, quats, scales, opacities, 0.5 + 0.28209479177387814 * colors[:, 0], viewmats, Ks,
                     width, height, **kw)


def dimmed(*args, **kw):
    out = rasterize(*args, **kw)
    return type(out)(out.rgb * 0.98, out.alpha, None)


def broken(*args, **kwargs):
    raise RuntimeError("kernel launch failed")


def wrong_shape(means, quats, scales, opacities, colors, viewmats, Ks, width, height, **kw):
    class Out:
        rgb = torch.zeros(1, height, width)
        alpha = torch.zeros(1, height, width, 1)
    return Out()


NOT_A_FUNCTION = 3
'''


@pytest.fixture
def outside(tmp_path, monkeypatch):
    """A module ``outside_renderer`` on the path, as a renderer's own package would be."""
    (tmp_path / "outside_renderer.py").write_text(textwrap.dedent(OUTSIDE))
    monkeypatch.syspath_prepend(str(tmp_path))
    yield "outside_renderer"
    sys.modules.pop("outside_renderer", None)


def _rows(results):
    return {(r["scene"], r["renderer"]): r for res in results.values() for r in res.rows}


def test_an_outside_renderer_passes_and_a_wrong_one_fails_each_case(outside, tmp_path):
    from gdbench.refcheck.compare import run

    refs = [f"{outside}:{f}" for f in ("rasterize", "dimmed", "broken", "wrong_shape", "NOT_A_FUNCTION")]
    refs.append("no_such_module_here:fn")
    results = run(["crossing", "isotropic"], out=tmp_path / "cmp", renderers=refs, verbose=False)
    rows = _rows(results)
    for scene in ("crossing", "isotropic"):
        good = rows[(scene, f"{outside}:rasterize")]
        assert good["verdict"] == "PASS" and good["max_abs"] <= 1e-4, good
        dim = rows[(scene, f"{outside}:dimmed")]
        assert dim["verdict"] == "FAIL" and "rgb max error" in dim["reason"]  # the twin sees it
        assert "kernel launch failed" in rows[(scene, f"{outside}:broken")]["reason"]
        assert "rgb should be a float tensor" in rows[(scene, f"{outside}:wrong_shape")]["reason"]
        assert "not a function" in rows[(scene, f"{outside}:NOT_A_FUNCTION")]["reason"]
        assert "cannot import 'no_such_module_here'" in rows[(scene, "no_such_module_here:fn")]["reason"]
        assert all("\n" not in r.get("reason", "") for r in rows.values())
    assert not any(r["renderer"] in ("splat", "gsplat_torch") for r in rows.values())  # only those asked for


def test_colours_as_sh0_and_what_a_renderer_lacks_is_skipped(outside, tmp_path):
    from gdbench.refcheck.compare import run
    from gdbench.refcheck.protocol import REGISTERED, register_renderer

    fn = __import__(outside).from_sh0
    try:
        register_renderer("mine_sh0", fn, colors="sh0")
        register_renderer("mine_cuda", fn, colors="sh0", device="cuda")
        results = run("crossing", out=tmp_path / "cmp", renderers=["mine_sh0", "mine_cuda"], verbose=False)
    finally:
        REGISTERED.pop("mine_sh0", None)
        REGISTERED.pop("mine_cuda", None)
    rows = _rows(results)
    assert rows[("crossing", "mine_sh0")]["verdict"] == "PASS"
    import torch

    skipped = results["crossing"].skipped
    if not torch.cuda.is_available():
        assert [s["renderer"] for s in skipped] == ["mine_cuda"] and skipped[0]["verdict"] == "SKIP"
        assert "CUDA" in skipped[0]["reason"]


def test_registration_refuses_a_builtin_name_and_bad_specs(outside):
    from gdbench.refcheck.protocol import RendererSpec, register_renderer

    fn = __import__(outside).rasterize
    with pytest.raises(ValueError, match="not a built-in backend"):
        register_renderer("splat", fn)
    with pytest.raises(ValueError, match="colors must be 'rgb' or 'sh0'"):
        RendererSpec("x", fn, colors="sh3")
    with pytest.raises(ValueError, match="expected a callable"):
        RendererSpec("x", 3)


def test_compare_exits_non_zero_when_a_case_fails(outside, tmp_path):
    from gdbench.app.cli import main
    from gdbench.app.cmd_refs import Compare

    ok = main(Compare(scene="crossing", out=tmp_path / "a", renderer=(f"{outside}:rasterize",)))
    assert ok == {"crossing": {"rows": 2, "skipped": 0}}
    with pytest.raises(SystemExit, match=r"1 case\(s\) FAIL: crossing/outside_renderer:broken"):
        main(Compare(scene="crossing", out=tmp_path / "b", renderer=(f"{outside}:broken",)))
