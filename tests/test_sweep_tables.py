"""A sweep's tables and verdicts from any mix of values (checked against an oracle verdict), the
code's name, the turned class, the decisive script's rounds and the docs' janus settings."""

import math
import shutil
import statistics

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from tests._util import TINY_CELL, csv_rows, strict_json

PROMPT = "a yellow duck"
TINY = TINY_CELL


def _oracle_verdict(a: list, b: list, fails_at) -> str:
    """The verdict words from the pairs alone, written out independently of claims.verdict
    (where only the tests can decide, the words they may give). The table holds two claims with
    the same values, so Holm doubles the smallest exact p: n pairs all one way give p = 2 / 2^n
    and p_holm = 4 / 2^n, under 0.05 only from n = 7 on (at n = 6 the tests decide)."""
    pairs = [(x, y) for x, y in zip(a, b) if x is not None and y is not None and x == x and y == y]
    if not pairs:
        return "not measured"
    if all(x == 0 and y == 0 for x, y in pairs):
        return "not testable here (neither preset fails)"
    if fails_at is not None and all(x == fails_at and y == fails_at for x, y in pairs):
        return "not testable here (both always fail)"
    if len(pairs) < 6:
        return "too few pairs (n < 6)"
    if len(pairs) >= 7 and all(x < y for x, y in pairs):
        return "holds"  # p_holm = 4 / 2^n < 0.05
    if len(pairs) >= 7 and all(x > y for x, y in pairs):
        return "does not hold"

    def upper(v: list) -> float:  # one-sided 95% t bound of the mean

        from scipy import stats

        if len(set(v)) == 1:
            return v[0]
        return statistics.fmean(v) + stats.t.ppf(0.95, len(v) - 1) * statistics.stdev(v) / len(v) ** 0.5

    if upper([y for _, y in pairs]) < 0.05 and upper([x for x, _ in pairs]) < 0.05:
        return "not testable here (baseline fails < 0.05)"  # both arms surely under the margin: nothing to reduce
    if all(x == y for x, y in pairs):
        return "no effect beyond +-0.05"  # every one-sided test of d -+ m has p <= 2^-n
    return "tests"


values = st.one_of(st.none(), st.just(float("nan")), st.just(0.0), st.just(1.0), st.floats(0, 1, width=32))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pairs=st.lists(st.tuples(values, values), min_size=0, max_size=12), gaussians=st.integers(1, 10_000))
@example(pairs=[(1.0, 0.0)] * 6, gaussians=1)  # all one way, but Holm over two claims: undecided
@example(pairs=[(1.0, 0.0)] * 7, gaussians=1)  # all one way and enough pairs: does not hold
@example(pairs=[(0.0, 1.0)] * 7, gaussians=1)
def test_tables_from_any_mix_of_values_are_strict_and_numeric_with_the_right_verdict(
    tmp_path, monkeypatch, pairs, gaussians
):
    from gdbench.core.io import num, write_json
    from gdbench.experiments import tables as sweep_tables
    from gdbench.experiments.tables import tables

    monkeypatch.setattr(sweep_tables, "plot", lambda rows, path: path)  # the figure is not under test here

    rows = []
    for i, (a, b) in enumerate(pairs):
        for preset, v in (("gd", a), ("gd-no-sn", b)):
            rows.append({"setting": "easy", "prompt": f"p{i}", "preset": preset, "seed": 0,
                         "multi_face_rate": v, "colmap_failure_rate": v, "gaussians": gaussians})  # fmt: skip
    out = tmp_path / "t"
    shutil.rmtree(out, ignore_errors=True)
    if not rows:
        return
    tables(rows, out)
    write_json({"rows": rows}, out / "rows.json")
    back = strict_json(out / "rows.json")["rows"]
    assert [num(r["multi_face_rate"]) == num(r["multi_face_rate"]) for r in back] == [
        r["multi_face_rate"] is not None and r["multi_face_rate"] == r["multi_face_rate"] for r in rows
    ]
    for row in csv_rows(out / "summary.csv"):
        for key, value in row.items():
            if key.endswith(("_mean", "_std", "_median", "_n")):
                assert value == "" or math.isfinite(float(value)), (key, value)
    verdicts = {v["metric"]: v for v in csv_rows(out / "verdict.csv")}
    want = _oracle_verdict([a for a, _ in pairs], [b for _, b in pairs], 1.0)
    for metric in ("multi_face_rate",):
        got = verdicts[metric]["verdict"]
        if want == "tests":
            assert got in ("holds", "does not hold", "no effect beyond +-0.05", "undecided") or got.startswith(
                "too few non-tied pairs"
            )
        else:
            assert got == want
        for key in ("mean_a", "mean_b", "mean_diff", "ci_low", "ci_high", "p_value", "p_holm", "p_equivalence"):
            value = verdicts[metric][key]
            assert value == "" or math.isfinite(float(value))


