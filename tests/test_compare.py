"""Fixture scenes, golden regression of the splat renderer, and the compare harness."""

import pytest

from gdbench.refcheck.compare import BACKENDS, compare_scene, image_errors, run
from gdbench.refcheck.golden import load_golden
from gdbench.refcheck.scenes import fixture_names, load_fixture
from tests._util import write_failure_images

FIXTURES = fixture_names()


def test_the_required_fixture_scenes_exist():
    assert {"isotropic", "anisotropic", "crossing", "near_wide", "random_cloud_10k", "subpixel", "procedural"} <= set(
        FIXTURES
    )
    assert len(load_fixture("random_cloud_10k").scene) == 10000


@pytest.mark.parametrize("name", FIXTURES)
def test_splat_matches_golden(name, tmp_path):
    from renderers.splat import rasterize

    fx = load_fixture(name)
    gold = load_golden(name)
    c = fx.cameras
    out = rasterize(
        **fx.scene.render_args(),
        viewmats=c.viewmats,
        Ks=c.Ks,
        width=c.width,
        height=c.height,
        background=fx.background,
        outputs=("rgb", "alpha"),
    )
    tol = fx.tolerance("reference")
    err = image_errors(out.rgb, gold["rgb"])
    assert float(gold["alpha"].max()) > 0.3  # the golden image is not empty
    if err["mean_abs"] > tol["mean_abs"] or err["max_abs"] > tol["max_abs"]:
        path = write_failure_images(name, out.rgb, gold["rgb"], tmp_path)
        pytest.fail(f"{name}: {err} exceeds {tol}; actual | reference | error written to {path}")


def test_harness_rows_tolerances_and_skips(tmp_path):
    res = compare_scene(load_fixture("anisotropic"))
    rows = {(r["renderer"], r["settings"], r["against"], r["quantity"]): r for r in res.rows}
    tol = load_fixture("anisotropic").tolerance("gsplat_torch")
    peer = next(r for k, r in rows.items() if k[0] == "gsplat_torch" and k[2].startswith("splat["))
    assert peer["max_abs"] <= tol["max_abs"]
    default = rows[("splat", "default", "reference", "rgb")]
    assert default["max_abs"] <= load_fixture("anisotropic").tolerance("reference")["max_abs"]
    coarse = rows[("splat", "alpha_min=0.02", "reference", "rgb")]
    assert coarse["max_abs"] > default["max_abs"]  # the ladder moves the error, as it should
    pts = rows[("pyrender_points", "16x supersampled points", "splat projection", "centre_px")]
    assert pts["max_abs"] <= 0.05
    for r in res.rows:
        assert r["time_s"] > 0


def test_run_writes_report_and_lists_skips(tmp_path, monkeypatch):
    import gdbench.refcheck.compare as cmp

    monkeypatch.setattr(
        cmp, "available", lambda name: (False, "pretend it is missing") if name == "gsplat_torch" else (True, "")
    )
    results = run("isotropic", out=tmp_path, verbose=False)
    assert (tmp_path / "compare.csv").is_file() and (tmp_path / "isotropic_pareto.png").stat().st_size > 0
    assert (tmp_path / "isotropic_errors.png").is_file()
    skipped = results["isotropic"].skipped
    assert skipped == [
        {"scene": "isotropic", "renderer": "gsplat_torch", "reason": "not available here: pretend it is missing"}
    ]


