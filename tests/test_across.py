"""Statistics with the prompt as the unit (gdbench/experiments/across.py, the sign-flip test of
claims.py) and the v3 experiment's design and report (gdbench/experiments/v3*.py): each against
an independent oracle (every sign pattern enumerated, the binomial closed form, a simulated t
test, variance components drawn at known values, the pre-stated design rules by hand)."""

import itertools
import math

import numpy as np
import pytest


def test_sign_flip_p_against_every_pattern_and_the_binomial():
    """Exact by meeting in the middle: equal to enumerating all 2^G sign patterns (G up to 12);
    with equal magnitudes the p is a binomial tail in closed form, also past the exact range
    (Monte Carlo there, within 4 standard errors)."""
    from scipy import stats

    from gdbench.experiments.stats import SIGN_FLIP_EXACT_UP_TO, sign_flip_p

    rng = np.random.default_rng(3)
    for g in (1, 2, 3, 7, 12):
        for _ in range(4):
            x = np.round(rng.normal(0.05, 0.2, g), 2)  # rounded: ties between patterns happen
            obs, a = abs(x.sum()), np.abs(x)
            k = sum(abs(np.dot(s, a)) >= obs - 1e-9 for s in itertools.product((1, -1), repeat=g))
            assert sign_flip_p(x) == pytest.approx(k / 2**g, abs=1e-12)
    assert sign_flip_p(np.zeros(5)) == 1.0 and math.isnan(sign_flip_p(np.array([])))

    def binomial(g: int, k: int) -> float:  # P(|2B - g| >= |2k - g|), B ~ Bin(g, 1/2)
        b = np.arange(g + 1)
        return float(stats.binom.pmf(b, g, 0.5)[np.abs(2 * b - g) >= abs(2 * k - g)].sum())

    for g, k in ((20, 15), (31, 22), (SIGN_FLIP_EXACT_UP_TO + 6, 35)):
        x = np.array([0.1] * k + [-0.1] * (g - k))
        want, got = binomial(g, k), sign_flip_p(x)
        tol = 1e-12 if g <= SIGN_FLIP_EXACT_UP_TO else 4 * math.sqrt(want * (1 - want) / 2**20) + 2**-20
        assert got == pytest.approx(want, abs=tol), (g, k)


def test_across_prompts_holds_on_the_sign_flip_test_when_asked():
    """``prompt_test='signflip'`` puts the exact sign-flip p (of the per-prompt means) in the Holm
    family; the t p stays beside it, and the default is the t test as before."""
    from gdbench.experiments.claims import CLAIMS, evaluate
    from gdbench.experiments.stats import sign_flip_p

    rng = np.random.default_rng(5)
    rows = []
    for i in range(8):
        for s in range(3):
            base = rng.uniform(0.4, 0.8)
            rows += [{"setting": "janus", "preset": "gd-no-sn", "prompt": f"p{i}", "seed": s, "janus_rate": base},
                     {"setting": "janus", "preset": "gd", "prompt": f"p{i}", "seed": s,
                      "janus_rate": base - 0.2 + rng.normal(0, 0.1)}]  # fmt: skip
    claims = [c for c in CLAIMS if (c.a, c.b, c.metric) == ("gd", "gd-no-sn", "janus_rate")]
    (t_row,) = evaluate(rows, claims)
    (f_row,) = evaluate(rows, claims, prompt_test="signflip")
    pm = {}
    for r in rows:
        pm.setdefault(r["prompt"], []).append(r["janus_rate"] * (1 if r["preset"] == "gd" else -1))
    means = np.array([np.sum(v) / 3 for v in pm.values()])
    assert f_row["p_prompts"] == pytest.approx(sign_flip_p(means)) == pytest.approx(2 / 2**8)  # all 8 negative
    assert t_row["p_prompts"] == pytest.approx(f_row["p_prompts_t"]) and t_row["p_prompts"] != f_row["p_prompts"]
    assert f_row["verdict_prompts"] == "holds" and f_row["prompt_ci_high"] < 0
    with pytest.raises(ValueError, match="test"):
        evaluate(rows, claims, prompt_test="z")


