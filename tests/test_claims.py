"""The paper's claims as paired comparisons (gdbench/experiments/claims.py): the verdict words against
pairs built to give each, the statistics against independent oracles (enumerated sign flips,
scipy's tests, Holm by hand, a power simulation), the reading across prompts, the Holm family
and the arms' model sizes."""

import pytest


def _row(preset, prompt, seed, value, metric="multi_face_rate", setting="janus"):
    return {"setting": setting, "preset": preset, "prompt": prompt, "seed": seed, metric: value}


def test_claims_verdict_from_paired_tests():
    """Paired differences over (prompt, seed) decide: a signed-rank test significant after Holm
    holds (or, the other way, does not hold), a tie within the margin is a null result of its
    own, too few pairs or a metric that cannot fail (or always fails) gives no verdict."""
    import numpy as np

    from gdbench.experiments.claims import CLAIMS, evaluate
    from gdbench.experiments.stats import signed_rank_p

    keys = [(p, s) for p in "abcdef" for s in (0, 1, 2)]
    rng = np.random.default_rng(0)
    sn = rng.uniform(0.2, 0.4, len(keys))
    rows = [_row("gd-no-sn", p, s, v) for (p, s), v in zip(keys, sn)]
    rows += [_row("gd", p, s, v - 0.15) for (p, s), v in zip(keys, sn)]  # better in every pair
    rows += [_row("sjc-gs", p, s, v) for (p, s), v in zip(keys, sn)]
    rows += [_row("gd-no-vgs", p, s, v + rng.normal(0, 0.2)) for (p, s), v in zip(keys, sn)]  # noise only
    rows.append(_row("gd", "z", 0, 0.1))  # unpaired cells are left out
    got = {(v["a"], v["b"], v["metric"]): v for v in evaluate(rows)}
    v = got["gd", "gd-no-sn", "multi_face_rate"]
    assert v["verdict"] == "holds" and v["pairs"] == 18 and v["a_better_pairs"] == 18
    assert v["p_value"] < 1e-4 and v["p_holm"] == pytest.approx(2 * v["p_value"])  # the smaller of 2 tests
    assert v["mean_diff"] == pytest.approx(-0.15) and v["ci_low"] == pytest.approx(-0.15) == v["ci_high"]
    assert v["by_prompt"].startswith("a -0.15 (3); b -0.15 (3)")
    assert got["gd-no-vgs", "sjc-gs", "multi_face_rate"]["verdict"] == "undecided"
    assert got["gd", "gd-no-vgs", "floaters"]["verdict"] == "not measured"  # no floaters column
    # the Janus failure (the front everywhere or a second face) is read only where view prompting is off
    janus = [dict(r, janus_rate=r["multi_face_rate"]) for r in rows]
    assert not [v for v in evaluate([dict(r, setting="easy") for r in janus]) if v["metric"] == "janus_rate"]
    jv = [v for v in evaluate(janus) if v["metric"] == "janus_rate"]
    assert len(jv) == 1 and jv[0]["verdict"] == "holds" and jv[0]["pairs"] == 18 and jv[0]["left_out"] == ""
    # a prompt whose asset has no front gives no Janus pair, and the row says which and why
    burger = janus + [dict(_row(p, "a hamburger", s, 0.0), janus_rate=float("nan")) for p in ("gd", "gd-no-sn")
                      for s in range(3)]  # fmt: skip
    jb = next(v for v in evaluate(burger) if v["metric"] == "janus_rate")
    assert jb["pairs"] == 18 and jb["left_out"] == "janus_rate: a hamburger (the asset declares no front)"
    from gdbench.experiments.tables import markdown

    assert "Left out of the claims on janus_rate: a hamburger (the asset declares no front)." in markdown([], [jb])
    nm = got["gd", "gd-no-vgs", "floaters"] | {"left_out": "floaters: a, b, c (not measured)"}
    md = markdown([], [jb, nm])  # a claim no cell measured: one line, not a table row of n/a nor its prompts
    assert "| gd vs gd-no-vgs | floaters |" not in md and "Left out of the claims on floaters" not in md
    assert md.count("gd vs gd-no-vgs, floaters") == 1 and "Not measured (no cell has the metric in both arms)" in md
    flipped = [dict(r, multi_face_rate=-r["multi_face_rate"]) for r in rows]
    flipped_got = {(v["a"], v["b"], v["metric"]): v for v in evaluate(flipped)}
    assert flipped_got["gd", "gd-no-sn", "multi_face_rate"]["verdict"] == "does not hold"
    same = [dict(r, multi_face_rate=0.25) for r in rows]  # a tie in every pair: the presets do the same
    assert evaluate(same)[0]["verdict"] == "no effect beyond +-0.05"
    # a failure too rare for the claim: 3 baseline cells and 1 treated cell fail a little, the
    # rest are clean; an equivalence test would pass whatever the mechanism did
    fails = {("gd-no-sn", "a"), ("gd-no-sn", "b"), ("gd-no-sn", "c"), ("gd", "d")}
    rare = [
        dict(r, multi_face_rate=0.1 if (r["preset"], r["prompt"]) in fails and r["seed"] == 0 else 0.0) for r in rows
    ]
    assert evaluate(rare)[0]["verdict"] == "not testable here (baseline fails < 0.05)"  # not "no effect"
    # ... but a treated arm that fails beyond the margin is not hidden behind a rare baseline
    worse = [dict(r, multi_face_rate=0.4) if r["preset"] == "gd" and r["prompt"] in "abc" else r for r in rare]
    assert evaluate(worse)[0]["verdict"] in ("undecided", "does not hold")
    never_fails = [dict(r, multi_face_rate=0.0) for r in rows]  # nothing for the mechanism to fix
    assert evaluate(never_fails)[0]["verdict"] == "not testable here (neither preset fails)"
    always_fails = [dict(r, multi_face_rate=1.0) for r in rows]  # the metric cannot see a difference
    assert evaluate(always_fails)[0]["verdict"] == "not testable here (both always fail)"
    # skewed pairs as a table: 40 ties, 10 pairs where gd fails 0.5 more, 10 where 0.1 less: a
    # mean difference of 0.067, outside +-0.05, not significant; signed-rank TOST called it "no effect"
    gd_minus = [0.0] * 40 + [0.5] * 10 + [-0.1] * 10
    skew = [_row("gd-no-sn", f"q{i}", 0, 0.2) for i in range(60)]
    skew += [_row("gd", f"q{i}", 0, 0.2 + x) for i, x in enumerate(gd_minus)]
    dd = np.array(gd_minus)
    assert max(signed_rank_p(dd + 0.05, "greater"), signed_rank_p(dd - 0.05, "less")) < 0.01
    v = evaluate(skew)[0]
    assert v["mean_diff"] == pytest.approx(4 / 60) and v["p_value"] > 0.05 and v["verdict"] == "undecided"
    # a baseline whose mean is under the margin but not surely (one cell in six fails 0.2: mean
    # 0.033, 95% upper bound 0.06): a reduction beyond the margin was possible, so the test decides
    unsure = [
        _row(p, f"q{i}", 0, 0.2 if p == "gd-no-sn" and i % 6 == 0 else 0.0)
        for i in range(36)
        for p in ("gd", "gd-no-sn")
    ]
    assert evaluate(unsure)[0]["verdict"] == "holds"  # 6 of 36 pairs, all one way: exact p 2^-5
    # five pairs that agree among ties are not a result, whatever the family
    five = [
        _row(p, f"q{i}", 0, 0.1 if p == "gd-no-sn" and i < 5 else 0.3 * (i >= 5))
        for i in range(60)
        for p in ("gd", "gd-no-sn")
    ]
    assert evaluate(five)[0]["p_value"] == pytest.approx(1 / 16) and evaluate(five)[0]["verdict"] != "holds"
    few = [r for r in rows if r["prompt"] in "abcde" and r["seed"] == 0]
    assert evaluate(few)[0]["pairs"] == 5 and evaluate(few)[0]["verdict"] == "too few pairs (n < 6)"
    # ten pairs, three of them differ (by more than the margin): the test cannot reach 5%
    ties = [
        _row(p, f"q{i}", 0, 0.3 + (0.3 if p == "gd" and i < 3 else 0.0)) for i in range(10) for p in ("gd", "gd-no-sn")
    ]
    v = evaluate(ties)[0]
    assert v["nonzero_pairs"] == 3 and v["verdict"] == "too few non-tied pairs (k < 6)"
    metrics = {"multi_face_rate", "janus_rate", "judge_janus", "instance_inconsistency", "floaters",
               "colmap_failure_rate"}  # fmt: skip
    assert {c.metric for c in CLAIMS} == metrics  # Var(theta): a selection of registered views, no verdict