def test_comparing_another_scene_into_the_same_folder_keeps_one_table_and_no_orphan_image(tmp_path, monkeypatch):
    import csv
    import json

    first, second = "isotropic", next(n for n in fixture_names() if n != "isotropic")
    a = run(first, backends=["splat"], out=tmp_path, verbose=False)
    run(second, backends=["splat"], out=tmp_path, verbose=False)
    third = next(n for n in fixture_names() if n not in (first, second))
    (tmp_path / f"{third}_errors.png").write_bytes(b"an image whose scene has no row")
    (tmp_path / "mine_errors.png").write_bytes(b"a file compare never writes: left alone")

    def strict(path):
        return json.loads(path.read_text(), parse_constant=lambda c: pytest.fail(f"{path}: {c} in strict JSON"))

    strict(tmp_path / "compare.json")
    again = run(first, backends=["splat"], out=tmp_path, verbose=False)  # the first scene again: its rows replaced
    blob = strict(tmp_path / "compare.json")
    with open(tmp_path / "compare.csv") as f:
        table = list(csv.DictReader(f))
    scenes = [r["scene"] for r in blob["rows"]]
    assert scenes.count(first) == len(again[first].rows) == len(a[first].rows) and second in scenes
    assert [r["scene"] for r in table] == scenes
    # the float64 twin against itself: PSNR infinite in memory, null (empty) in the files
    twin = next(r for r in blob["rows"] if r["scene"] == first and r["renderer"] == "reference")
    assert twin["psnr"] is None and next(r for r in table if r["renderer"] == "reference")["psnr"] == ""
    images = {p.name for p in tmp_path.glob("*.png")}
    assert images == {f"{n}_{k}.png" for n in (first, second) for k in ("errors", "pareto")} | {"mine_errors.png"}
    (tmp_path / "compare.json").write_text('{"rows": [')
    import gdbench.refcheck.compare as cmp

    monkeypatch.setattr(cmp, "compare_scene", lambda *a: pytest.fail("rendered before reading the broken table"))
    with pytest.raises(ValueError, match=r"compare\.json: .* is not valid JSON"):
        run(first, backends=["splat"], out=tmp_path, verbose=False)


def test_bad_scene_and_backend_names(tmp_path):
    with pytest.raises(ValueError, match="scene: no fixture named 'nope'"):
        load_fixture("nope")
    out = tmp_path / "never"  # an unknown --scene fails before --out is made or anything runs
    with pytest.raises(ValueError, match=r"scene \(--scene\): no fixture named 'nope'"):
        run(["isotropic", "nope"], backends=["splat"], out=out, verbose=False)
    assert not out.exists()
    with pytest.raises(ValueError, match="backends: unknown"):
        run("isotropic", backends=["blender"], verbose=False)
    assert set(BACKENDS) >= {"splat", "gsplat_torch", "pyrender_points"}


def test_cli_compare(tmp_path, capsys):
    from gdbench.app.cli import main
    from gdbench.app.cmd_refs import Compare

    summary = main(Compare(scene="near_wide", out=tmp_path, backends=("splat",)))
    assert summary == {"near_wide": {"rows": 7, "skipped": 0}}
    assert "near_wide" in capsys.readouterr().out


def test_every_backend_puts_a_gaussian_where_the_camera_projects_it(backend):
    """One small Gaussian off-centre: each renderer's alpha centroid lands on the pinhole
    projection of its mean (an independent closed form), within a fraction of a pixel; and the
    registry names every renderer the compare harness and the benchmarks use."""
    import torch

    from gdbench.core.camera import SphericalPoses
    from gdbench.refcheck.backends import BACKENDS

    assert {"splat", "splat_torch", "gsplat_torch", "mitsuba_ellipsoids", "pyrender_points"} <= set(BACKENDS)
    assert backend.renders
    cams = SphericalPoses.orbit(1, radius=2.0, elevation=10.0, fovy=40.0).cameras(48, 40)
    mean = torch.tensor([[0.1, -0.15, 0.08]])
    out = backend.render(
        mean, torch.tensor([[1.0, 0.0, 0.0, 0.0]]), torch.full((1, 3), 0.03), torch.tensor([0.9]),
        torch.tensor([[0.9, 0.3, 0.2]]), cams.viewmats, cams.Ks, 48, 40, background=torch.ones(3),
    )  # fmt: skip
    a = out.alpha[0, ..., 0].double()
    assert float(a.max()) > 0.5
    ys, xs = torch.meshgrid(torch.arange(40) + 0.5, torch.arange(48) + 0.5, indexing="ij")
    centroid = torch.stack([(a * xs).sum() / a.sum(), (a * ys).sum() / a.sum()])
    uv, _ = cams.project(mean)
    assert float((centroid - uv[0, 0].double()).norm()) < 0.25, (backend.name, centroid, uv)
