"""The rendering benchmark's machinery on a quick sweep (the numbers themselves live in the
CSV written by `make bench`, never in timed unit tests)."""

import csv
import json
import math

import pytest
import torch

from gdbench.bench.common import random_cloud, timeit
from gdbench.refcheck import bm_render
from tests._util import script


def test_quick_sweep_writes_rows_summary_and_plot(tmp_path):
    out = tmp_path / "render.csv"
    assert bm_render.main(["--quick", "--inprocess", "--out", str(out), "--backend", "splat"]) == 0
    rows = list(csv.DictReader(out.open()))
    assert len(rows) == 2 * 2 * 2  # N x res x mode
    for r in rows:
        assert r["status"] == "ok" and float(r["median_s"]) > 0 and float(r["peak_rss_mb"]) > 0
        # oracle for the work count: tile-box pairs counted from the float64 twin's projection (its
        # own EWA formula); float32 vs float64 may flip a box edge exactly on a tile boundary
        scene = random_cloud(int(r["n"]))
        cams = bm_render._camera(int(r["res"]), "cpu")
        expected = _count_by_twin(scene, cams)
        assert abs(int(r["intersections"]) - expected) <= max(2, 0.002 * expected)
    summary = json.loads((tmp_path / "render_summary.json").read_text())
    assert "splat fwd" in summary["fits"] and (tmp_path / "render_fit.png").stat().st_size > 0


def _count_by_twin(scene, cams, ts=16, alpha_min=1 / 255):
    """Tile-Gaussian pairs from the float64 twin's projection: each Gaussian's box of
    alpha >= alpha_min (half-widths sqrt(2 ln(o / alpha_min)) sqrt(diag cov2d)), in tiles."""
    import math

    from renderers.splat.reference import project_reference

    d = {k: v.double() for k, v in scene.items()}
    W, H = cams.width, cams.height
    tx, ty = (W + ts - 1) // ts, (H + ts - 1) // ts
    total = 0
    for c in range(len(cams)):
        m2, cov, _, ok = project_reference(
            d["means"], d["quats"], d["scales"], cams.viewmats[c].double(), cams.Ks[c].double(), W, H
        )
        o = d["opacities"]
        ext = torch.sqrt(2 * torch.log((o / alpha_min).clamp_min(1.0)))
        r = ext[:, None] * torch.sqrt(torch.stack([cov[:, 0, 0], cov[:, 1, 1]], -1))
        inside = (m2 + r > 0).all(-1) & (m2[:, 0] - r[:, 0] < W) & (m2[:, 1] - r[:, 1] < H)
        vis = ok & (o >= alpha_min) & inside
        lo = torch.floor((m2 - r - 1e-3) / ts).long()
        hi = torch.floor((m2 + r + 1e-3) / ts).long()
        nx = hi[:, 0].clamp(0, tx - 1) - lo[:, 0].clamp(0, tx - 1) + 1
        ny = hi[:, 1].clamp(0, ty - 1) - lo[:, 1].clamp(0, ty - 1) + 1
        total += int((nx * ny)[vis].sum())
    assert not math.isnan(total)
    return total


def test_dense_cells_beyond_limits_are_skipped_with_a_reason():
    reason = bm_render._skip_reason("dense", 100_000, 512, "fwd")
    assert reason is not None and "N x pixels" in reason
    assert bm_render._skip_reason("splat", 100_000, 512, "fwd") is None