def test_the_statistics_against_independent_oracles():
    """BCa against the t interval, the signed-rank p against enumerating every sign flip, Holm
    by hand, the power formula against a simulation, and the equivalence test both ways."""
    import itertools

    import numpy as np
    from scipy import stats

    from gdbench.experiments.stats import bca_ci, equivalence_p, holm, pairs_for_power, signed_rank_p

    rng = np.random.default_rng(1)
    d = rng.normal(1.0, 2.0, 400)
    lo, hi = bca_ci(d)
    half = stats.t.ppf(0.975, d.size - 1) * d.std(ddof=1) / np.sqrt(d.size)
    assert lo == pytest.approx(d.mean() - half, abs=0.03) and hi == pytest.approx(d.mean() + half, abs=0.03)
    # the width is the 95% one: within 5% of 2 t s / sqrt(n) (measured 0.98-1.01 over five samples;
    # a 90% interval, the 5th and 95th percentiles, is 16% narrower)
    assert (hi - lo) / (2 * half) == pytest.approx(1.0, abs=0.05)
    # exact two-sided signed-rank p: the share of the 2^n sign patterns at least as extreme
    x = np.array([0.3, -0.1, 0.25, 0.7, -0.05, 0.4, 0.9, 0.15])
    ranks = stats.rankdata(np.abs(x))
    w = ranks[x > 0].sum()
    centre = ranks.sum() / 2
    flips = [sum(r for r, s in zip(ranks, signs) if s) for signs in itertools.product((0, 1), repeat=x.size)]
    exact = np.mean([abs(f - centre) >= abs(w - centre) - 1e-12 for f in flips])
    assert signed_rank_p(x) == pytest.approx(exact, rel=1e-9)
    assert holm([0.01, 0.04, 0.03, 0.005]) == pytest.approx([0.03, 0.06, 0.06, 0.02])
    assert np.isnan(holm([0.01, float("nan")])[1]) and holm([0.01, float("nan")])[0] == pytest.approx(0.01)
    # 80% power: the planned number of pairs rejects in about 80% of simulated experiments
    n = int(pairs_for_power(rng.normal(0.5, 1.0, 20_000)))
    assert 30 <= n <= 36
    hits = [stats.wilcoxon(rng.normal(0.5, 1.0, n)).pvalue < 0.05 for _ in range(1500)]
    assert np.mean(hits) == pytest.approx(0.8, abs=0.04)
    assert equivalence_p(rng.normal(0.0, 0.01, 30), 0.05) < 0.05  # within the margin: said so
    assert equivalence_p(rng.normal(0.1, 0.01, 30), 0.05) > 0.5  # an effect twice the margin: not
    # with zeros and ties the p is exact too (scipy's normal approximation gave five agreeing pairs
    # among 55 ties p = 0.043): every sign pattern of the mid-ranks, enumerated here by hand
    x = np.array([0.3, -0.1, 0.3, 0.7, -0.1, 0.4, 0.0, 0.3, 0.0])
    nz = x[x != 0]
    ranks = stats.rankdata(np.abs(nz))
    w = ranks[nz > 0].sum()
    flips = [sum(r for r, s in zip(ranks, signs) if s) for signs in itertools.product((0, 1), repeat=nz.size)]
    exact = np.mean([abs(f - ranks.sum() / 2) >= abs(w - ranks.sum() / 2) - 1e-12 for f in flips])
    assert signed_rank_p(x) == pytest.approx(exact, rel=1e-9)
    assert signed_rank_p(x, "greater") == pytest.approx(np.mean([f >= w - 1e-12 for f in flips]), rel=1e-9)
    assert signed_rank_p(np.r_[np.zeros(55), np.full(5, -0.1)]) == pytest.approx(2 / 2**5)
    assert signed_rank_p(np.array([0.3 - 0.2, 0.1, 0.1, -0.1, 0.2, 0.1])) == pytest.approx(
        signed_rank_p(np.array([0.1, 0.1, 0.1, -0.1, 0.2, 0.1]))
    )  # float noise neither breaks a tie nor makes a zero count: 0.3 - 0.2 ties 0.1
    assert signed_rank_p(np.r_[np.full(6, 1e-17), [0.1]]) == 1.0  # one real difference: p 1
    big = rng.normal(0.3, 1.0, 40)  # past the enumeration: scipy's
    assert signed_rank_p(big) == pytest.approx(stats.wilcoxon(big).pvalue, rel=1e-9)
    # TOST against scipy's one-sided one-sample t-tests of d + m > 0 and d - m < 0
    d = rng.normal(0.02, 0.1, 40)
    want = max(stats.ttest_1samp(d + 0.05, 0, alternative="greater").pvalue,
               stats.ttest_1samp(d - 0.05, 0, alternative="less").pvalue)  # fmt: skip
    assert equivalence_p(d, 0.05) == pytest.approx(want, rel=1e-9)
    # the mean decides, not the ranks: 50 ties and 10 pairs 0.43 apart have a mean difference of
    # 0.072, outside +-0.05 (two one-sided signed-rank tests passed this: both p < 0.01)
    skewed = np.r_[np.zeros(50), np.full(10, 0.43)]
    assert max(signed_rank_p(skewed + 0.05, "greater"), signed_rank_p(skewed - 0.05, "less")) < 0.01
    assert equivalence_p(skewed, 0.05) > 0.5


