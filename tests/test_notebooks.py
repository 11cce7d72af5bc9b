"""The benchmark notebooks (notebooks/*.ipynb): stored without outputs, and executed end to
end on small data that the benchmark commands write here and on the shipped snapshots in
docs/results (the published numbers come from the full commands; see the README). Every figure
they draw is checked for a title, axis labels and, where it draws several series, a legend; the
targets they judge against their summary JSONs; the ablation's forest plot against verdict.csv."""

import json
import math
import random
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
NOTEBOOKS = ROOT / "notebooks"
SHIPPED = ROOT / "docs" / "results"
NAMES = ("render_speed", "error_vs_runtime", "stability", "ablation")

# Run first: keep the figures open after their cell, for the check at the end.
KEEP_FIGURES = "%config InlineBackend.close_figures = False"
# Run last: what every figure lacks (title, axis labels, legend), as one JSON line. An axes
# without data or without axes (an empty panel's note, a colour bar, a twin's labels) is skipped;
# one with more than one artist drawn needs a legend of its own or one shared in its figure.
FIGURE_CHECK = """
import json as _json
import matplotlib.pyplot as _plt
_lacks = []
for _num in _plt.get_fignums():
    _fig = _plt.figure(_num)
    _sup = _fig._suptitle.get_text() if _fig._suptitle else ""
    _shared = bool(_fig.legends) or any(_a.get_legend() for _a in _fig.axes)
    for _i, _ax in enumerate(_fig.axes):
        if not _ax.axison or not _ax.has_data() or hasattr(_ax, "_colorbar"):
            continue
        _at = f"figure {_num} axes {_i} ({_ax.get_title() or _sup!r})"
        _lacks += [f"{_at}: no {_w}" for _w, _t in (("title", _ax.get_title() or _sup),
                   ("x label", _ax.get_xlabel()), ("y label", _ax.get_ylabel())) if not _t]
        if len(_ax.lines) + len(_ax.collections) + len(_ax.containers) > 1 and not (_ax.get_legend() or _shared):
            _lacks.append(f"{_at}: several series, no legend")
print("FIGURE_CHECK " + _json.dumps({"figures": len(_plt.get_fignums()), "lacks": _lacks}))
"""
# Run last in the ablation notebook: its forest plot as drawn.
FOREST_CHECK = """
import json as _json
from matplotlib.container import ErrorbarContainer as _EB
_drawn = [_ax for _ax in forest_fig.axes if _ax.containers] if forest_fig else []
_main = [_ax for _ax in forest_fig.axes if _ax.get_ylabel() != "verdict"] if forest_fig else []
print("FOREST_CHECK " + _json.dumps({
    "sweep": str(sweep),
    "errorbars": sum(isinstance(_c, _EB) for _ax in _drawn for _c in _ax.containers),
    "rows": sum(len(_ax.get_yticks()) for _ax in _main),
    "forest": FOREST,
}))
"""


def _run(nb, results: Path, cwd: Path, monkeypatch) -> list:
    """Execute ``nb`` on ``results`` (the kernel inherits GDBENCH_RESULTS); its outputs."""
    nbclient = pytest.importorskip("nbclient")
    monkeypatch.setenv("GDBENCH_RESULTS", str(results))
    nbclient.NotebookClient(
        nb, timeout=300, kernel_name="python3", resources={"metadata": {"path": str(cwd)}}
    ).execute()
    return [o for c in nb.cells if c.cell_type == "code" for o in c.outputs]


def _execute(name: str, results: Path, cwd: Path, monkeypatch) -> str:
    """The notebook executed on ``results`` with the checks above; its printed text, one string."""
    nbformat = pytest.importorskip("nbformat")
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    nb.cells.insert(0, nbformat.v4.new_code_cell(KEEP_FIGURES))
    nb.cells.append(nbformat.v4.new_code_cell(FIGURE_CHECK))
    if name == "ablation":
        nb.cells.append(nbformat.v4.new_code_cell(FOREST_CHECK))
    outputs = _run(nb, results, cwd, monkeypatch)
    assert not [o for o in outputs if o.output_type == "error"]
    assert not [o for o in outputs if o.output_type == "stream" and o.name == "stderr" and "Traceback" in o.text]
    assert any(o.output_type == "display_data" and "image/png" in o.data for o in outputs)  # it drew its figure
    text = "".join(o.text for o in outputs if o.output_type == "stream" and o.name == "stdout")
    check = json.loads(re.search(r"^FIGURE_CHECK (.*)$", text, re.M).group(1))
    assert check["figures"] >= 1 and check["lacks"] == [], check["lacks"]
    return text


VERDICT = re.compile(r"^(\w+)\.csv: (\w+) = \S+ \(want [^)]*\) -> (met|NOT met|not decided .*)$", re.M)


