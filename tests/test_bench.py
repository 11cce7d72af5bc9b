"""The rendering benchmark's machinery on a quick sweep (the numbers themselves live in the
CSV written by `make bench`, never in timed unit tests)."""

import csv
import json

import pytest
import torch

from gdbench.bench import bm_render
from gdbench.bench.common import random_cloud, timeit


def test_quick_sweep_writes_rows_summary_and_plot(tmp_path):
    out = tmp_path / "render.csv"
    assert bm_render.main(["--quick", "--inprocess", "--out", str(out), "--backend", "splat"]) == 0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 2 * 2 * 2  # N x res x mode
    for r in rows:
        assert r["status"] == "ok" and float(r["median_s"]) > 0 and float(r["peak_rss_mb"]) > 0
        # oracle for the work count: an independent count from the projected boxes
        scene = random_cloud(int(r["n"]))
        cams = bm_render._camera(int(r["res"]), "cpu")
        assert int(r["intersections"]) == _count_by_boxes(scene, cams)
    summary = json.loads((tmp_path / "render_summary.json").read_text())
    assert "splat fwd" in summary["fits"] and (tmp_path / "render_fit.png").stat().st_size > 0


def _count_by_boxes(scene, cams, ts=16):
    from renderers.splat.bin_tiles import tile_ranges
    from renderers.splat.project import project

    p = project(
        scene["means"],
        scene["quats"],
        scene["scales"],
        scene["opacities"],
        cams.viewmats,
        cams.Ks,
        cams.width,
        cams.height,
    )
    tx = (cams.width + ts - 1) // ts
    ty = (cams.height + ts - 1) // ts
    x0, x1, y0, y1 = tile_ranges(p.means2d, p.radii, tx, ty, ts)
    return int((((x1 - x0 + 1) * (y1 - y0 + 1))[p.visible]).sum())


def test_dense_cells_beyond_limits_are_skipped_with_a_reason():
    reason = bm_render._skip_reason("dense", 100_000, 512, "fwd")
    assert reason is not None and "N x pixels" in reason
    assert bm_render._skip_reason("splat", 100_000, 512, "fwd") is None


def test_fit_recovers_a_linear_law():
    rows = [{"x": x, "median_s": 0.5 + 2e-3 * x} for x in (10, 200, 3000, 5000)]
    fit = bm_render._fit(rows, "x")
    assert fit["slope_s"] == pytest.approx(2e-3) and fit["intercept_s"] == pytest.approx(0.5) and fit["r2"] > 0.999


def test_timeit_counts_repeats():
    calls = []
    t = timeit(lambda: calls.append(torch.ones(1)), warmup=2, min_repeats=3, max_repeats=5, budget_s=0.0)
    assert t["repeats"] == 3 and len(calls) == 5


def test_noise_benchmark_row_is_consistent():
    from gdbench.bench import bm_noise

    row = bm_noise.measure(32, scene_n=300, budget_s=0.05)
    assert row["noise_s"] > 0 and row["step_render_fwd_bwd_s"] > 0
    assert row["share"] == pytest.approx(row["noise_s"] / row["step_render_fwd_bwd_s"])
    assert 0 < row["coverage"] <= 1 and row["correlation_length_px"] > 0


def test_interleaved_timing_alternates():
    from gdbench.bench.bm_noise import interleaved

    order = []
    ta, tb = interleaved(lambda: order.append("a"), lambda: order.append("b"), budget_s=0.0, warmup=1, min_repeats=3)
    assert order == ["a", "b"] * 4 and ta >= 0 and tb >= 0


def test_train_benchmark_denoise_row():
    from gdbench.bench import bm_train

    row = bm_train.denoise_time("window")
    assert "bank of 360" in row["what"] and 0 < row["seconds"] < 1.0 and row["met"] == (row["seconds"] <= 0.005)