def test_fixed_cost_case_draws_one_pixel_sized_gaussian_and_is_reported_apart_from_the_fit():
    """The direct fixed-cost case: one Gaussian of scale 2e-3 at 1.5 from a 50-degree, 256 px
    camera (focal 128 / tan 25 = 274 px: sigma 0.37 px, under 1 px with the 0.3 px^2 dilation)
    touches at most the 4 tiles around the centre and a few dozen pixels; its row is reported as
    ``fixed_cost`` and kept out of the splat fit."""
    row = bm_render.run_case(*bm_render.FIXED)
    assert row["status"] == "ok" and row["intersections"] == 4  # its centre is the corner of 4 tiles
    # pixel pairs: the pixel centres k + 0.5 within the projected radius r of 128 on each axis,
    # 2 floor(r + 0.5) of them (r from the projection, the count in closed form)
    from renderers.splat.project import project

    s, cam = bm_render._scene(*bm_render.FIXED[:2]), bm_render._camera(256, "cpu")
    p = project(s["means"], s["quats"], s["scales"], s["opacities"], cam.viewmats, cam.Ks, 256, 256)
    assert torch.equal(p.means2d.flatten(), torch.tensor([128.0, 128.0]))
    per_axis = [2 * math.floor(float(r) + 0.5) for r in p.radii.flatten()]
    assert row["pixel_pairs"] == per_axis[0] * per_axis[1] > 0
    # the work counters: the 4 tile pairs, each a box under one block wide, so one block per row
    # of the box in that tile (half the box's rows)
    assert row["fwd_pairs_visited"] == 4 and row["fwd_blocks"] == 4 * per_axis[1] // 2
    fit_rows = [
        {
            "path": "splat",
            "n": n,
            "res": 64,
            "mode": "fwd",
            "status": "ok",
            "pixels": 4096,
            "intersections": n,
            "median_s": 1e-3 + 1e-6 * n,
            "pixel_pairs": n,
        }
        for n in (100, 1000, 10000)
    ]
    summary = bm_render.summarise(fit_rows + [row])
    assert summary["fixed_cost"]["value"] == row["median_s"]
    assert summary["fits"]["splat fwd"]["vs_intersections"]["points"] == 3
    assert summary["fits"]["splat fwd"]["vs_intersections"]["intercept_s"] == pytest.approx(1e-3, rel=1e-6)


def test_fit_recovers_a_linear_law():
    rows = [{"x": x, "median_s": 0.5 + 2e-3 * x} for x in (10, 200, 3000, 5000)]
    fit = bm_render._fit(rows, "x")
    assert fit["slope_s"] == pytest.approx(2e-3) and fit["intercept_s"] == pytest.approx(0.5) and fit["r2"] > 0.999


def test_work_fit_recovers_the_fixed_cost_and_becomes_the_intercept_target():
    """time = a + b blocks + c N on rows whose blocks and N vary independently: the fit returns
    a, b and c, and the intercept target reads it (not the fit against intersections)."""
    law = {"a": 2e-3, "blocks": 30e-9, "n": 200e-9}
    rows = []
    for n, fb, bb, inter in (
        (1000, 3e4, 0, 9e3),
        (10000, 4e5, 0, 2e4),
        (100000, 2e5, 0, 7e4),
        (30000, 1e6, 0, 5e3),
        (1000, 3e4, 3e4, 9e3),
        (10000, 4e5, 4e5, 2e4),
        (100000, 2e5, 2e5, 7e4),
        (30000, 1e6, 1e6, 5e3),
    ):
        mode = "fwd" if bb == 0 else "fwd+bwd"
        t = law["a"] + law["blocks"] * (fb + bb) + law["n"] * n
        rows.append(
            {
                "path": "splat",
                "n": n,
                "res": 256,
                "mode": mode,
                "status": "ok",
                "pixels": 65536,
                "intersections": inter,
                "pixel_pairs": inter,
                "median_s": t,
                "fwd_blocks": fb,
                "bwd_blocks": bb,
            }
        )
    summary = bm_render.summarise(rows)
    for mode in ("fwd", "fwd+bwd"):
        w = summary["fits"][f"splat {mode}"]["vs_work"]
        assert w["intercept_s"] == pytest.approx(law["a"], rel=1e-6) and w["r2"] > 0.999999
        assert w["slopes_s"]["blocks"] == pytest.approx(law["blocks"], rel=1e-6)
        assert w["slopes_s"]["n"] == pytest.approx(law["n"], rel=1e-6)
        assert w["intercept_se_s"] < 1e-9  # an exact law: no spread
    target = summary["targets"]["splat_fit_intercept_s"]
    assert target["fit"] == "vs_work" and target["value"] == pytest.approx(law["a"], rel=1e-6) and target["met"]
    assert summary["fits"]["splat fwd"]["vs_intersections"]["r2"] < 0.99  # intersections are not the work here
    # a law with a negative cost per Gaussian (what a 4-point quick grid can fit): no verdict on the target
    for r in rows:
        r["median_s"] = law["a"] + law["blocks"] * (r["fwd_blocks"] + r["bwd_blocks"]) - 1e-9 * r["n"]
    target = bm_render.summarise(rows)["targets"]["splat_fit_intercept_s"]
    assert target["met"] is None and "negative cost per n" in target["why"]


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
    assert "bank of 360" in row["what"] and row["seconds"] > 0 and row["met"] == (row["seconds"] <= row["target_s"])