def test_the_code_name_follows_the_code_and_only_the_code(tmp_path, monkeypatch):
    """A checkout is named by its commit; the same edits give the same name and other edits
    another; edits outside the code (docs, results) none; where git cannot say, the source
    files' hash names it."""
    import subprocess

    from gdbench.core import provenance

    root = tmp_path / "repo"
    (root / "gdbench").mkdir(parents=True)
    (root / "renderers").mkdir()
    (root / "docs").mkdir()
    (root / "gdbench" / "core").mkdir()
    src = root / "gdbench" / "core" / "provenance.py"
    src.write_text(open(provenance.__file__).read())
    (root / "gdbench" / "a.py").write_text("x = 1\n")
    (root / "docs" / "notes.md").write_text("notes\n")
    git = ["git", "-c", "user.name=t", "-c", "user.email=t@t", "-c", "commit.gpgsign=false"]
    subprocess.run([*git, "init", "-q"], cwd=root, check=True)
    subprocess.run([*git, "add", "-A"], cwd=root, check=True)
    subprocess.run([*git, "commit", "-qm", "c"], cwd=root, check=True)
    head = subprocess.run(["git", "rev-parse", "--short=12", "HEAD"], cwd=root, capture_output=True, text=True)

    def name():
        monkeypatch.setattr(provenance, "__file__", str(src))
        provenance.code_commit.cache_clear()
        try:
            return provenance.code_commit()
        finally:
            provenance.code_commit.cache_clear()

    clean = name()
    assert clean == head.stdout.strip()
    (root / "docs" / "notes.md").write_text("other notes\n")  # not the code
    assert name() == clean
    (root / "gdbench" / "a.py").write_text("x = 2\n")
    edited = name()
    assert edited.startswith(clean + "-dirty-") and name() == edited  # the same edits, the same name
    (root / "gdbench" / "a.py").write_text("x = 3\n")
    assert name() not in (clean, edited)
    (root / "gdbench" / "a.py").write_text("x = 1\n")
    (root / "gdbench" / "b.py").write_text("y = 1\n")  # a new source file is an edit too
    assert name().startswith(clean + "-dirty-")
    monkeypatch.setenv("PATH", str(tmp_path / "no-git-here"))  # git missing: the sources' hash
    by_source = name()
    assert by_source.startswith("src-") and len(by_source) == 16
    (root / "gdbench" / "b.py").write_text("y = 2\n")
    assert name().startswith("src-") and name() != by_source


def test_turned_is_a_failure_only_where_the_front_is_defined_and_the_result_has_one():
    import math

    from gdbench.experiments.sweep import turned_failure

    assert turned_failure({"turned_deg": 90.0, "featureless_rate": 0.0}, True) == 1.0
    assert turned_failure({"turned_deg": -45.0, "featureless_rate": 0.0}, True) == 0.0
    assert turned_failure({"turned_deg": 180.0, "featureless_rate": 0.0}, True) == 1.0
    assert math.isnan(turned_failure({"turned_deg": 90.0, "featureless_rate": 0.0}, False))  # janus: no front
    assert math.isnan(turned_failure({"turned_deg": 95.0, "featureless_rate": 1.0}, True))  # a blob
    assert math.isnan(turned_failure({}, True))  # not scored