def test_claims_across_prompts_take_the_prompt_as_the_unit():
    """The reading across prompts: the per-prompt mean differences against scipy's one-sample t
    test, and an effect carried by seeds of a few prompts holds on these prompts (the pairs' test)
    but not across prompts, where an effect every prompt shares holds on both readings."""
    import numpy as np
    from scipy import stats

    from gdbench.experiments.claims import evaluate

    rng = np.random.default_rng(3)
    prompts = [f"p{i}" for i in range(6)]
    shift = {"p0": -0.5, "p1": -0.5, "p2": 0.0, "p3": 0.0, "p4": 0.0, "p5": 0.0}  # two prompts carry it
    rows = []
    for pr in prompts:
        for seed in range(10):
            b = rng.uniform(0.4, 0.6)
            rows += [_row("gd-no-sn", pr, seed, b), _row("gd", pr, seed, b + shift[pr] + rng.normal(0, 0.02))]
    v = evaluate(rows)[0]
    per = {}
    for r in rows:
        per.setdefault(r["prompt"], {}).setdefault(r["seed"], {})[r["preset"]] = r["multi_face_rate"]
    pm = np.array([np.mean([c["gd"] - c["gd-no-sn"] for c in per[p].values()]) for p in prompts])
    t = stats.ttest_1samp(pm, 0.0)
    assert v["prompts"] == 6 and v["prompt_mean_diff"] == pytest.approx(pm.mean())
    assert v["p_prompts"] == pytest.approx(t.pvalue, rel=1e-9)
    ci = t.confidence_interval(0.95)
    assert (v["prompt_ci_low"], v["prompt_ci_high"]) == pytest.approx((ci.low, ci.high), rel=1e-9)
    assert v["p_value"] < 1e-3 and v["verdict"] == "holds"  # on these prompts: 20 large pairs vs 40 small
    assert v["verdict_prompts"] == "undecided"  # across prompts: 2 of 6 move
    shared = [dict(r, multi_face_rate=r["multi_face_rate"] - 0.3 * (r["preset"] == "gd")) for r in rows]
    v = evaluate(shared)[0]  # every prompt moves by at least -0.2
    assert v["verdict"] == "holds" and v["verdict_prompts"] == "holds" and v["p_prompts_holm"] < 0.05
    two = [r for r in rows if r["prompt"] in ("p0", "p1")]
    assert evaluate(two)[0]["verdict_prompts"] == "too few prompts (G < 3)"
    # prompts that all moved alike (one pair each, d = 0.05: their std is float noise, not 0): the
    # exact sign-flip p over six prompts, 2 / 2^6
    alike = [_row(p, f"q{i}", 0, 0.1 if p == "gd" else 0.05) for i in range(6) for p in ("gd", "gd-no-sn")]
    v = evaluate(alike)[0]
    assert v["p_prompts"] == pytest.approx(2 / 2**6) and v["prompt_ci_low"] == pytest.approx(0.05)
    # five non-tied pairs among 60 (prompt means -0.01 x 5 and 0): the pairs' words across prompts
    # too, not a t test over almost equal prompt means (its p: 0.004)
    few = [_row(p, f"q{i}", s, 0.2 if p == "gd" and s == 0 and i < 5 else 0.3) for i in range(6) for s in range(10)
           for p in ("gd", "gd-no-sn")]  # fmt: skip
    v = evaluate(few)[0]
    assert v["nonzero_pairs"] == 5 and v["p_prompts"] < 0.01 and v["verdict_prompts"] == v["verdict"] != "holds"