def test_variance_components_and_power_against_simulation():
    """Random-effects data drawn at known between- and within-prompt variances give them back;
    the noncentral-t power matches the rejection rate of simulated t tests across prompts."""
    from scipy import stats

    from gdbench.experiments.across import components, detectable, power, seeds_for_power

    rng = np.random.default_rng(0)
    keys, d = [], []
    for p in range(400):
        mu = rng.normal(0.1, 0.2)  # between: 0.04
        for s in range(3):
            keys.append((f"p{p}", s))
            d.append(mu + rng.normal(0, 0.3))  # within: 0.09
    c = components(keys, np.array(d))
    assert c["within"] == pytest.approx(0.09, rel=0.1) and c["between"] == pytest.approx(0.04, rel=0.25)
    g, s, effect, alpha = 31, 3, 0.12, 0.05 / 6
    sims = rng.normal(effect, 0.2, (4000, g)) + rng.normal(0, 0.3, (4000, g, s)).mean(axis=2)
    t = sims.mean(axis=1) / (sims.std(axis=1, ddof=1) / math.sqrt(g))
    rate = float((np.abs(t) > stats.t.ppf(1 - alpha / 2, g - 1)).mean())
    assert power(effect, 0.04, 0.09, g, s, alpha) == pytest.approx(rate, abs=0.03)
    need = seeds_for_power(effect, 0.04, 0.09, g, alpha, 0.5)
    assert need > 1 and power(effect, 0.04, 0.09, g, need, alpha) >= 0.5 > power(effect, 0.04, 0.09, g, need - 1, alpha)
    assert seeds_for_power(0.01, 0.04, 0.09, g, alpha, most=5) is None  # the between spread caps it
    mde = detectable(0.04, 0.09, g, 3, alpha)
    assert power(mde, 0.04, 0.09, g, 3, alpha) == pytest.approx(0.8, abs=1e-6)
    assert math.isnan(detectable(0.04, 0.09, g, 0, alpha))  # no seeds: no design


def test_components_with_unequal_seeds_and_power_at_few_prompts():
    """With 1, 2 and 5 seeds per prompt the within variance is the pooled one-way ANOVA's (by hand)
    and between is the prompt means' variance less within over the harmonic mean of the seeds; at
    2-3 degrees of freedom the power equals the noncentral t's integral over the chi-square (quad),
    also where scipy's far lower tail is NaN."""
    from scipy import integrate, stats

    from gdbench.experiments.across import components, power

    per = {"a": [0.1], "b": [0.3, -0.1], "c": [0.5, 0.2, 0.4, 0.0, 0.6], "d": [0.2, 0.25]}
    keys = [(p, i) for p, v in per.items() for i in range(len(v))]
    c = components(keys, np.array([x for v in per.values() for x in v]))
    ss = sum(((np.array(v) - np.mean(v)) ** 2).sum() for v in per.values())
    within = ss / (1 + 4 + 1)
    n_h = 4 / (1 + 1 / 2 + 1 / 5 + 1 / 2)
    assert c["within"] == pytest.approx(within)
    assert c["between"] == pytest.approx(max(0.0, np.var([np.mean(v) for v in per.values()], ddof=1) - within / n_h))

    def by_quad(nc: float, df: int, alpha: float) -> float:
        crit = stats.t.ppf(1 - alpha / 2, df)

        def f(v):  # P(|Z + nc| > crit * sqrt(v / df)) weighted by the chi-square density of v
            c = crit * math.sqrt(v / df)
            return (stats.norm.sf(c - nc) + stats.norm.cdf(-c - nc)) * stats.chi2.pdf(v, df)

        return integrate.quad(f, 0, np.inf, limit=200)[0]

    for prompts, effect in ((3, 0.4), (3, 1.2), (4, 0.9), (2, 3.0)):
        sd = math.sqrt(0.05 + 0.1 / 2)
        nc = effect / (sd / math.sqrt(prompts))
        assert power(effect, 0.05, 0.1, prompts, 2, 0.05) == pytest.approx(by_quad(nc, prompts - 1, 0.05), abs=2e-3)