def _check_targets(text: str, results: Path) -> dict:
    """Each target the notebook judged, against the summary JSON of the sweep it judged it on (written by
    the benchmark beside its CSV): the same verdict, so never "NOT met" where the JSON says met; every
    target of those JSONs judged once. Returns {target: verdict}."""
    judged = {}
    for stem, key, said in VERDICT.findall(text):
        assert key not in judged, f"{key} judged twice"
        stored = json.loads((results / f"{stem}_summary.json").read_text())["targets"][key]["met"]
        want = "met" if stored is True else "NOT met" if stored is False else "not decided"
        assert said.split(" (")[0] == want, (
            f"{stem}.csv: {key}: the notebook says {said!r}, {stem}_summary.json {want!r}"
        )
        judged[key] = said
    for line in text.splitlines():  # no other line may say it
        assert "NOT met" not in line or VERDICT.match(line), line
    stems = {stem for stem, _, _ in VERDICT.findall(text)}
    for stem in stems:
        stored = json.loads((results / f"{stem}_summary.json").read_text())["targets"]
        assert set(stored) <= set(judged), f"not judged: {set(stored) - set(judged)}"
    return judged


@pytest.mark.parametrize("name", NAMES)
def test_notebooks_are_stored_without_outputs(name):
    nb = json.loads((NOTEBOOKS / f"{name}.ipynb").read_text())
    code = [c for c in nb["cells"] if c["cell_type"] == "code"]
    assert code and all(c["outputs"] == [] and c["execution_count"] is None for c in code)


@pytest.fixture(scope="module")
def small_results(tmp_path_factory):
    from gdbench.experiments.tables import tables
    from gdbench.refcheck import bm_error, bm_render, bm_stability

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
    text = _execute(name, small_results, tmp_path, monkeypatch)
    if name == "render_speed":
        _check_targets(text, small_results)
        assert "render.csv: not in" in text  # the small data has no render sweep: said in one line, skipped


@pytest.mark.parametrize("name", NAMES)
def test_notebook_runs_on_the_shipped_results(name, monkeypatch, tmp_path):
    """On docs/results as shipped (what `make notebooks` runs): no error, every figure labelled,
    each target judged as its sweep's summary JSON says (never "NOT met" where that JSON says
    met), and the forest plot one interval per row of the sweep's verdict.csv that has one."""
    text = _execute(name, SHIPPED, tmp_path, monkeypatch)
    if name == "render_speed":
        judged = _check_targets(text, SHIPPED)
        assert judged and "peers.csv: " in text and "render.csv: " in text  # both sweeps read, targets judged
    if name == "ablation":
        from gdbench.core.io import num, read_csv

        forest = json.loads(re.search(r"^FOREST_CHECK (.*)$", text, re.M).group(1))
        rows = read_csv(Path(forest["sweep"]) / "verdict.csv")
        with_ci = [r for r in rows if all(math.isfinite(num(r[k])) for k in ("mean_diff", "ci_low", "ci_high"))]
        across = [r for r in with_ci if all(math.isfinite(num(r.get(k))) for k in ("prompt_ci_low", "prompt_ci_high"))]
        assert rows and forest["forest"]["rows"] == len(rows)
        assert forest["rows"] == len(with_ci) == forest["forest"]["intervals"]  # a row per interval, no empty rows
        assert forest["forest"]["prompt_intervals"] == len(across) > 0  # the shipped sweep reads both ways
        assert forest["errorbars"] == len(with_ci) + len(across)
        assert len(forest["forest"]["without_interval"]) == len(rows) - len(with_ci)


WRITTEN_BY = {  # a notebook's first input and the command that writes it
    "render_speed": ("peers.csv", "`gdbench bench peers --out DIR`"),
    "error_vs_runtime": ("error_vs_runtime.csv", "`gdbench bench error --out DIR`"),
    "stability": ("stability.csv", "`gdbench bench stability --out DIR`"),
    "ablation": ("cells.csv", "`gdbench sweep --out DIR`"),
}


@pytest.mark.parametrize("name", NAMES)
def test_notebook_names_a_missing_input(name, monkeypatch, tmp_path):
    """On a folder without its input (`make bench` writes only render.csv): one line naming the
    file and the command that writes it, the rest skipped, no error."""
    nbformat = pytest.importorskip("nbformat")
    (tmp_path / "results").mkdir()
    nb = nbformat.read(NOTEBOOKS / f"{name}.ipynb", as_version=4)
    outputs = _run(nb, tmp_path / "results", tmp_path, monkeypatch)
    assert not [o for o in outputs if o.output_type in ("error", "display_data")]
    lines = "".join(o.text for o in outputs if o.output_type == "stream").splitlines()
    assert [line for line in lines if all(w in line for w in WRITTEN_BY[name])], lines