def test_the_verdict_reports_each_arms_model_size_and_flags_a_2x_gap():
    """Mean final Gaussian count per arm over the pairs (unpaired cells left out), and a flag when
    the arms differ by more than 2x (the growth, not only the ablation, then differs)."""
    from gdbench.experiments.claims import CLAIMS, evaluate

    keys = [(p, s) for p in "abc" for s in (0, 1)]
    rows = [dict(_row("gd", p, s, 0.2), gaussians=7000 + 100 * s, gt_psnr=20.0 + s) for p, s in keys]
    rows += [dict(_row("gd-no-sn", p, s, 0.3), gaussians=6000, gt_psnr=21.0) for p, s in keys]
    rows += [dict(_row("sds-gs", p, s, 0.3), gaussians=1500) for p, s in keys]
    rows.append(dict(_row("gd", "z", 0, 0.1), gaussians=1, gt_psnr=99.0))  # unpaired: not in the means
    claims = [CLAIMS[0], type(CLAIMS[0])("size", "gd", "sds-gs", "multi_face_rate")]
    got = {(v["a"], v["b"]): v for v in evaluate(rows, claims)}
    v = got["gd", "gd-no-sn"]
    assert (v["gaussians_a"], v["gaussians_b"]) == (7050.0, 6000.0) and not v["size_confounded"]
    assert (v["gt_psnr_a"], v["gt_psnr_b"]) == (20.5, 21.0)  # GT PSNR beside the claim, over the pairs
    from gdbench.experiments.tables import markdown

    assert "| 7050 / 6000 | 20.5 / 21 |" in markdown([], [v])
    v = got["gd", "sds-gs"]
    assert v["size_ratio"] == pytest.approx(7050 / 1500) and v["size_confounded"]