def _cells(effects: dict, prompts: int, seeds, rng, *, group="learned-v1", setting="janus", metric="janus_rate"):
    """Rows of one (group, setting): each preset's rate = a prompt's baseline + its effect + noise."""
    rows = []
    for p in range(prompts):
        base = rng.uniform(0.5, 0.9)
        for s in seeds:
            for preset, e in effects.items():
                v = float(np.clip(base + e + rng.normal(0, 0.05), 0, 1))
                row = {"group": group, "setting": setting, "preset": preset, "prompt": f"prompt {p}", "seed": s}
                row |= {metric: v, "janus_failure_rate": v, "label_janus": round(v * 2) / 2, "gaussians": 1000.0}
                row |= {"gt_psnr": 20.0, "cell_s": 30.0}
                rows.append(row | {"registration_rate": 0.5, "train_commit": "abc", "variants": 3})
    return rows


def test_share_kept_by_a_control():
    """A control built to keep half of gd's effect in every prompt reads 0.5, its interval about it."""
    from gdbench.experiments.across import share_kept

    rows = _cells({"gd": -0.3, "gd-no-sn": 0.0, "gd-pose-locked": -0.15}, 12, [0, 1], np.random.default_rng(1))
    s = share_kept(rows, "gd-pose-locked", "janus_rate")
    assert s["prompts"] == 12 and s["share"] == pytest.approx(0.5, abs=0.08) and s["low"] < 0.5 < s["high"]
    # every arm read at the same seeds: a control missing seed 1 everywhere (its cells failed) and a
    # baseline whose seed 1 is far off give the share of seed 0 alone
    rows2 = [r for r in rows if not (r["preset"] == "gd-pose-locked" and r["seed"] == 1)]
    rows2 = [r | {"janus_rate": r["janus_rate"] + 0.4} if (r["preset"], r["seed"]) == ("gd-no-sn", 1) else r
             for r in rows2]  # fmt: skip
    seed0 = share_kept([r for r in rows if r["seed"] == 0], "gd-pose-locked", "janus_rate")
    assert share_kept(rows2, "gd-pose-locked", "janus_rate")["share"] == pytest.approx(seed0["share"])
    # no effect to keep: resamples flip its sign, and the interval is unbounded, not made finite
    flat = _cells({"gd": 0.0, "gd-no-sn": 0.0, "gd-pose-locked": 0.0}, 12, [0, 1], np.random.default_rng(2))
    s = share_kept(flat, "gd-pose-locked", "janus_rate")
    assert s["flipped"] > 0 and math.isnan(s["low"]) and math.isnan(s["high"])


