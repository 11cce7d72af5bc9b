"""The v3 experiment's design (from its pilot) and report (from its sweep): docs/decisive_v3.md.

``design`` applies ``v3_design.DESIGN_RULES`` to the pilot's cells and writes design.json, power.csv and
design.md; ``report`` writes the verdict with the prompt as the unit first (exact sign-flip p,
Holm over ``v3_design.claims()``; t intervals), the pooled pairs second, a forest plot per main claim,
the share of gd's effect each control keeps, the prompts that go the other way, and checks that
the pre-registration's commit precedes every cell's.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from gdbench.core.io import num


def pairs(rows: list[dict], group: str, setting: str, a: str, b: str, metric: str) -> tuple[list[tuple], np.ndarray]:
    """The (prompt, seed) keys both presets ran in (group, setting) with ``metric`` finite in both,
    and the differences a - b (``claims.evaluate``'s pairing)."""
    from gdbench.experiments.claims import by_pair, paired, where

    sel = [r for r in rows if where(r) == (group, setting)]
    keys, va, vb = paired(by_pair(sel, a, metric), by_pair(sel, b, metric))
    return keys, va - vb


def across_groups(rows: list[dict], preset: str, metric: str, g1: str, g2: str, setting: str) -> dict:
    """``metric`` of ``preset`` in group ``g2`` minus in ``g1`` at the same (prompt, seed): mean and
    95% t interval (the four-view rule of ``v3_design.DESIGN_RULES``)."""
    from gdbench.experiments.across import t_interval
    from gdbench.experiments.claims import by_pair, paired

    def of(g: str) -> dict:
        return by_pair([r for r in rows if (r.get("group"), r.get("setting")) == (g, setting)], preset, metric)

    keys, v1, v2 = paired(of(g1), of(g2))
    m, lo, hi = t_interval(v2 - v1)
    return {"preset": preset, "pairs": len(keys), "mean": m, "low": lo, "high": hi}


def design(rows: list[dict], results: Path) -> dict:
    """The sweep's design from the pilot's cells by ``v3_design.DESIGN_RULES`` (module docstring)."""
    from gdbench.core.io import write_csv, write_json
    from gdbench.core.provenance import code_commit
    from gdbench.experiments.across import components, detectable, power, seeds_for_power
    from gdbench.experiments.v3_design import DESIGN_RULES, METRIC_MAIN, claims, effect_for, prompts

    if not rows:
        raise SystemExit("design: no finished pilot cell (run the pilot stage first)")
    rules = DESIGN_RULES
    m = rules["margin"]
    four = [across_groups(rows, p, metric, "learned-v1", "learned-v4", "janus") | {"metric": metric}
            for p in ("gd", "gd-no-sn") for metric in METRIC_MAIN]  # fmt: skip
    v4 = any(abs(f["mean"]) >= m and (f["low"] > 0 or f["high"] < 0) for f in four if f["pairs"] >= 2)

    def mean_of(group, setting, preset, metric):
        vals = [num(r.get(metric)) for r in rows if (r.get("group"), r.get("setting"), r["preset"]) ==
                (group, setting, preset)]  # fmt: skip
        vals = [v for v in vals if v == v]
        return float(np.mean(vals)) if vals else math.nan

    inst_base = mean_of("learned-v1", "instance", "gd-no-sn", "instance_inconsistency")
    colmap_base = mean_of("empirical-v1", "easy", "sjc-gs", "colmap_failure_rate")
    registers = any(num(r.get("registration_rate")) > 0 for r in rows if r.get("group") == "empirical-v1")
    instance, colmap = inst_base > m, colmap_base > m and registers
    where = [("learned-v1", "janus")] + [("learned-v4", "janus")] * v4
    where += [("learned-v1", "instance")] * instance + [("empirical-v1", "easy")] * colmap
    settings_of = {"instance_inconsistency": "instance", "colmap_failure_rate": "easy"}
    families = {name: [(g, s, c) for g, s in where for c in fam if settings_of.get(c.metric, "janus") == s]
                for name, fam in claims().items()}  # fmt: skip
    G = len(prompts())
    out = []
    for name, family in families.items():
        alpha = rules["alpha"] / len(family)
        for g, s, c in family:
            keys, d = pairs(rows, g, s, c.a, c.b, c.metric)
            if not keys and g == "learned-v4":  # the pilot ran only gd and gd-no-sn at four views
                keys, d = pairs(rows, "learned-v1", s, c.a, c.b, c.metric)
            if not keys and name == "primary":
                raise SystemExit(f"design: no pilot pair of {c.metric} for {c.a} vs {c.b} in {g} / {s}: the primary "
                                 "outcome needs the raters' labels (--labels)")  # fmt: skip
            comp = components(keys, d)
            eff = effect_for(g, c.a, c.b, c.metric)
            need = seeds_for_power(eff, comp["between"], comp["within"], G, alpha, rules["power"], rules["most_seeds"])
            row = {"family": name, "group": g, "setting": s, "a": c.a, "b": c.b, "metric": c.metric,
                   "main": name == "primary", "effect": eff, "pilot_pairs": comp["pairs"],
                   "pilot_prompts": comp["prompts"], "pilot_mean_diff": comp["mean"], "within_var": comp["within"],
                   "between_var": comp["between"], "prompts": G, "alpha": alpha,
                   "seeds_needed": need if need is not None else math.nan}  # fmt: skip
            for k in range(1, rules["most_seeds"] + 1):
                row[f"power_{k}_seeds"] = power(eff, comp["between"], comp["within"], G, k, alpha)
            out.append(row)
    alpha = rules["alpha"] / len(families["primary"])
    family = families["primary"]
    needs = [r["seeds_needed"] for r in out if r["main"]]
    short = [r for r in out if r["main"] and r["seeds_needed"] != r["seeds_needed"]]
    seeds = max([rules["least_seeds"], *[int(n) for n in needs if n == n]] + [rules["most_seeds"]] * bool(short))
    for r in out:  # what the chosen design can see: the effect it detects with the target power
        r["detectable_at_seeds"] = detectable(r["between_var"], r["within_var"], G, seeds, r["alpha"], rules["power"])
    cost = {}
    for r in rows:
        cost.setdefault((r.get("group"), r.get("setting")), []).append(num(r.get("cell_s")))
    cell_s = {f"{g} / {s}": float(np.nanmedian(v)) for (g, s), v in cost.items()}
    per_seed = sum(cell_s.get(f"{g} / {s}", math.nan) * len(ARMS_OF[s]) for g, s in where) * G
    result = {"v4": bool(v4), "instance": bool(instance), "colmap": bool(colmap), "seeds": int(seeds),
              "family": len(family), "alpha_first_step": alpha, "prompts": G, "four_view_change": four,
              "instance_baseline": inst_base, "colmap_baseline": colmap_base, "colmap_registers": registers,
              "underpowered": [f"{r['group']} {r['a']} vs {r['b']}" for r in short], "median_cell_s": cell_s,
              "cell_hours": per_seed * seeds / 3600, "wall_hours_two_workers": per_seed * seeds / 7200,
              "rules": rules, "pilot_cells": len(rows), "commit": code_commit(),
              "pilot_commits": sorted({str(r.get("train_commit")) for r in rows})}  # fmt: skip
    results.mkdir(parents=True, exist_ok=True)
    write_csv(out, results / "power.csv")
    write_json(result, results / "design.json")
    print(f"design: {result['seeds']} seeds x {G} prompts; four-view group {'in' if v4 else 'out'}, instance "
          f"{'in' if instance else 'out'}, COLMAP {'in' if colmap else 'out'}; family of {len(family)}; about "
          f"{result['wall_hours_two_workers']:.1f} h on two workers -> {results}")  # fmt: skip
    return result


ARMS_OF = {"janus": ("gd", "gd-no-sn", "gd-redraw-step", "gd-pose-locked"), "instance": ("gd", "gd-no-sn"),
           "easy": ("gd", "gd-no-sn", "sjc-gs")}  # fmt: skip
"""The presets each setting's block runs (``v3_design.pilot_blocks``, ``v3_design.sweep_blocks``)."""


def _f(x, digits: int = 2) -> str:
    return "n/a" if x is None or x != x else f"{x:+.{digits}f}" if isinstance(x, float) and x < 0 else f"{x:.{digits}g}"


def against(keys: list[tuple], d: np.ndarray, overall: float, margin: float) -> list[str]:
    """The prompts whose mean difference lies beyond ``margin`` on the side opposite to ``overall``
    (the across-prompts mean), e.g. 'a penguin +0.21 (3)'."""
    from gdbench.experiments.claims import per_prompt

    out = []
    for p, v in per_prompt(keys, d).items():
        m = float(np.mean(v))
        if overall == overall and abs(m) > margin and np.sign(m) == -np.sign(overall):
            out.append(f"{p} {m:+.2f} ({len(v)})")
    return out


def _janus(rows: list[dict], group: str | None) -> list[dict]:
    """The Janus setting's rows, of ``group`` alone where one is named."""
    return [r for r in rows if r.get("setting") == "janus" and (group is None or r.get("group") == group)]


def example_prompts(rows: list[dict], keys: list[tuple], d: np.ndarray, metric: str, group: str | None = None,
                    presets: tuple = ()) -> dict[str, str]:  # fmt: skip
    """The prompts the report shows turntables of, chosen by rule from the first primary claim's
    per-prompt means ``d`` over ``keys`` (means rounded to 1e-9, so that float noise cannot break a
    tie): the largest effect (the most negative mean), a ceiling (a prompt of the claim whose cells
    of ``group``'s Janus setting are all 1 on ``metric``, every one of ``presets`` among them) and
    the largest reversal (the most positive mean above 0). Ties go to the alphabetically first
    prompt; a kind with no prompt is left out."""
    from gdbench.experiments.claims import per_prompt

    means = sorted((round(float(np.mean(v)), 9), p) for p, v in per_prompt(keys, d).items())
    out = {"the largest effect": means[0][1]} if means and means[0][0] < 0 else {}
    cells: dict[str, list[tuple[str, float]]] = {}
    for r in _janus(rows, group):
        cells.setdefault(r["prompt"], []).append((r["preset"], num(r.get(metric))))
    ceiling = sorted(p for _, p in means if p in cells and all(x == 1 for _, x in cells[p])
                     and set(presets) <= {a for a, _ in cells[p]})  # fmt: skip
    if ceiling:
        out["Janus in every arm"] = ceiling[0]
    if means and means[-1][0] > 0:
        out["the largest reversal"] = min(p for m, p in means if m == means[-1][0])
    return out


def example_turntables(blocks: Path, chosen: dict[str, str], seed: int, path: Path, group: str | None = None):
    """Seed ``seed``'s turntables of the ``chosen`` prompts (kind -> prompt), every Janus arm of
    ``group`` a row, one figure per prompt stacked into ``path`` (the figures in between removed);
    None when no cell kept its turntable."""
    from PIL import Image

    from gdbench.experiments.turntables import turntable_grid

    parts = []
    for kind, prompt in chosen.items():
        one = path.with_name(f"{path.stem}_{kind.replace(' ', '_')}.png")
        try:
            if turntable_grid(blocks, prompt, seed=seed, group=group, path=one) is not None:
                parts.append(Image.open(one).convert("RGB"))
        finally:
            one.unlink(missing_ok=True)
    if not parts:
        return None
    sheet = Image.new("RGB", (max(im.width for im in parts), sum(im.height for im in parts)), "white")
    y = 0
    for im in parts:
        sheet.paste(im, (0, y))
        y += im.height
    sheet.save(path, quality=90)  # WebP or JPEG by the suffix: a photo-like sheet, a tenth of its PNG
    return path


def what_raters_saw(rows: list[dict], files: list, presets: tuple, group: str | None = None):
    """What a person would see, per Janus arm of ``group``: each rater's count of the four labels
    over the arm's results (a row per rater and preset), and each prompt's mean ``label_janus`` in
    every arm (a row per prompt with a labelled cell, sorted by ``presets[0]`` minus
    ``presets[1]``, prompts missing either last; '' where an arm has no labelled cell)."""
    from gdbench.metrics.agreement import LABELS, read_labels

    if len(presets) < 2:
        raise ValueError(f"presets: expected at least two arms to compare, got {presets}")
    janus = _janus(rows, group)
    preset_of = {r.get("run_id"): r["preset"] for r in janus}
    counts = []
    for i, f in enumerate(files, start=1):
        got = [(preset_of[r["run_id"]], r["label"]) for r in read_labels(f) if r["run_id"] in preset_of]
        for preset in presets:
            counts.append({"rater": i, "preset": preset, "results": sum(p == preset for p, _ in got)}
                          | {lab: sum(x == (preset, lab) for x in got) for lab in LABELS})  # fmt: skip
    per: dict[tuple, list[float]] = {}
    for r in janus:
        if num(r.get("label_janus")) == num(r.get("label_janus")):
            per.setdefault((r["prompt"], r["preset"]), []).append(num(r["label_janus"]))
    prompts = []
    for prompt in sorted({p for p, _ in per}):
        prompts.append({"prompt": prompt} | {a: float(np.mean(per[prompt, a])) if (prompt, a) in per else ""
                                             for a in presets})  # fmt: skip
    a, b = presets[0], presets[1]
    prompts.sort(key=lambda r: (r[a] - r[b]) if "" not in (r[a], r[b]) else math.inf)
    return counts, prompts


def size_and_label(rows: list[dict], presets: tuple, metric: str = "label_janus", group: str | None = None):
    """An exploratory look (not registered): per Janus arm of ``group``, Pearson's r between a
    cell's Gaussians and its ``metric`` within prompts (both centred on their prompt's mean over the
    arm's seeds), i.e. whether the larger of two results of one prompt and arm is labelled
    differently. Cells missing either value, and prompts left with one cell (nothing to compare
    within), are left out; NaN where fewer than two degrees of freedom remain or either is constant."""
    out = []
    for preset in presets:
        by: dict[str, list[tuple[float, float]]] = {}
        for r in _janus(rows, group):
            g, y = num(r.get("gaussians")), num(r.get(metric))
            if r["preset"] == preset and g == g and y == y:
                by.setdefault(r["prompt"], []).append((g, y))
        by = {p: np.array(v) for p, v in by.items() if len(v) > 1}
        r_ = math.nan
        if sum(len(v) - 1 for v in by.values()) >= 2:
            g, y = (np.concatenate([v[:, k] - v[:, k].mean() for v in by.values()]) for k in (0, 1))
            if g.std() > 0 and y.std() > 0:
                r_ = float(np.corrcoef(g, y)[0, 1])
        out.append({"preset": preset, "cells": sum(len(v) for v in by.values()), "r_within_prompt": r_})
    return out


def _md(rows: list[dict], head: tuple = ()) -> list[str]:
    """A markdown table of ``rows`` (``head``, or their first row's keys, as the head; floats to 2
    decimals); nothing without a head."""
    head = list(head or (rows[0] if rows else ()))
    if not head:
        return []
    cell = lambda x: f"{x:.2f}" if isinstance(x, float) else str(x).replace("|", "\\|")  # noqa: E731
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head),
            *["| " + " | ".join(cell(r[k]) for k in head) + " |" for r in rows]]  # fmt: skip


