"""Conformance: images and gradients against the float64 twin, PASS/FAIL/SKIP against stated
tolerances (gdbench/refcheck/conformance.py), the stiff cases' table and the bring-your-own paths."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from gdbench.refcheck import conformance as cf
from gdbench.refcheck import tolerance as tl
from gdbench.refcheck.protocol import RendererSpec, builtin, load_renderer

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "examples" / "gsplat_renderer.py"


def _flip(group: int, how):
    """splat_torch with the gradient of one of its inputs changed by ``how`` (a bug to catch)."""
    from renderers.splat import rasterize

    class Hook(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.view_as(x)

        @staticmethod
        def backward(ctx, g):
            return how(g)

    def fn(*args, **kw):
        args = list(args)
        args[group] = Hook.apply(args[group])
        return rasterize(*args, **kw, backend="torch")

    return RendererSpec("flipped", fn)


def test_every_exact_builtin_passes_every_case_against_the_twin():
    rows = cf.run([builtin("splat"), builtin("splat_torch")], progress=False)
    assert len(rows) == 2 * len(cf.case_names())
    bad = [(r["case"], r["renderer"], r["reason"]) for r in rows if r["verdict"] != "PASS"]
    assert not bad
    drawn = [r for r in rows if r["alpha_max_twin"] > 0.05]
    assert len(drawn) >= len(rows) - 2 * 4  # only the empty, behind-camera and invisible cases draw nothing
    # gradients were compared where something is drawn: a real, non-zero error against the twin
    assert all(r["grad_err"] is not None for r in rows) and max(r["grad_err"] for r in drawn) > 0


@pytest.mark.parametrize(
    "case, group, how, expect",
    [
        # the C++ backward's old bug, as the twin sees it: the scales' gradient negated and x/y swapped
        ("huge scale 1e4", 2, lambda g: -g[:, [1, 0, 2]], "scales gradient"),
        ("huge scale 1e4", 0, lambda g: g * torch.tensor([1.0, 1.0, -1.0]), "means gradient"),
        ("anisotropy 1e6", 2, lambda g: g * 1.01, "scales gradient"),  # a 1% error in one group
        ("anisotropic", 3, lambda g: -g, "opacities gradient"),
    ],
)
def test_a_wrong_gradient_fails_its_case_and_names_the_group(case, group, how, expect):
    make = cf.case_names()[case]
    row = cf.check(_flip(group, how), make())
    assert row["verdict"] == "FAIL" and expect in row["reason"]
    if "wrong sign" not in row["reason"]:
        assert case == "anisotropy 1e6"  # a scaled gradient keeps its sign
    # the same renderer with the gradient untouched passes the same case
    assert cf.check(_flip(group, lambda g: g), make())["verdict"] == "PASS"


def test_image_errors_fail_and_a_failing_renderer_fails_only_its_own_cases():
    from renderers.splat import rasterize

    def dim(*a, **k):
        out = rasterize(*a, **k)
        return type(out)(rgb=out.rgb * (1 - 1e-3), alpha=out.alpha)

    def broken(*a, **k):
        raise RuntimeError("kernel launch failed\nsecond line")

    rows = cf.run([RendererSpec("dim", dim), RendererSpec("broken", broken), builtin("splat")],
                  ["isotropic", "zero quaternion"], progress=False)  # fmt: skip
    by = {(r["renderer"], r["case"]): r for r in rows}
    assert by[("dim", "isotropic")]["verdict"] == "FAIL" and "rgb max error" in by[("dim", "isotropic")]["reason"]
    assert by[("broken", "zero quaternion")]["reason"] == "RuntimeError: kernel launch failed"
    assert all(by[("splat", c)]["verdict"] == "PASS" for c in ("isotropic", "zero quaternion"))
    counts = cf.summary(rows)
    assert counts["broken"]["FAIL"] == 2 and counts["splat"]["PASS"] == 2


def test_what_a_renderer_lacks_is_a_skip_with_its_reason():
    from renderers.splat import rasterize

    images_only = RendererSpec("nograd", lambda *a, **k: rasterize(*a, **k), gradients=False)
    row = cf.check(images_only, cf.case_names()["anisotropy 1e6"]())
    assert row["verdict"] == "PASS" and row["grad_err"] is None and "declares no gradients" in row["reason"]
    cuda = RendererSpec("gpu", rasterize, device="cuda")
    if not torch.cuda.is_available():
        row = cf.check(cuda, cf.case_names()["isotropic"]())
        assert row["verdict"] == "SKIP" and "CUDA" in row["reason"]
    # the approximate class does not apply where the ray tracer's model differs by construction
    ray = RendererSpec("ray", rasterize, tolerance="approximate")
    row = cf.check(ray, cf.case_names()["huge scale 1e4"]())
    assert row["verdict"] == "SKIP" and "by construction" in row["reason"]


def test_a_missing_or_malformed_tolerance_is_an_error_at_load(tmp_path, monkeypatch):
    from gdbench.refcheck import scenes

    with pytest.raises(ValueError, match="no 'tolerances' block"):
        tl.parse_tolerances(None, "fixture 'x'")
    with pytest.raises(ValueError, match=r"missing \['approximate'\]"):
        tl.parse_tolerances({"exact": "n/a"}, "fixture 'x'")
    with pytest.raises(ValueError, match=r"missing \['grad_atol'\]"):
        tl.Tolerance.parse({"mean_abs": 1, "max_abs": 1, "grad_rel": 1, "grad_floor": 1}, "x.exact")
    with pytest.raises(ValueError, match="not a positive number"):
        tl.Tolerance.parse({"mean_abs": 0, "max_abs": 1, "gradients": "none"}, "x.exact")
    spec = json.loads((scenes.FIXTURE_DIR / "isotropic.json").read_text())
    del spec["tolerances"]["exact"]
    (tmp_path / "isotropic.json").write_text(json.dumps(spec))
    monkeypatch.setattr(scenes, "FIXTURE_DIR", tmp_path)
    with pytest.raises(ValueError, match="fixture 'isotropic': tolerance classes missing"):
        scenes.load_fixture("isotropic")
    stated = json.loads(cf.STIFF_TOLERANCES.read_text())
    del stated["zero quaternion"]
    (tmp_path / "stiff.json").write_text(json.dumps(stated))
    monkeypatch.setattr(cf, "STIFF_TOLERANCES", tmp_path / "stiff.json")
    with pytest.raises(ValueError, match=r"case 'zero quaternion'.*no 'tolerances' block"):
        cf.stiff_case("zero quaternion")


def test_every_case_states_both_classes_and_the_huge_scale_allowance_judges_its_sign():
    for name, make in cf.case_names().items():
        case = make()
        assert set(case.tolerances) == set(tl.CLASSES), name
    huge = cf.stiff_case("huge scale 1e4").tolerances["exact"]
    gs = cf.twin(cf.stiff_case("huge scale 1e4"), 0.99)[1]
    top = max(float(g.norm()) for g in gs.values())
    # the scales' gradient is tiny beside the opacity's, yet above the case's allowance
    assert float(gs["scales"].norm()) < 1e-9 * top and float(gs["scales"].norm()) > 100 * huge.grad_atol * top


def test_a_renderer_written_outside_the_repository_loads_by_path_and_passes():
    pytest.importorskip("gsplat")
    spec = load_renderer(f"{EXAMPLE}:SPEC")
    assert spec.name == "gsplat_example" and spec.alpha_max == 0.999
    rows = cf.run([spec], ["anisotropic", "huge scale 1e4", "grazing view: disc edge-on", "empty scene"],
                  progress=False)  # fmt: skip
    assert [r["verdict"] for r in rows] == ["PASS"] * 4, [r["reason"] for r in rows]
    with pytest.raises(ValueError, match="cannot import"):
        load_renderer(f"{EXAMPLE.with_name('nope.py')}:SPEC")


def test_compare_and_the_error_benchmark_judge_gradients_and_exit_non_zero(tmp_path, capsys):
    from gdbench.refcheck import bm_error
    from gdbench.refcheck.compare import run
    from gdbench.refcheck.protocol import REGISTERED, register_renderer

    register_renderer("flipped_opacity", _flip(3, lambda g: -g).fn)
    try:
        results = run("anisotropic", backends=["splat"], out=tmp_path / "cmp", renderers=["flipped_opacity"],
                      verbose=False)  # fmt: skip
        verdicts = {v["renderer"]: v for v in results["anisotropic"].verdicts}
        assert verdicts["flipped_opacity"]["verdict"] == "FAIL" and "opacities gradient" in verdicts[
            "flipped_opacity"]["reason"]  # fmt: skip
        assert verdicts["splat"]["verdict"] == verdicts["splat_torch"]["verdict"] == "PASS"
        row = next(r for r in results["anisotropic"].rows if r["renderer"] == "flipped_opacity")
        assert row["verdict"] == "FAIL" and row["max_abs"] < 1e-5  # its images alone would pass
        written = json.loads((tmp_path / "cmp" / "compare.json").read_text())["verdicts"]
        assert {v["renderer"] for v in written} == {"flipped_opacity", "splat", "splat_torch"}
        out = tmp_path / "err.csv"
        argv = ["--out", str(out), "--scene", "isotropic", "--renderer", "flipped_opacity"]
        assert bm_error.main(argv) == 1
        assert "FAIL isotropic/flipped_opacity: opacities gradient" in capsys.readouterr().out
        assert bm_error.main(argv[:4] + ["--renderers", "splat"]) == 0
        summary = json.loads((tmp_path / "err_summary.json").read_text())
        assert summary["verdicts"]["splat"]["PASS"] == 1 and summary["verdicts"]["splat_torch"]["PASS"] == 1
    finally:
        REGISTERED.pop("flipped_opacity", None)


def test_bench_passes_renderers_and_cases_only_where_they_apply(tmp_path):
    from gdbench.app.cmd_refs import Bench, run_bench

    done = run_bench(Bench("stability", out=tmp_path, renderers=("splat",), cases=("zero quaternion",)))
    assert done["exit"] == 0
    rows = (tmp_path / "stability.csv").read_text().splitlines()
    assert len(rows) == 2 and "PASS" in rows[1]
    with pytest.raises(ValueError, match="cases: only the stability benchmarks take it"):
        run_bench(Bench("render", out=tmp_path, cases=("zero quaternion",)))
    with pytest.raises(SystemExit, match="bench stability: a case failed"):
        run_bench(Bench("stability", out=tmp_path, renderer=("no_such_module:fn",), cases=("zero quaternion",)))


BUGGY = """
from gdbench.refcheck.protocol import RendererSpec