def test_design_applies_the_pre_stated_rules(tmp_path, monkeypatch):
    """The pilot's rules by hand: a four-view group that lowers both arms by 0.2 is swept, an
    instance baseline under the margin is not, a COLMAP baseline above it is; the seeds are the
    fewest that power every main claim (checked against ``power`` itself)."""
    from gdbench.experiments import v3_design as v3
    from gdbench.experiments.across import power
    from gdbench.experiments.v3_report import design

    monkeypatch.setattr(v3, "prompts", lambda: [f"prompt {i}" for i in range(31)])
    rng = np.random.default_rng(2)
    arms = {"gd": -0.3, "gd-no-sn": 0.0, "gd-redraw-step": -0.1, "gd-pose-locked": -0.25}
    rows = _cells(arms, 8, [100, 101], rng)
    rows += [
        r | {"group": "learned-v4", "janus_rate": r["janus_rate"] - 0.2}
        for r in rows
        if r["preset"] in ("gd", "gd-no-sn")
    ]  # fmt: skip (the pilot's four-view block)
    rows += _cells({"gd": 0.0, "gd-no-sn": 0.0}, 8, [100, 101], rng, setting="instance",
                   metric="instance_inconsistency")  # fmt: skip
    for r in rows[-32:]:
        r["instance_inconsistency"] = 0.01
    rows += _cells({"gd": 0.0, "gd-no-sn": 0.0, "sjc-gs": 0.0}, 8, [100, 101], rng, group="empirical-v1",
                   setting="easy", metric="colmap_failure_rate")  # fmt: skip
    got = design(rows, tmp_path)
    assert (got["v4"], got["instance"], got["colmap"]) == (True, False, True)
    assert got["family"] == 3 + 3 and got["alpha_first_step"] == pytest.approx(0.05 / 6)  # the primary family
    table = [r for r in __import__("csv").DictReader(open(tmp_path / "power.csv")) if r["main"] == "True"]
    assert len(table) == 6 and {r["metric"] for r in table} == {"label_janus"}
    v1, v4 = ({r["b"]: r for r in table if r["group"] == g} for g in ("learned-v1", "learned-v4"))
    assert v4["gd-pose-locked"]["within_var"] == v1["gd-pose-locked"]["within_var"]  # the one-view spread

    def p(r, seeds):
        return power(
            float(r["effect"]), float(r["between_var"]), float(r["within_var"]), 31, seeds, got["alpha_first_step"]
        )

    assert not got["underpowered"] and got["seeds"] >= 2
    assert all(p(r, got["seeds"]) >= 0.8 for r in table)
    assert got["seeds"] == 2 or any(p(r, got["seeds"] - 1) < 0.8 for r in table)  # the fewest
    with pytest.raises(SystemExit, match="labels"):  # the primary outcome cannot be planned without them
        design([{k: v for k, v in r.items() if k != "label_janus"} for r in rows], tmp_path / "none")


def test_report_reads_across_prompts_first_and_draws_a_forest(tmp_path, monkeypatch):
    """The report's across-prompts row equals the mean of the per-prompt means with the exact
    sign-flip p; a prompt built to go the other way beyond the margin is named; one forest plot per
    main claim is drawn with a row per prompt."""
    from gdbench.experiments import v3_design as v3
    from gdbench.experiments.stats import sign_flip_p
    from gdbench.experiments.v3_report import report

    monkeypatch.setattr(v3, "prereg_commit", lambda root=None: None)
    rng = np.random.default_rng(4)
    rows = _cells({"gd": -0.3, "gd-no-sn": 0.0, "gd-redraw-step": -0.1, "gd-pose-locked": -0.28}, 10, [0, 1, 2], rng)
    for r in rows:  # prompt 9 goes the other way
        if r["prompt"] == "prompt 9" and r["preset"] == "gd":
            r["janus_rate"] += 0.5
    got = report(rows, tmp_path, tmp_path / "results", figures=tmp_path / "figures")
    v = next(x for x in got["verdicts"] if x["b"] == "gd-no-sn" and x["metric"] == "janus_rate")
    # the README's copies: the primary claims' forest plots (label_janus), the same bytes, no turntables here
    assert sorted(p.name for p in (tmp_path / "figures").iterdir()) == sorted(
        f"v3_forest_label_janus_gd_vs_{b}.png" for b in ("gd-no-sn", "gd-redraw-step", "gd-pose-locked")
    )
    for c in got["copies"]:
        assert (
            c.read_bytes()
            == (tmp_path / "results" / "figures" / c.name.replace("v3_forest_", "forest_learned-v1_")).read_bytes()
        )
    per = {}
    for r in rows:
        if r["preset"] in ("gd", "gd-no-sn"):
            per.setdefault(r["prompt"], []).append(r["janus_rate"] * (1 if r["preset"] == "gd" else -1))
    means = np.array([sum(x) / 3 for x in per.values()])
    assert float(v["prompt_mean_diff"]) == pytest.approx(means.mean())
    assert float(v["p_prompts"]) == pytest.approx(sign_flip_p(means))
    assert "prompt 9" in v["against"] and len(got["forests"]) == 9  # three comparisons x three metrics
    md = (tmp_path / "results" / "report.md").read_text()
    assert "gd-pose-locked gives" in md and "across prompts" in md
    assert "gd vs gd-no-sn, janus_rate: prompt 9 +" in md  # the reversal names its metric
    assert "## What the raters saw" not in md and got["turntables"] is None  # no rater files, no GIFs
    bare = [{k: v for k, v in r.items() if k != "label_janus"} for r in rows]  # before any label: no crash
    report(bare, tmp_path, tmp_path / "unlabelled")
    assert "## The share labelled Janus" not in (tmp_path / "unlabelled" / "report.md").read_text()
    from PIL import Image

    assert Image.open(got["forests"][0]).size[1] > 0.22 * 10 * 100  # a row per prompt at 100 dpi