def _raters_rule(verdicts: list[dict], raters: dict, path: Path) -> None:
    """The registered rule: an outcome people do not agree on decides nothing (the primary verdicts
    become undecided when the raters' kappa is below ``RATERS_MIN_KAPPA``; rewritten in ``path``)."""
    from gdbench.core.io import write_csv
    from gdbench.experiments.v3_design import RATERS_MIN_KAPPA

    if raters["kappa_janus"] == raters["kappa_janus"] and raters["kappa_janus"] < RATERS_MIN_KAPPA:
        for v in verdicts:
            if v.get("family") == "primary" and v["verdict"] != "not measured":
                v["verdict"] = v["verdict_prompts"] = "undecided (the raters disagree)"
        write_csv(verdicts, path)


def _forests(rows: list[dict], verdicts: list[dict], commits: list[str], forest_dir: Path) -> list[Path]:
    """Each measured verdict's prompts on the other side (``against``, set in its row), and a forest
    plot per claim on a main metric."""
    from gdbench.core.provenance import code_commit
    from gdbench.experiments.across import forest
    from gdbench.experiments.claims import label
    from gdbench.experiments.v3_design import MAIN, METRIC_MAIN

    forests = []
    for v in verdicts:
        if v["verdict"] == "not measured":
            continue
        keys, d = pairs(rows, v["group"], v["setting"], v["a"], v["b"], v["metric"])
        pooled = {k: float(v[k]) if v[k] not in ("", None) else math.nan
                  for k in ("prompt_mean_diff", "prompt_ci_low", "prompt_ci_high")}  # fmt: skip
        v["against"] = "; ".join(against(keys, d, pooled["prompt_mean_diff"], float(v["margin"]))) or "none"
        if v["metric"] not in MAIN + METRIC_MAIN:
            continue
        name = f"forest_{v['group']}_{v['metric']}_{v['a']}_vs_{v['b']}.png".replace(" ", "_")
        title = (f"{label(v)}: {v['metric']}, {v['a']} - {v['b']}; across prompts: {v.get('verdict_prompts', '')}\n"
                 f"cells trained at {', '.join(c[:7] for c in commits)}, tables at {code_commit()[:7]}")  # fmt: skip
        forests.append(forest(keys, d, title=title, margin=float(v["margin"]), path=forest_dir / name, pooled=pooled))
    return forests