def _public(ext) -> dict:
    return {n: getattr(ext, n) for n in dir(ext) if not n.startswith("_")}


def test_kernel_clock_times_each_extension_call_passes_results_through_and_restores():
    import time

    from gdbench.bench.common import kernel_clock

    from ._util import require_cpp

    ext = require_cpp()
    originals = _public(ext)
    c = random_cloud(400, seed=3)
    cams = bm_render._camera(48, "cpu")

    def render_and_backward():
        from renderers.splat import rasterize

        means = c["means"].clone().requires_grad_(True)
        out = rasterize(means, c["quats"], c["scales"], c["opacities"], c["colors"], cams.viewmats, cams.Ks, 48, 48)
        (out.rgb * torch.linspace(0, 1, 3)).sum().backward()
        return out.rgb.detach(), means.grad

    rgb, grad = render_and_backward()
    assert rgb.std() > 0.01  # the cloud is in view
    t0 = time.perf_counter()
    with kernel_clock() as clock:
        rgb_c, grad_c = render_and_backward()
        with pytest.raises(RuntimeError, match="already running"), kernel_clock():
            pass
    wall = time.perf_counter() - t0
    assert torch.equal(rgb_c, rgb) and torch.equal(grad_c, grad)  # the wrappers change nothing
    # one CPU render and its backward: one projection, binning and composite each way
    calls = {n: v[1] for n, v in clock.items() if v[1]}
    assert calls == {"project_forward": 1, "bin_tiles": 1, "composite_forward": 1, "composite_backward": 1,
                     "project_backward": 1}  # fmt: skip
    assert all(0 < clock[n][0] for n in calls) and sum(v[0] for v in clock.values()) <= wall
    assert _public(ext) == originals  # every function put back
    with pytest.raises(ZeroDivisionError), kernel_clock():
        1 / 0
    assert _public(ext) == originals  # put back after an error too
    with kernel_clock():  # and a new clock may start
        pass


def test_train_benchmark_times_each_steps_kernels_apart_from_the_outputs(tmp_path):
    from gdbench.bench import bm_train
    from gdbench.train import run as run_module
    from gdbench.train.config import preset

    from ._util import require_cpp

    originals = _public(require_cpp())
    step_fn = run_module.train_step
    with bm_train.kernels_per_step() as (per, inside):
        r = run_module.train(preset("gd", out=tmp_path, steps=4, progress=False), resume=False)
    assert run_module.train_step is step_fn and len(inside) == 4 == len(r.state.history)
    # a gd step composites the scene and its structured noise and backpropagates the scene only;
    # the outputs' turntable renders after the steps are not counted
    calls = {n: v[1] for n, v in per.items()}
    assert calls["composite_forward"] == 2 * 4 and calls["composite_backward"] == 4
    steps = [h["seconds"] for h in r.state.history]
    assert all(0 < k < s for k, s in zip(inside, steps))
    step = sorted(steps)[2]
    rows = bm_train.kernel_rows(per, inside, step)
    floor = rows[0]
    assert floor["seconds"] == pytest.approx(sum(sorted(inside)[1:3]) / 2)  # the median of four
    assert floor["share"] == pytest.approx(floor["seconds"] / step)
    row = next(r for r in rows if "composite_forward" in r["what"])
    assert "(2 calls a step" in row["what"] and row["seconds"] == pytest.approx(per["composite_forward"][0] / 4)
    assert "composite_backward (1 call a step" in " ".join(r["what"] for r in rows)
    # an error in the block puts the trainer's step and the extension back
    with pytest.raises(ZeroDivisionError), bm_train.kernels_per_step():
        1 / 0
    assert run_module.train_step is step_fn and _public(require_cpp()) == originals