def test_registration_precedes_in_git_history():
    """``precedes`` reads the repository's own history: a commit precedes its child, not the reverse."""
    import subprocess
    from pathlib import Path

    from gdbench.experiments.v3_design import precedes

    root = Path(__file__).resolve().parents[1]
    log = subprocess.run(["git", "-C", str(root), "log", "--format=%h", "-2"], capture_output=True, text=True)
    if log.returncode != 0 or len(log.stdout.split()) < 2:
        pytest.skip("no git history here")
    child, parent = log.stdout.split()
    assert precedes(parent, child) is True and precedes(child, parent) is False


def test_v3_prompts_follow_the_rule_and_the_sweep_waits_for_a_registration():
    """The prompts are every caption the front-biased model was trained on (held-out ones out) with
    a front: at least 30, read here from the model's metadata and the catalogue independently of
    ``v3.prompts``; the pilot's are every fourth; the sweep refuses to run before a design is
    registered, and a registered design gives its blocks."""
    from gdbench.assets.library import CAPTIONS, FRONTS
    from gdbench.experiments import v3_design as v3
    from gdbench.priors.learned.prior import model_captions

    known, held = model_captions("front")
    want = [c for c in CAPTIONS if c in known and c not in held and FRONTS.get(c)]
    assert v3.prompts() == want and len(want) >= 30 and "a hamburger" not in want
    assert v3.pilot_prompts() == want[::4] and not set(held) & set(want)
    if v3.REGISTERED is None:
        from gdbench.experiments.v3 import main

        with pytest.raises(SystemExit, match="registered"):
            main(["sweep", "--out", "unused"])
    blocks = v3.sweep_blocks({"v4": True, "instance": False, "colmap": True, "seeds": 3})
    assert [(b.name, b.groups) for b in blocks] == [
        ("janus", ["learned-v1", "learned-v4"]),
        ("colmap", ["empirical-v1"]),
    ]
    assert all(b.prompts == want and b.steps == v3.STEPS for b in blocks)