def test_holm_family_holds_only_the_claims_a_test_decides():
    """A claim that cannot be tested (neither preset fails) adds no hypothesis: the one tested
    claim beside it keeps its raw p-value (Holm over a family of one)."""
    import numpy as np

    from gdbench.experiments.claims import evaluate

    keys = [(p, s) for p in "abcdef" for s in (0, 1)]
    rng = np.random.default_rng(1)
    base = rng.uniform(0.2, 0.4, len(keys))
    rows = []
    for (p, s), v in zip(keys, base):
        rows += [
            dict(_row("gd-no-sn", p, s, v), floaters=0.0),
            dict(_row("gd", p, s, v - 0.1), floaters=0.0),
            dict(_row("gd-no-vgs", p, s, v), floaters=0.0),
        ]
    got = {(v["a"], v["b"], v["metric"]): v for v in evaluate(rows)}
    tested = got["gd", "gd-no-sn", "multi_face_rate"]
    untested = got["gd", "gd-no-vgs", "floaters"]
    assert untested["verdict"] == "not testable here (neither preset fails)"
    assert untested["p_holm"] != untested["p_holm"]  # NaN: no hypothesis tested
    assert tested["p_holm"] == pytest.approx(tested["p_value"]) and tested["verdict"] == "holds"


def test_a_prompt_that_reverses_the_pooled_effect_is_named():
    """Five prompts where gd lowers the rate in every seed and one (the penguin) where it raises it
    in 9 of 10: the penguin is listed with its effect and count; 7 of 10 is not a reversal, and
    where the pooled reading decided, a prompt that goes with it never is."""
    import numpy as np

    from gdbench.experiments.claims import evaluate, reversals

    rows = []
    for p in ["a duck", "a corgi", "a sofa", "a lego figure", "a cat", "a penguin"]:
        for s in range(10):
            up = p == "a penguin" and s < 9
            rows += [_row("gd-no-sn", p, s, 0.5), _row("gd", p, s, 0.9 if up else 0.2)]
    v = next(v for v in evaluate(rows) if v["a"] == "gd" and v["b"] == "gd-no-sn")
    assert v["mean_diff"] < 0 and v["reversals"] == "a penguin +0.33 (9 of 10 pairs)"
    keys = [("x", s) for s in range(10)] + [("y", s) for s in range(10)]
    d = np.array([0.1] * 7 + [-0.1] * 3 + [-0.5] * 10)  # x: 7 of 10 against the pooled sign
    assert reversals(keys, d) == ""
    # a pooled reading that decided nothing hides one-way prompts of either sign
    d = np.array([0.1] * 9 + [-0.1] + [-0.2] * 8 + [0.3] * 2)
    assert reversals(keys, d) == "x +0.08 (9 of 10 pairs)"
    assert reversals(keys, d, decided=False) == "x +0.08 (9 of 10 pairs); y -0.1 (8 of 10 pairs)"
    from gdbench.experiments.tables import markdown

    assert "| a penguin +0.33 (9 of 10 pairs) |" in markdown([], [v])


def test_the_pose_locked_control_is_a_claim_of_its_own():
    """A janus sweep with gd and gd-pose-locked reads the 3D-correspondence claim (gd against the
    control) on the view classes and on the judge's labels, and only there: the same rows in the
    easy setting give no Janus claim."""
    from gdbench.experiments.claims import evaluate

    rows = []
    for p in "abcdef":
        for s in range(3):
            rows += [
                dict(_row("gd", p, s, 0.1), janus_rate=0.2, judge_janus=float(s == 0)),
                dict(_row("gd-pose-locked", p, s, 0.1), janus_rate=0.5, judge_janus=1.0),
            ]
    got = [v for v in evaluate(rows) if v["b"] == "gd-pose-locked"]
    assert [v["claim"] for v in got] == [
        "3D correspondence between views, not persistence alone, cuts Janus failures",
        "3D correspondence cuts the results the judge calls Janus",
    ]
    assert got[0]["mean_diff"] == pytest.approx(-0.3) and got[0]["verdict"] == "holds"
    assert got[1]["mean_diff"] == pytest.approx(-2 / 3) and got[1]["pairs"] == 18
    assert not [v for v in evaluate([dict(r, setting="easy") for r in rows]) if v["b"] == "gd-pose-locked"]