def _control_shares(rows: list[dict], verdicts: list[dict]) -> tuple[list[dict], list[str]]:
    """The share of gd's effect each control keeps, per Janus group and main metric: rows and lines."""
    import itertools

    from gdbench.experiments.across import share_kept
    from gdbench.experiments.v3_design import MAIN, METRIC_MAIN

    shares, lines = [], []
    for group in sorted({v["group"] for v in verdicts if v["setting"] == "janus"}):
        sel = _janus(rows, group)
        for control, metric in itertools.product(("gd-redraw-step", "gd-pose-locked"), MAIN + METRIC_MAIN):
            s = share_kept(sel, control, metric)
            shares.append({"group": group, "control": control, "metric": metric} | s)
            interval = (f"[{_f(s['low'])}, {_f(s['high'])}]" if not s["flipped"] else
                        f"[unbounded: {s['flipped']} of 10,000 resamples give gd's effect the other sign]")  # fmt: skip
            lines.append(f"- {group}: {control} gives {_f(s['share'])} of gd's effect on {metric} "
                         f"{interval} ({s['prompts']} prompts; gd's effect "
                         f"{_f(s.get('effect', math.nan))}, the control's {_f(s.get('kept', math.nan))}).")  # fmt: skip
    return shares, lines


def _report_md(
    n: int,
    head: dict,
    raters: dict,
    table: str,
    lines: list[str],
    seen: dict,
    verdicts: list[dict],
    forests: list[Path],
    turntables: dict,
) -> str:
    """report.md: the provenance (``head``), the raters, the verdict table, the controls, what the
    raters saw (``seen``: counts, by_prompt, sizes, arms), the prompts against, the figures."""
    from gdbench.experiments.claims import label
    from gdbench.experiments.v3_design import RATERS_MIN_KAPPA

    reg, commits, before, hours, tables_at = head["reg"], head["commits"], head["before"], head["hours"], head["at"]
    counts, by_prompt, sizes, arms = seen["counts"], seen["by_prompt"], seen["sizes"], seen["arms"]
    chosen, seed, tt = turntables["chosen"], turntables["seed"], turntables["path"]
    md = [f"# v3: the verdict ({n} cells)", "",
          f"Pre-registration: {reg or 'not found'}; cells trained at {', '.join(commits)}; "
          f"the registration precedes every cell: {all(before.values()) if reg else 'n/a'}; tables "
          f"at {tables_at}; {hours:.1f} hours of cell time.", "",
          f"Raters: Cohen's kappa {_f(raters['kappa_janus'])} on the Janus split, {_f(raters['kappa_classes'])} over "
          f"the four classes, on {raters['results']} results (the primary verdicts are read at "
          f"{RATERS_MIN_KAPPA} or more).", "",
          "## Across prompts first, then the pooled pairs", "", table, "",
          "## The controls: the share of gd's effect each keeps", "", *lines, "",
          *(["## What the raters saw, per arm (counts of results)", "", *_md(counts), ""] if counts else []),
          *([f"## The share labelled Janus, per prompt and arm (sorted by {arms[0]} - {arms[1]})", "",
             *_md(by_prompt), ""] if by_prompt else []),
          *(["## Exploratory, not registered: does a result's size track its label?", "",
             "Pearson's r between a cell's Gaussians and its label_janus within prompts (each centred on "
             "its prompt's mean in the arm): near 0, the larger results of a prompt and arm are not the "
             "ones labelled differently.", "", *_md(sizes), ""] if sizes else []),
          "## Prompts beyond the margin on the other side", "",
          *[f"- {label(v)}, {v['a']} vs {v['b']}, {v['metric']}: {v['against']}" for v in verdicts if "against" in v],
          "", "Forest plots: " + ", ".join(f"[{p.name}](figures/{p.name})" for p in forests), "",
          *([f"Turntables at seed {seed} ([turntables.webp](turntables.webp)), chosen by rule from the first "
             f"primary claim's prompts: " + "; ".join(f"{k}: {p}" for k, p in chosen.items()) + ".", ""]
            if tt else [])]  # fmt: skip
    return "\n".join(md)