def test_raters_labels_unblinded_and_attached_as_shares(tmp_path):
    """Numbered labels go through the sheets' key to run ids (a number outside the key, or a label
    outside the classes, is an error naming it); each result's label shares are the share of the
    raters that call it Janus (front everywhere or second face) or not fine; a result one rater
    left out gets none."""
    import json

    from gdbench.experiments.outcome import attach_labels
    from gdbench.metrics.label_sheets import unblind

    key = {str(n): {"run_id": f"r{n}", "run": f"/x/{n}", "caption": "a corgi"} for n in (1, 2, 3)}
    (tmp_path / "key.json").write_text(json.dumps(key))
    raters = {"a": ["front_everywhere", "fine", "blob"], "b": ["second_face", "blob", "blob"]}
    files = []
    for name, labels in raters.items():
        src = tmp_path / f"{name}.csv"
        src.write_text("number,label,confidence\n" + "".join(f"{n},{lab},high\n" for n, lab in zip((1, 2, 3), labels)))
        files.append(tmp_path / f"{name}_by_id.csv")
        assert [r["run_id"] for r in unblind(src, tmp_path / "key.json", files[-1])] == ["r1", "r2", "r3"]
    rows = [{"run_id": f"r{n}"} for n in (1, 2, 3, 4)]
    got = attach_labels(rows, files)
    assert [(r.get("label_janus"), r.get("label_failure")) for r in got] == [
        (1.0, 1.0),
        (0.0, 0.5),
        (0.0, 1.0),
        (None, None),
    ]
    bad = tmp_path / "bad.csv"
    bad.write_text("number,label,run_id\n1,fine,x\n2,blob,x\n")  # 3 missing; a run_id column of its own
    with pytest.raises(ValueError, match="3"):
        unblind(bad, tmp_path / "key.json", tmp_path / "x.csv")
    bad.write_text("number,label,run_id\n1,fine,x\n2,blob,x\n3,fine,x\n")
    assert [r["run_id"] for r in unblind(bad, tmp_path / "key.json", tmp_path / "x.csv")] == ["r1", "r2", "r3"]
    bad.write_text("number,label\n9,fine\n")
    with pytest.raises(ValueError, match="'9'"):
        unblind(bad, tmp_path / "key.json", tmp_path / "x.csv")
    bad.write_text("number,label\n1,face\n")
    with pytest.raises(ValueError, match="'face'"):
        unblind(bad, tmp_path / "key.json", tmp_path / "x.csv")


def test_raters_who_disagree_leave_the_primary_verdicts_undecided(tmp_path, monkeypatch):
    """The registered rule: raters who agree at kappa < 0.4 on the Janus split make every primary
    verdict 'undecided (the raters disagree)' however strong its p; raters who agree leave it. The
    kappa is Cohen's, checked here against its formula on the two label lists."""
    import csv

    from gdbench.experiments import v3_design
    from gdbench.experiments.outcome import attach_labels
    from gdbench.experiments.v3_design import raters_kappa
    from gdbench.experiments.v3_report import report

    monkeypatch.setattr(v3_design, "prereg_commit", lambda root=None: None)
    rng = np.random.default_rng(6)
    rows = _cells({"gd": -0.4, "gd-no-sn": 0.0, "gd-redraw-step": 0.0, "gd-pose-locked": 0.0}, 10, [0, 1, 2], rng)
    for i, r in enumerate(rows):
        r["run_id"] = f"r{i}"
    truth = ["front_everywhere" if r["janus_rate"] > 0.5 else "blob" for r in rows]  # gd mostly not Janus
    noise = [str(rng.choice(["front_everywhere", "blob"])) for _ in rows]
    for name, labels in (("a", truth), ("same", truth), ("random", noise)):
        with open(tmp_path / f"{name}.csv", "w", newline="") as f:
            w = csv.writer(f)
            w.writerow(["run_id", "label"])
            w.writerows((r["run_id"], lab) for r, lab in zip(rows, labels))
    ids = {r["run_id"] for r in rows}
    k = raters_kappa([tmp_path / "a.csv", tmp_path / "random.csv"], ids)["kappa_janus"]
    ja, jb = np.array([t == "front_everywhere" for t in truth]), np.array([t == "front_everywhere" for t in noise])
    pe = ja.mean() * jb.mean() + (1 - ja.mean()) * (1 - jb.mean())
    assert k == pytest.approx(((ja == jb).mean() - pe) / (1 - pe)) and k < 0.4
    for other, want in (("same", "holds"), ("random", "undecided (the raters disagree)")):
        files = [tmp_path / "a.csv", tmp_path / f"{other}.csv"]
        got = report(attach_labels(rows, files), tmp_path, tmp_path / other, files)
        primary = [v for v in got["verdicts"] if v["family"] == "primary"]
        assert len(primary) == 3 and all(v["verdict_prompts"] == want for v in primary), other


