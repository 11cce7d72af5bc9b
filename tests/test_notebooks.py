"""The benchmark notebooks (notebooks/*.ipynb): stored without outputs, and executed end to
end on small data that the benchmark commands write here (the published numbers come from the
full commands; see the README)."""

import json
import random
from pathlib import Path

import pytest

NOTEBOOKS = Path(__file__).resolve().parents[1] / "notebooks"
NAMES = ("render_speed", "error_vs_runtime", "stability", "ablation")


@pytest.mark.parametrize("name", NAMES)
def test_notebooks_are_stored_without_outputs(name):
    nb = json.loads((NOTEBOOKS / f"{name}.ipynb").read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert code and all(c["outputs"] == [] and c["execution_count"] is None for c in code)


@pytest.fixture(scope="module")
def small_results(tmp_path_factory):
    from gdbench.bench import bm_error, bm_render, bm_stability
    from gdbench.sweep_tables import tables

    d = tmp_path_factory.mktemp("results")
    rows = bm_render.sweep(d / "peers.csv", quick=True, inprocess=True, paths=("splat", "gsplat_torch"))
    assert any(r.get("time_over_splat") for r in rows)
    bm_error.run(d / "error_vs_runtime.csv", "isotropic", backends=["splat", "pyrender_points"], verbose=False)
    bm_stability.run(d / "stability.csv", ("splat", "splat_torch"), ["anisotropy 1e6", "fovy 1 deg"], progress=False)
    # sweep cells: the notebook only reads cells.csv, so these are drawn, not trained
    rng = random.Random(0)
    cells = [
        {
            "setting": st,
            "prompt": pr,
            "preset": p,
            "seed": s,
            "iterations": 2000,
            "train_time_s": 60.0,
            "gaussians": 5000,
            "gt_psnr": 20 + rng.random(),
            "gt_ssim": 0.7,
            "registration_rate": 0.9,
            "var_theta_deg2": (1 + i) * (1 + rng.random()) if (i, s) != (4, 1) else float("nan"),
            "translation_dir_err_deg": 2.0,
            "multi_face_rate": rng.random() / (1 + i),
            "instance_inconsistency": rng.random() / 3,
            "floaters": rng.random() / 10,
            "colmap_failure_rate": rng.random() / 4,
            "janus_failure_rate": rng.random() if st == "janus" else 0.0,
            "group": g,
        }
        for g in ("", "learned-v4")
        for st in ("easy", "janus")
        for pr in ("a", "b")
        for i, p in enumerate(("gd", "gd-no-vgs", "gd-no-sn", "sjc-gs", "sds-gs"))
        for s in (0, 1)
    ]
    tables(cells, d)
    return d


@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs_on_small_data(name, small_results, monkeypatch, tmp_path):
    nbformat = pytest.importorskip("nbformat")
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("GDBENCH_RESULTS", str(small_results))
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(tmp_path)}}
    ).execute()
    outputs = [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]
    assert not [o for o in outputs if o.output_type == "error"]
    assert any(o.output_type == "display_data" and "image/png" in o.data for o in outputs)  # it drew its figure