def test_train_benchmark_says_why_it_has_no_kernel_floor(monkeypatch):
    import math

    from gdbench.bench import bm_train
    from gdbench.train import run as run_module
    from renderers.splat import _ext

    def why(per, inside):
        (row,) = bm_train.kernel_rows(per, inside, 0.01)
        assert math.isnan(row["seconds"])
        return row["what"].split("not measured, ")[1]

    # steps whose kernels are not the extension's (CUDA, or the torch path): entries, no calls
    assert why({"composite_forward": [0.0, 0]}, [0.0, 0.0]) == "the steps called none of its kernels"
    assert why({}, []) == "no training step ran"  # a finished run resumed: nothing to time
    step_fn = run_module.train_step
    monkeypatch.setattr(_ext, "load_extension", lambda verbose=False: None)  # not built here
    with bm_train.kernels_per_step() as (per, inside):
        assert run_module.train_step is step_fn  # the steps run untimed
    assert per is None and inside == []
    assert why(per, inside).startswith("the C++ extension is not available")


def test_cell_kernels_script_counts_a_cells_steps_kernels(tmp_path):

    from ._util import require_cpp

    require_cpp()
    module = script("cell_kernels")
    out = tmp_path / "ck.csv"
    assert module.main(["--rounds", "1", "--steps", "3", "--out", str(out)]) == 0
    rows = {r["kernel"]: r for r in csv.DictReader(out.open())}
    # three gd steps: the scene's and the noise's composites, the scene's backward; the scores'
    # renders after the steps are not counted
    assert int(rows["composite_forward"]["calls"]) == 6 and int(rows["composite_backward"]["calls"]) == 3
    r = rows["composite_forward"]
    assert 0 < float(r["kernels_s"]) < float(r["train_steps_s"]) < float(r["cell_s"])
    assert json.loads((tmp_path / "ck_summary.json").read_text())["environment"]["commit"]
    with pytest.raises(SystemExit):
        module.main(["--rounds", "0"])


# ------------------------------------------------------------------ peers and stability
def test_peer_sweep_reports_each_peer_against_splat_in_the_same_run(tmp_path):
    pytest.importorskip("gsplat")
    out = tmp_path / "peers.csv"
    assert bm_render.main(["--quick", "--inprocess", "--peers", "--out", str(out)]) == 0
    rows = list(csv.DictReader(out.open()))
    ok = {(r["path"], r["n"], r["res"], r["mode"]): r for r in rows if r["status"] == "ok"}
    peers = [k for k in ok if k[0] == "gsplat_torch"]
    assert len(peers) == 2 * 2 * 2
    for k in peers:
        base = ok[("splat", *k[1:])]
        assert float(ok[k]["time_over_splat"]) == pytest.approx(float(ok[k]["median_s"]) / float(base["median_s"]))
    # Mitsuba is timed forward only, and says so
    assert all("forward only" in r["status"] for r in rows if r["path"] == "mitsuba" and r["mode"] == "fwd+bwd")


def test_stability_cases_agree_with_the_twin_and_flag_non_finite_renderers(tmp_path):
    from gdbench.refcheck import bm_stability as bs
    from gdbench.refcheck.protocol import register_renderer

    names = ["anisotropy 1e6", "grazing view: disc edge-on", "fovy 170 deg", "10k Gaussians on one pixel"]
    rows = bs.run(tmp_path / "stab.csv", ("splat", "splat_torch"), names, progress=False)
    assert len(rows) == 8
    for r in rows:
        assert r["status"] == "ok" and r["twin_finite"] and not r["nan_out"] and not r["nan_grad"]
        assert r["alpha_max_twin"] > 0.05  # each case draws something
        assert max(r["max_err_rgb"], r["max_err_alpha"]) < 1e-5 and r["grad_err"] < 1e-3 and r["verdict"] == "PASS"
    summary = json.loads((tmp_path / "stab_summary.json").read_text())
    assert summary["verdicts"]["splat"] == {"PASS": 4, "FAIL": 0, "SKIP": 0, "failed": []}

    # a renderer that returns NaN is flagged in its row and in the table, FAILs, and the command exits 1
    from renderers.splat import rasterize

    def broken(*a, **k):
        out = rasterize(*a, **k)
        return type(out)(rgb=out.rgb * float("nan"), alpha=out.alpha)

    register_renderer("nan_renderer", broken)
    bad = bs.run(tmp_path / "bad.csv", (), names[:1], progress=False, refs=("nan_renderer",))
    assert bad[0]["nan_out"] and bad[0]["nan_grad"] and bad[0]["status"] == "non-finite"
    assert bad[0]["verdict"] == "FAIL" and "rgb not finite" in bad[0]["reason"]
    assert "NaN out, NaN grad" in (tmp_path / "bad.md").read_text()
    argv = ["--out", str(tmp_path / "cli.csv"), "--renderer", "nan_renderer", "--cases", names[0]]
    assert bs.main(argv) == 1
    assert bs.main(argv[:2] + ["--renderers", "splat", "--cases", names[0]]) == 0
    with pytest.raises(ValueError, match="cases: unknown"):
        bs.run(tmp_path / "x.csv", ("splat",), ["no such case"])