def test_example_turntables_are_chosen_by_rule_and_stacked(tmp_path):
    """The report's example prompts follow the rule (the most negative mean, the first prompt Janus
    in every cell of every arm, the most positive mean above 0, ties to the first name), none where
    no mean qualifies; their turntables stack into one sheet, a grid per prompt (each row a preset,
    its frames from the cells' GIFs), and the grids in between are removed."""
    import imageio.v3 as iio
    from PIL import Image

    from gdbench.experiments.v3_report import example_prompts, example_turntables, pairs

    rows = _cells({"gd": -0.3, "gd-no-sn": 0.0}, 7, [0, 1], np.random.default_rng(2), metric="label_janus")
    lab = {  # prompt: (gd, gd-no-sn); the differences -1, 0 (ceiling), +0.5, 0, -0.5, +0.5 (a tie), -1 (a tie)
        "prompt 0": (0.0, 1.0), "prompt 1": (1.0, 1.0), "prompt 2": (0.5, 0.0), "prompt 3": (0.5, 0.5),
        "prompt 4": (0.5, 1.0), "prompt 5": (1.0, 0.5), "prompt 6": (0.0, 1.0),
    }  # fmt: skip
    for r in rows:
        r["label_janus"] = lab[r["prompt"]][r["preset"] == "gd-no-sn"]
    keys, d = pairs(rows, "learned-v1", "janus", "gd", "gd-no-sn", "label_janus")
    chosen = example_prompts(rows, keys, d, "label_janus", "learned-v1", ("gd", "gd-no-sn"))
    assert chosen == {
        "the largest effect": "prompt 0",
        "Janus in every arm": "prompt 1",
        "the largest reversal": "prompt 2",
    }
    # a ceiling needs every arm: without gd-no-sn's cells prompt 1 is no ceiling; nothing reverses where all gain
    gd_only = [r for r in rows if not (r["prompt"] == "prompt 1" and r["preset"] == "gd-no-sn")]
    assert "Janus in every arm" not in example_prompts(gd_only, keys, d, "label_janus", None, ("gd", "gd-no-sn"))
    assert example_prompts(rows, keys, -np.abs(d), "label_janus").get("the largest reversal") is None
    assert example_prompts(rows, keys, np.abs(d), "label_janus").get("the largest effect") is None
    blocks = tmp_path / "janus"
    assert example_turntables(blocks, chosen, 0, tmp_path / "t.webp") is None  # no GIF kept: no sheet
    rng = np.random.default_rng(0)
    for prompt in ("prompt_0", "prompt_1"):
        for preset in ("gd", "gd-no-sn"):
            gif = blocks / "cells" / "learned-v1" / "janus" / prompt / preset / "seed0" / "turntable.gif"
            gif.parent.mkdir(parents=True)
            iio.imwrite(gif, rng.integers(0, 255, (12, 32, 32, 3), dtype=np.uint8), extension=".gif")
    got = example_turntables(blocks, chosen, 0, tmp_path / "t.webp", "learned-v1")
    one = example_turntables(blocks, {"x": "prompt 0"}, 0, tmp_path / "one.webp")
    assert Image.open(got).height == 2 * Image.open(one).height  # two prompts have GIFs, the third none
    assert sorted(p.name for p in tmp_path.iterdir()) == ["janus", "one.webp", "t.webp"]  # no grid left behind