def test_decisive_script_runs_blocks_in_rounds_and_merges_them(tmp_path, monkeypatch):
    """gdbench.experiments.decisive: two blocks in two rounds of seeds give every cell once (the
    second round skips the first's), ``collect`` reads back exactly the cells the sweeps returned,
    and ``report`` writes one verdict table over both blocks' groups."""
    import argparse

    from gdbench.experiments import decisive as dec

    tiny = dict(TINY)
    blocks = [
        dec.Block("a", ["empirical-v1"], ["easy"], ["gd", "gd-no-sn"], steps=4, prompts=[PROMPT], overrides=tiny),
        dec.Block("b", ["empirical-v4"], ["easy"], ["gd"], steps=4, prompts=[PROMPT], overrides=tiny),
    ]
    args = argparse.Namespace(executor="local", address="", workers=1, progress=False)
    rows = dec.run_blocks(blocks, [0, 1], tmp_path, args, rounds=2)
    assert [len(rows[b]) for b in ("a", "b")] == [4, 2]
    got = dec.collect(tmp_path)  # (groups say their step count when it is not 1000)
    key = lambda r: (r["group"].replace(", 4 steps", ""), r["preset"], r["seed"])  # noqa: E731
    assert sorted(map(key, got)) == sorted(map(key, rows["a"] + rows["b"]))
    assert {r["views_per_step"] for r in got if r["group"] == "empirical-v4, 4 steps"} == {4}
    with pytest.raises(ValueError, match="cells found twice"):  # a plain folder overlapping a block
        dec.collect(tmp_path, [(tmp_path / "blocks" / "a", "empirical-v1")])
    with pytest.raises(ValueError, match="presets"):
        dec.Block("c", ["empirical-v1"], ["easy"], ["gd", "best"])
    from gdbench.experiments.decisive_report import report

    report(tmp_path, tmp_path / "results", dec.collect, PROMPT)
    verdicts = csv_rows(tmp_path / "results" / "verdict.csv")
    assert {v["group"] for v in verdicts} == {"empirical-v1, 4 steps"}  # block b has one preset: no claim
    assert len(csv_rows(tmp_path / "results" / "cells.csv")) == 6
    assert (tmp_path / "results" / "turntables_a.png").is_file() and (
        tmp_path / "results" / "turntables_b.png"
    ).is_file()
    # one figure over both blocks: a row per seed-0 cell of each (a: gd, gd-no-sn; b: gd), 1.7 in
    # each at 90 dpi under a half-inch title
    from PIL import Image

    heights = {n: Image.open(tmp_path / "results" / f"turntables{n}.png").height for n in ("", "_a", "_b")}
    rows_of = {n: round((h / 90 - 0.5) / 1.7) for n, h in heights.items()}
    assert rows_of == {"": 3, "_a": 2, "_b": 1}


def test_the_docs_state_each_priors_janus_setting_as_the_code_applies_it():
    """docs/scoring.md's settings table names the janus setting's front bias for each prior as
    ``setting_overrides`` gives it (1 on the empirical prior, 2 on the learned one)."""
    from pathlib import Path

    from gdbench.experiments.sweep import setting_overrides

    row = next(ln for ln in (Path(__file__).resolve().parents[1] / "docs" / "scoring.md").read_text().splitlines()
               if ln.startswith("| `janus` |"))  # fmt: skip
    for prior, words in (("empirical", "on the empirical prior"), ("learned", "on the learned prior")):
        o = setting_overrides("janus", prior)
        stated = f"--view-prompting {o['view_prompting']} --front-bias {o['front_bias']:g}` {words}"
        assert stated in row, (stated, row)