def test_pareto_flags_keep_exactly_the_non_dominated_runs():
    from gdbench.refcheck.bm_error import pareto_flags

    base = {"scene": "s", "quantity": "rgb", "against": "reference"}
    pts = [(1.0, 0.1), (2.0, 0.05), (3.0, 0.07), (0.5, 0.5), (2.0, 0.05), (4.0, float("nan"))]
    rows = [base | {"time_s": t, "max_abs": e} for t, e in pts]
    rows.append({**base, "scene": "other", "time_s": 10.0, "max_abs": 1.0})  # another scene: its own front
    # (3.0, 0.07) is beaten by (2.0, 0.05); the two equal runs do not dominate each other
    assert pareto_flags(rows) == [True, True, False, True, True, False, True]


def test_error_benchmark_writes_one_csv_with_skips(tmp_path):
    from gdbench.refcheck import bm_error

    out = tmp_path / "err.csv"
    rows = bm_error.run(out, "isotropic", backends=["splat", "pyrender_points"], verbose=False)
    got = list(csv.DictReader(out.open()))
    assert len(got) == len(rows) and got[0]["renderer"] == "reference"
    splat = [r for r in got if r["renderer"] == "splat"]
    exact = [r for r in splat if r["settings"] in ("default", "backend=torch")]
    assert len(splat) >= 5 and len(exact) == 2 and all(float(r["max_abs"]) < 1e-5 for r in exact)
    assert all(math.isfinite(float(r["max_abs"])) for r in splat)
    assert any(r["pareto"] == "True" for r in splat)
    summary = json.loads((tmp_path / "err_summary.json").read_text())
    assert summary["pareto"]["isotropic"]


def test_bench_quick_runs_render_in_one_process_and_peers_as_asked(monkeypatch, tmp_path):
    import importlib

    from gdbench.app.cmd_refs import Bench, run_bench

    seen = {}

    class Fake:
        @staticmethod
        def main(argv):
            seen["argv"] = argv
            return 0

    real = importlib.import_module
    fake = lambda name: Fake if name.startswith(("gdbench.bench", "gdbench.refcheck.bm_")) else real(name)  # noqa: E731
    monkeypatch.setattr(importlib, "import_module", fake)
    run_bench(Bench("render", out=tmp_path, quick=True))
    assert "--quick" in seen["argv"] and "--inprocess" in seen["argv"]
    run_bench(Bench("render", out=tmp_path))
    assert "--quick" not in seen["argv"] and "--inprocess" not in seen["argv"]
    with pytest.raises(ValueError, match="quick: only render and peers"):
        run_bench(Bench("train", out=tmp_path, quick=True))


def test_train_benchmark_times_other_learned_models_beside_the_shipped_one(tmp_path):
    """`bench train --learned-models`: each model's step is timed in the same alternating blocks and
    reported as its ratio to the shipped learned model's step, round by round, and judged against
    the target as reported; the model really reaches the prior (an unknown one is refused naming
    learned_model)."""
    from gdbench.bench import bm_train

    rows = bm_train.prior_steps(tmp_path, blocks=3, block=4, warmup=2, models=("uniform",))
    shipped = next(r for r in rows if r["what"].startswith("training step with the learned prior"))
    mine = next(r for r in rows if r["what"].startswith("training step with the learned uniform model"))
    assert shipped["seconds"] > 0 and mine["seconds"] > 0
    assert mine["met"] == (mine["ratio"] <= bm_train.MAX_MODEL_RATIO)
    # no bound on the ratio itself: the same work reads about 1x on an idle machine, but three
    # rounds of four steps beside other jobs have read 4.5x (a timing belongs in the benchmark's
    # CSV, not in a unit test's assertion)
    assert 0 < mine["ratio"] < float("inf")
    with pytest.raises(FileNotFoundError, match="learned_model: expected"):
        bm_train.prior_steps(
            tmp_path / "bad", blocks=1, block=1, warmup=0, models=(str(tmp_path / "none.safetensors"),)
        )