def test_what_the_raters_saw_counts_each_label_per_arm(tmp_path):
    """The raters' make-up per arm equals a direct count of their files by the cells' presets (all
    four labels), and each prompt's share labelled Janus per arm is the mean of its cells'
    ``label_janus``; the rows are sorted by gd minus the first baseline (not by name), a prompt
    missing an arm last; without labels there are no rows."""
    import collections
    import csv

    from gdbench.experiments.outcome import attach_labels
    from gdbench.experiments.v3_report import what_raters_saw
    from gdbench.metrics.agreement import LABELS

    rng = np.random.default_rng(5)
    rows = _cells({"gd": -0.3, "gd-no-sn": 0.0}, 4, [0, 1, 2], rng)
    for i, r in enumerate(rows):
        r["run_id"] = f"r{i:03d}"
    rows = [r for r in rows if not (r["prompt"] == "prompt 0" and r["preset"] == "gd-no-sn")]  # an arm missing
    files = []
    for k in range(2):
        f = tmp_path / f"rater{k}.csv"
        labs = rng.choice(list(LABELS), size=len(rows))
        with open(f, "w", newline="") as fh:
            w = csv.writer(fh)
            w.writerow(["run_id", "label"])
            w.writerows([(r["run_id"], lab) for r, lab in zip(rows, labs)] + [("elsewhere", "blob")])
        files.append(f)
    bare = [{k: v for k, v in r.items() if k != "label_janus"} for r in rows]
    assert what_raters_saw(bare, [], ("gd", "gd-no-sn")) == ([], [])  # no labels: nothing to show
    rows = attach_labels(rows, files)
    counts, prompts = what_raters_saw(rows, files, ("gd", "gd-no-sn"))
    preset = {r["run_id"]: r["preset"] for r in rows}
    for k, f in enumerate(files, start=1):
        with open(f, newline="") as fh:
            direct = collections.Counter(
                (preset[r["run_id"]], r["label"]) for r in csv.DictReader(fh) if r["run_id"] in preset
            )
        for c in (c for c in counts if c["rater"] == k):
            assert c["results"] == sum(c[lab] for lab in LABELS) == (12 if c["preset"] == "gd" else 9)
            assert all(c[lab] == direct[c["preset"], lab] for lab in LABELS)
    for p in prompts:
        for arm in ("gd", "gd-no-sn"):
            cells = [r["label_janus"] for r in rows if r["prompt"] == p["prompt"] and r["preset"] == arm]
            assert p[arm] == (pytest.approx(np.mean(cells)) if cells else "")
    assert prompts[-1]["prompt"] == "prompt 0" and prompts[-1]["gd-no-sn"] == ""
    d = [p["gd"] - p["gd-no-sn"] for p in prompts[:-1]]
    assert d == sorted(d) and len(prompts) == 4


def test_size_and_label_is_pearson_within_prompts():
    """The exploratory size check equals Pearson's r of the prompt-centred Gaussians and labels
    (scipy on the centred arrays), and reads about 1 where a label is built to follow the size."""
    from scipy import stats

    from gdbench.experiments.v3_report import size_and_label

    rng = np.random.default_rng(6)
    rows = _cells({"gd": -0.3, "gd-no-sn": 0.0}, 6, range(5), rng)
    for r in rows:
        r["gaussians"] = 1000.0 + 400 * int(r["prompt"][-1]) + rng.normal(0, 50)
        r["label_janus"] = float(rng.uniform()) if r["preset"] == "gd" else (r["gaussians"] % 400) / 400
    got = {x["preset"]: x for x in size_and_label(rows, ("gd", "gd-no-sn"))}
    sel = [r for r in rows if r["preset"] == "gd"]
    mean = lambda p, k: np.mean([r[k] for r in sel if r["prompt"] == p])  # noqa: E731
    centre = {p: (mean(p, "gaussians"), mean(p, "label_janus")) for p in {r["prompt"] for r in sel}}
    g = [r["gaussians"] - centre[r["prompt"]][0] for r in sel]
    y = [r["label_janus"] - centre[r["prompt"]][1] for r in sel]
    assert got["gd"]["cells"] == 30 and got["gd"]["r_within_prompt"] == pytest.approx(stats.pearsonr(g, y)[0])
    extra = [sel[0] | {"gaussians": float("nan")}, sel[0] | {"prompt": "alone", "label_janus": 1.0}]
    again = {x["preset"]: x for x in size_and_label(rows + extra, ("gd", "gd-no-sn"))}
    assert again["gd"] == got["gd"]  # a cell without a size, and a prompt of one cell, are left out
    assert got["gd-no-sn"]["r_within_prompt"] > 0.95  # the label follows the size there