def _copy_figures(forests: list[Path], turntables: Path | None, group: str | None, figures: Path) -> list[Path]:
    """The primary claims' forest plots and the turntables, copied as the README's v3_* figures."""
    import shutil

    from gdbench.experiments.v3_design import MAIN

    figures.mkdir(parents=True, exist_ok=True)
    primary = [f for f in forests if any(f"_{m}_" in f.name for m in MAIN)]
    copies = []
    for f in [*primary, *([turntables] if turntables else [])]:
        name = "v3_" + f.name.replace(f"forest_{group}_", "forest_") if f in primary else f"v3_{f.name}"
        copies.append(Path(shutil.copyfile(f, figures / name)))
    return copies


def report(rows: list[dict], out: Path, results: Path, labels: list | None = None, figures: Path | None = None) -> dict:
    """Tables, forest plots, the controls' shares and report.md (module docstring); ``labels``: the
    raters' files, whose agreement decides whether the primary verdicts can be read
    (``v3_design.RATERS_MIN_KAPPA``); ``figures``: a folder that also gets copies of the primary
    claims' forest plots (``v3_forest_<metric>_<a>_vs_<b>.png``) and the turntables
    (``v3_turntables.webp``), the README's figures."""
    import csv

    from gdbench.core.io import write_csv, write_json
    from gdbench.core.provenance import code_commit
    from gdbench.experiments.tables import tables
    from gdbench.experiments.v3_design import claims, precedes, prereg_commit, raters_kappa

    if not rows:
        raise SystemExit(f"report: no finished cell under {out / 'blocks'}")
    paths = tables(rows, results, figures=True, claims=claims(), prompt_test="signflip")
    verdicts = list(csv.DictReader(open(paths["verdict_csv"])))
    raters = raters_kappa(list(labels or []), {r.get("run_id") for r in rows if r.get("setting") == "janus"})
    _raters_rule(verdicts, raters, paths["verdict_csv"])
    reg = prereg_commit()
    commits = sorted({str(r.get("train_commit")) for r in rows})
    before = {c: (precedes(reg, c) if reg else None) for c in commits}
    forests = _forests(rows, verdicts, commits, results / "figures")
    shares, lines = _control_shares(rows, verdicts)
    write_csv(shares, results / "shares.csv")
    first = next((v for v in verdicts if v.get("family") == "primary" and v["verdict"] != "not measured"), None)
    group = first["group"] if first is not None else None  # the primary claims' group: its Janus arms
    arms = tuple(p for p in ("gd", "gd-no-sn", "gd-redraw-step", "gd-pose-locked")
                 if any(r["preset"] == p for r in _janus(rows, group)))  # fmt: skip
    counts, by_prompt, sizes = [], [], []
    if len(arms) >= 2:
        counts, by_prompt = what_raters_saw(rows, list(labels or []), arms, group)
        sizes = size_and_label(rows, arms, group=group) if by_prompt else []
    for table, name in ((counts, "labels_by_arm.csv"), (by_prompt, "label_janus_by_prompt.csv")):
        if table:
            write_csv(table, results / name)
    chosen, turntables, seed = {}, None, None
    if first is not None:
        keys, d = pairs(rows, first["group"], first["setting"], first["a"], first["b"], first["metric"])
        chosen = example_prompts(rows, keys, d, first["metric"], group, arms)
        seed = min(int(num(r["seed"])) for r in _janus(rows, group))
        turntables = example_turntables(out / "blocks" / "janus", chosen, seed, results / "turntables.webp", group)
    table = readme_table(verdicts)
    (results / "verdict_readme.md").write_text(table)
    hours = sum(num(r.get("cell_s")) for r in rows if num(r.get("cell_s")) == num(r.get("cell_s"))) / 3600
    head = {"reg": reg, "commits": commits, "before": before, "hours": hours, "at": code_commit()}
    seen = {"counts": counts, "by_prompt": by_prompt, "sizes": sizes, "arms": arms}
    md = _report_md(len(rows), head, raters, table, lines, seen, verdicts, forests,
                    {"chosen": chosen, "seed": seed, "path": turntables})  # fmt: skip
    (results / "report.md").write_text(md)
    copies = _copy_figures(forests, turntables, group, figures) if figures is not None else []
    prov = {"raters": raters, "prereg_commit": reg, "train_commits": commits, "prereg_precedes": before,
            "cells": len(rows), "cell_hours": hours, "tables_commit": code_commit()}  # fmt: skip
    write_json(prov, results / "provenance.json")
    print(f"report: {len(rows)} cells -> {results / 'report.md'}")
    return {"verdicts": verdicts, "shares": shares, "forests": forests, "examples": chosen, "turntables": turntables,
            "copies": copies}  # fmt: skip


