"""The 068b215 experiment's report (docs/decisive.md; its definition: ``decisive.py``): the coupling
measurement, the merged tables of every block with one verdict table, the turntable grids, and the
README's verdict table of that time."""

from __future__ import annotations

import shutil
from pathlib import Path

from gdbench.experiments.runner import VIEWS_SPREAD_DEG


def coupling(results: Path, captions: list[str]) -> None:
    """coupling.csv (structured noise at one surface point, by separation and mixing ratio) and
    batch_coupling.csv (the same over the view pairs of one step: independent views or a spread)."""
    import itertools

    import torch

    from gdbench.core.camera import SphericalPoses
    from gdbench.core.io import write_csv
    from gdbench.core.provenance import code_commit
    from gdbench.priors.learned.evaluation import (
        noise_source,
        render_views,
        source_noise,
        surface_coupling,
        warped_corr,
    )

    commit = code_commit()
    rows = surface_coupling(captions, [0, 2, 5, 10, 15, 20, 30, 60, 90, 180], draws=6)
    write_csv([r | {"commit": commit} for r in rows], results / "coupling.csv")
    g = torch.Generator().manual_seed(1)
    batch = []
    for spread in (None, VIEWS_SPREAD_DEG):
        for caption in captions:
            for k in range(6):
                poses = SphericalPoses.sample(4, generator=g, spread_deg=spread)
                source = noise_source(g)
                for i, j in itertools.combinations(range(4), 2):
                    sel = torch.tensor([i, j])
                    _, z, cams = render_views(caption, poses.azimuth[sel], poses.elevation[sel], poses.fovy[sel],
                                              size=64, depth=True)  # fmt: skip
                    corr = warped_corr(source_noise(source, cams, g), z, cams)
                    batch.append({"spread_deg": spread or "independent", "caption": caption, "batch": k,
                                  "pair": f"{i}-{j}", "noise_corr": corr, "commit": commit})  # fmt: skip
    write_csv(batch, results / "batch_coupling.csv")


def report(out: Path, results: Path, collect, prompt: str, plain: list[tuple[Path, str]] = ()) -> None:
    """Merged tables of every block (and plain sweeps: ``plain``) in one verdict table, Holm across
    all its claims, and each block's turntable grid of ``prompt``; ``collect``: the experiment's
    reader of its cells (``decisive.collect``), passed in so that the report does not import its
    definition."""
    from gdbench.experiments.tables import tables
    from gdbench.experiments.turntables import turntable_grid

    rows = collect(out, plain)
    if not rows:
        raise SystemExit(f"report: no finished cell under {out / 'blocks'}")
    paths = tables(rows, results)
    paths["verdict_readme"] = readme_table(results / "verdict.csv", results / "verdict_readme.md")
    blocks = sorted(p.parent.name for p in (out / "blocks").glob("*/cells"))
    for b in blocks:
        grid = turntable_grid(out / "blocks" / b, prompt, seed=0)  # (group, setting) x preset
        if grid is not None:
            paths[f"turntables_{b}"] = Path(shutil.copy(grid, results / f"turntables_{b}.png"))
    # one figure: every block's (prior and views per step, setting) x preset for the first prompt
    grid = turntable_grid([out / "blocks" / b for b in blocks], prompt, seed=0, path=results / "turntables.png")
    if grid is not None:
        paths["turntables"] = grid
    print(f"report: {len(rows)} cells -> {', '.join(str(p) for p in paths.values())}")


def readme_table(verdict_csv: Path, path: Path) -> Path:
    """The README's verdict table: per claim, group (prior, views per step) and setting, the
    pooled effect with its BCa interval, the Holm-adjusted p, the equivalence p at the margin, the
    pairs and the verdict on these prompts; then the same across prompts (the prompt as the unit:
    ``claims.across_prompts``)."""
    import csv

    from gdbench.experiments.claims import label

    def f(x: str) -> str:
        return "n/a" if x in ("", None) else f"{float(x):.2g}"

    rows = list(csv.DictReader(open(verdict_csv)))
    md = ["| claim | group / setting | a vs b | metric | pairs | a - b [95% BCa] | p (Holm) | equivalence p (margin) "
          "| on these prompts | prompts: a - b [95% t] | p (Holm) | across prompts |",
          "|---|---|---|---|---|---|---|---|---|---|---|---|"]  # fmt: skip
    for v in rows:
        if v["verdict"] == "not measured":
            continue
        md.append(f"| {v['claim']} | {label(v)} | {v['a']} vs {v['b']} | {v['metric']} | {v['pairs']} | "
                  f"{f(v['mean_diff'])} [{f(v['ci_low'])}, {f(v['ci_high'])}] | {f(v['p_holm'])} | "
                  f"{f(v['p_equivalence'])} (+-{f(v['margin'])}) | **{v['verdict']}** | {v['prompts']}: "
                  f"{f(v['prompt_mean_diff'])} [{f(v['prompt_ci_low'])}, {f(v['prompt_ci_high'])}] | "
                  f"{f(v['p_prompts_holm'])} | **{v['verdict_prompts']}** |")  # fmt: skip
    path.write_text("\n".join(md) + "\n")
    return path