def _splat(*args, **kw):
    from renderers.splat import rasterize

    return rasterize(*args, **kw, backend="torch")


def flipped_scales(means, quats, scales, *rest, **kw):
    import torch

    class Flip(torch.autograd.Function):
        @staticmethod
        def forward(ctx, x):
            return x.view_as(x)

        @staticmethod
        def backward(ctx, g):
            return -g[:, [1, 0, 2]]

    return _splat(means, quats, Flip.apply(scales), *rest, **kw)


GOOD = RendererSpec("good", _splat)
"""


def test_the_pytest_plugin_collects_the_cases_as_tests_of_a_renderers_own_suite(tmp_path):
    """``pytest --gdbench-renderer`` in a renderer's own folder (the entry point, as installed):
    each (renderer, case) a test; the C++ bug's signature fails with the group named."""
    import subprocess
    import sys

    (tmp_path / "mine.py").write_text(BUGGY)
    (tmp_path / "test_own.py").write_text("def test_own():\n    assert True\n")
    cases = ["huge scale 1e4", "isotropic", "zero quaternion"]
    argv = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", "-rfs",
            "--gdbench-renderer", "mine.py:GOOD", "--gdbench-renderer", "mine.py:flipped_scales"]  # fmt: skip
    for c in cases:
        argv += ["--gdbench-case", c]
    done = subprocess.run(argv, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    out = done.stdout + done.stderr
    assert done.returncode == 1, out
    assert "3 failed, 4 passed" in out, out  # the suite's own test and GOOD's three cases pass
    assert "FAILED ::gdbench[mine.py:flipped_scales::huge scale 1e4]" in out
    assert "scales gradient error" in out and "with the wrong sign" in out
    bad = subprocess.run(argv[:6] + ["--gdbench-renderer", "x.py:f", "--gdbench-case", "no such"], cwd=tmp_path,
                         capture_output=True, text=True, timeout=600)  # fmt: skip
    assert bad.returncode == 4 and "--gdbench-case: unknown ['no such']" in bad.stdout + bad.stderr
    # without the option the plugin adds nothing
    plain = subprocess.run(argv[:6], cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert plain.returncode == 0 and "1 passed" in plain.stdout


def test_the_conformance_report_of_the_worked_example(tmp_path):
    """docs/references.md's worked example: gsplat's torch stages, written outside the repository,
    entering only through the protocol, beside the C++ compositor and the torch path."""
    pytest.importorskip("gsplat")
    from gdbench.app.cli import main
    from gdbench.app.cmd_refs import Conformance

    out = tmp_path / "report"
    cases = ("anisotropic", "huge scale 1e4")
    got = main(Conformance(renderer=(f"{EXAMPLE}:SPEC",), renderers=("splat", "splat_torch"), out=out, cases=cases))
    assert got == {"PASS": 6, "FAIL": 0, "SKIP": 0}
    md = (out / "report.md").read_text()
    for name in ("splat", "splat_torch", "gsplat_example"):
        assert f"| {name} | exact | 2 | 0 | 0 |" in md
    assert "| torch | 2.13" in md and "gsplat_renderer.py" in md and "![maps](error_maps.png)" in md
    assert (out / "error_maps.png").stat().st_size > 10_000 and (out / "pareto.png").stat().st_size > 10_000
    got = json.loads((out / "conformance.json").read_text())
    assert len(got["rows"]) == 6 and got["verdicts"]["gsplat_example"]["PASS"] == 2
    # the report of a failing renderer says which case and why, and the command exits 1
    from gdbench.refcheck.protocol import REGISTERED, register_renderer

    register_renderer("flipped_scales", _flip(2, lambda g: -g).fn)
    try:
        with pytest.raises(SystemExit, match="huge scale 1e4/flipped_scales: scales gradient error"):
            main(Conformance(renderer=("flipped_scales",), out=tmp_path / "bad", cases=cases[1:]))
    finally:
        REGISTERED.pop("flipped_scales", None)
    assert "- FAIL huge scale 1e4 / flipped_scales: scales gradient" in (tmp_path / "bad" / "report.md").read_text()


def test_review_findings_stay_fixed(tmp_path, capsys):
    """A file renderer with a dataclass loads; a zero gradient on 10k Gaussians fails (the floor is a
    derivative's typical size, not Cauchy-Schwarz's bound); a NaN twin passes nothing; verdicts of a
    scene compared again replace the old ones; a renderer that raises fails `bench error` cleanly."""
    from gdbench.refcheck import bm_error
    from gdbench.refcheck.compare import run
    from gdbench.refcheck.protocol import REGISTERED, register_renderer

    mine = tmp_path / "dc_renderer.py"
    mine.write_text(
        "from __future__ import annotations\nfrom dataclasses import dataclass\n\n\n@dataclass\nclass Out:\n"
        "    rgb: object\n    alpha: object\n\n\ndef fn(*a, **k):\n    from renderers.splat import rasterize\n\n"
        "    o = rasterize(*a, **k)\n    return Out(o.rgb, o.alpha)\n"
    )
    assert cf.check(load_renderer(f"{mine}:fn"), cf.case_names()["isotropic"]())["verdict"] == "PASS"
    row = cf.check(_flip(0, lambda g: 0 * g), cf.case_names()["random_cloud_10k"]())
    assert row["verdict"] == "FAIL" and "means gradient" in row["reason"]
    tol = tl.Tolerance(1e-5, 1e-4, 1e-3, 1e-3, 1e-7)
    g = {"means": torch.ones(2, 3)}
    nan = cf.gradient_errors(g, {"means": torch.full((2, 3), float("nan"))}, cf.directions({"means": g["means"]}), tol)
    assert nan["means"]["ok"] is False
    register_renderer("raises", lambda *a, **k: 1 / 0)
    try:
        for _ in range(2):
            run("isotropic", backends=[], out=tmp_path / "cmp", renderers=["raises"], verbose=False)
        verdicts = json.loads((tmp_path / "cmp" / "compare.json").read_text())["verdicts"]
        assert [(v["case"], v["verdict"]) for v in verdicts] == [("isotropic", "FAIL")]
        assert bm_error.main(["--out", str(tmp_path / "e.csv"), "--scene", "isotropic", "--renderer", "raises"]) == 1
        assert "FAIL isotropic/raises: ZeroDivisionError" in capsys.readouterr().out
    finally:
        REGISTERED.pop("raises", None)