def readme_table(verdicts: list[dict]) -> str:
    """The README's verdict table: across prompts first (G, the mean of the per-prompt means with its
    t interval, the sign-flip p Holm-adjusted, the verdict), the pooled pairs second (BCa interval,
    signed-rank p Holm-adjusted, verdict), GT PSNR and Gaussians of both arms beside."""
    from gdbench.experiments.claims import label

    def g(v, k, digits=2):
        x = v.get(k)
        return "n/a" if x in ("", None) or float(x) != float(x) else f"{float(x):.{digits}g}"

    head = ("family", "group / setting", "claim (a vs b), metric", "prompts", "across prompts: a - b [95% t]",
            "sign-flip p (Holm)", "**across prompts**", "pairs", "pooled: a - b [95% BCa]", "p (Holm)",
            "on these prompts", "GT PSNR a / b", "Gaussians a / b")  # fmt: skip
    rows = []
    for v in verdicts:
        if v["verdict"] == "not measured":
            continue
        cells = (
            v.get("family", ""),
            label(v),
            f"{v['a']} vs {v['b']}, {v['metric']}",
            v["prompts"],
            f"{g(v, 'prompt_mean_diff')} [{g(v, 'prompt_ci_low')}, {g(v, 'prompt_ci_high')}]",
            g(v, "p_prompts_holm"),
            f"**{v['verdict_prompts']}**",
            v["pairs"],
            f"{g(v, 'mean_diff')} [{g(v, 'ci_low')}, {g(v, 'ci_high')}]",
            g(v, "p_holm"),
            v["verdict"],
            f"{g(v, 'gt_psnr_a', 3)} / {g(v, 'gt_psnr_b', 3)}",
            f"{g(v, 'gaussians_a', 4)} / {g(v, 'gaussians_b', 4)}",
        )
        rows.append(dict(zip(head, cells)))
    return "\n".join(_md(rows, head)) + "\n"
