"""The v3 experiment's definitions (docs/decisive_v3.md): its prompts, blocks, claims, effects of
interest, the pilot's design rules and the registered design, and the registration's commit.
``gdbench.experiments.v3`` runs the stages; ``v3_report`` reads the cells."""

from __future__ import annotations

import subprocess
from pathlib import Path

from gdbench.experiments.runner import Block

ARMS = ["gd", "gd-no-sn", "gd-redraw-step", "gd-pose-locked"]
"""The Janus arms: the method, without structured noise, and the two controls (docs/decisive.md,
section 5): persistence removed (redrawn every step), 3D correspondence removed (one 2D field per
camera pose)."""
STEPS = 1000
"""Steps per cell: the 068b215 sweep's, whose 2000-step check gave the same Janus effects."""
PILOT_SEEDS = [100, 101]
"""The pilot's seeds: none of the sweep's, so no sweep cell was seen before the registration."""

MAIN = ("label_janus",)
"""The primary claims' metric: the share of two blind raters who label a result Janus (the front
seen from every side, or a second face) from its turntable alone (docs/decisive_v3.md,
"Registered": the view classes failed their calibration on the pilot)."""
METRIC_MAIN = ("janus_failure_rate", "janus_rate")
"""The view classes' rates the pilot's rules were written for (the four-view rule reads them), in
the secondary family since the registration."""


def prompts() -> list[str]:
    """Every caption the learned prior's front-biased model was trained on (not held out) whose
    asset has a front, in the catalogue's order (``gdbench prompts``)."""
    from gdbench.assets.library import CAPTIONS, has_front
    from gdbench.priors.learned.prior import model_captions

    known, held_out = model_captions("front")
    return [c for c in CAPTIONS if c in set(known) - set(held_out) and has_front(c)]


def pilot_prompts() -> list[str]:
    """Every fourth prompt of ``prompts``, from the first: a quarter, chosen by position alone."""
    return prompts()[::4]


def pilot_blocks() -> list[Block]:
    """Every block the sweep could run, at the pilot's prompts."""
    ps = pilot_prompts()
    return [
        Block("janus-v1", ["learned-v1"], ["janus"], ARMS, steps=STEPS, prompts=ps),
        # the four-view rule reads gd and gd-no-sn; the controls' spread is taken from one view
        Block("janus-v4", ["learned-v4"], ["janus"], ["gd", "gd-no-sn"], steps=STEPS, prompts=ps),
        Block("instance", ["learned-v1"], ["instance"], ["gd", "gd-no-sn"], steps=STEPS, prompts=ps),
        # COLMAP registers none of the learned prior's results (docs/decisive.md, section 2)
        Block("colmap", ["empirical-v1"], ["easy"], ["gd", "gd-no-sn", "sjc-gs"], colmap=True, steps=STEPS, prompts=ps),
    ]


def claims() -> dict[str, tuple]:
    """The two families Holm adjusts over, each on its own: ``primary``, the three Janus
    comparisons (gd against gd-no-sn, gd-redraw-step and gd-pose-locked) on the raters' Janus
    label; ``secondary``, the same comparisons on the raters' failure label (not fine) and on the
    view classes' failure and Janus rates, instance inconsistency and the two COLMAP claims (where
    their blocks run)."""
    from gdbench.experiments.claims import CLAIMS, Claim

    pairs = (("gd", "gd-no-sn", "structured noise"), ("gd", "gd-redraw-step", "persistent noise, not its texture,"),
             ("gd", "gd-pose-locked", "3D correspondence between views, not persistence alone,"))  # fmt: skip

    def family(metric: str, what: str) -> tuple:
        return tuple(Claim(f"{why} reduces {what}", a, b, metric, 1.0) for a, b, why in pairs)

    keep = {("gd", "gd-no-sn", "janus_rate"), ("gd", "gd-redraw-step", "janus_rate"),
            ("gd", "gd-pose-locked", "janus_rate"), ("gd", "gd-no-sn", "instance_inconsistency"),
            ("gd", "sjc-gs", "colmap_failure_rate"), ("gd", "gd-no-sn", "colmap_failure_rate")}  # fmt: skip
    return {
        "primary": family("label_janus", "the results labelled Janus by eye"),
        "secondary": (
            *family("label_failure", "the results labelled not fine by eye"),
            *family("janus_failure_rate", "the views the classes call not fine"),
            *(c for c in CLAIMS if (c.a, c.b, c.metric) in keep),
        ),
    }


RATERS_MIN_KAPPA = 0.4
"""Registered: below this Cohen's kappa between the two raters on the Janus split (over the sweep's
labelled results), every primary verdict reads "undecided (the raters disagree)"."""


def raters_kappa(files: list, run_ids: set) -> dict:
    """Cohen's kappa between the first two label ``files`` on the Janus split (front_everywhere or
    second_face against the rest) and over the four classes, over the ``run_ids`` both label."""
    from gdbench.metrics.agreement import JANUS, cohen_kappa, read_labels

    if len(files) < 2:
        return {"results": 0, "kappa_janus": float("nan"), "kappa_classes": float("nan")}
    a, b = ({r["run_id"]: r["label"] for r in read_labels(f)} for f in files[:2])
    ids = sorted(set(a) & set(b) & set(run_ids))
    if not ids:
        return {"results": 0, "kappa_janus": float("nan"), "kappa_classes": float("nan")}
    ja, jb = ([str(x[i] in JANUS) for i in ids] for x in (a, b))
    return {"results": len(ids), "kappa_janus": cohen_kappa(ja, jb, labels=("True", "False")),
            "kappa_classes": cohen_kappa([a[i] for i in ids], [b[i] for i in ids])}  # fmt: skip


EFFECTS = {
    ("learned-v1", "gd", "gd-no-sn", "janus_rate"): 0.19,  # half of -0.38
    ("learned-v4", "gd", "gd-no-sn", "janus_rate"): 0.16,  # half of -0.32
    ("learned-v1", "gd", "gd-redraw-step", "janus_rate"): 0.13,  # half of -0.26
    ("learned-v1", "gd", "gd-no-sn", "instance_inconsistency"): 0.024,  # half of +0.047
    ("empirical-v1", "gd", "sjc-gs", "colmap_failure_rate"): 0.04,  # half of -0.081
}
"""The effect each claim is powered for: half the 068b215 sweep's pooled effect (docs/decisive.md,
section 4). Claims that sweep did not run take the nearest one's (``effect_for``)."""


def effect_for(group: str, a: str, b: str, metric: str) -> float:
    """``EFFECTS``' entry; for a claim 068b215 did not run: the pose-locked control and the v4
    controls take the redraw control's 0.13 (the persistence effect a control is compared with),
    gd against gd-no-sn under COLMAP the SJC comparison's 0.04."""
    if (group, a, b, metric) in EFFECTS:
        return EFFECTS[(group, a, b, metric)]
    if metric in ("janus_failure_rate", "label_janus", "label_failure"):  # the same sizes of interest
        return effect_for(group, a, b, "janus_rate")
    if metric == "janus_rate":
        return EFFECTS[("learned-v1", "gd", "gd-redraw-step", "janus_rate")]
    if metric == "colmap_failure_rate":
        return EFFECTS[("empirical-v1", "gd", "sjc-gs", "colmap_failure_rate")]
    return EFFECTS[("learned-v1", "gd", "gd-no-sn", "instance_inconsistency")]


DESIGN_RULES = {
    "margin": 0.05,
    "power": 0.8,
    "least_seeds": 2,
    "most_seeds": 5,
    "alpha": 0.05,
}
"""Fixed before the pilot ran (docs/decisive_v3.md, "The pilot's rules"): the four-view group is
swept when the pilot's four-view cells change the Janus rate of gd or gd-no-sn against the same
(prompt, seed) at one view by at least ``margin`` on average with a 95% t interval that excludes
0; the instance block when gd-no-sn's mean inconsistency exceeds ``margin``; the COLMAP block when
sjc-gs's mean failure rate exceeds ``margin`` and some cell registers; the seeds per prompt are the
fewest (at least ``least_seeds``, so that every prompt's interval exists; at most ``most_seeds``)
that give every main claim ``power`` at its ``effect_for`` with all ``prompts()``, at ``alpha``
over the family's size (Holm's first step); the four-view controls, which the pilot does not run,
take the one-view controls' spread."""

REGISTERED: dict | None = {"v4": False, "instance": True, "colmap": True, "seeds": 5}
"""The registered design (docs/decisive_v3.md, "Registered"; docs/results/v3/pilot/design.json):
set once, in the commit that adds the registration (``sweep`` refuses to run while it is None)."""


def sweep_blocks(reg: dict) -> list[Block]:
    """The sweep's blocks of a registered design, at every prompt."""
    ps = prompts()
    janus = ["learned-v1", "learned-v4"] if reg["v4"] else ["learned-v1"]
    blocks = [Block("janus", janus, ["janus"], ARMS, steps=STEPS, prompts=ps)]
    if reg["instance"]:
        blocks.append(Block("instance", ["learned-v1"], ["instance"], ["gd", "gd-no-sn"], steps=STEPS, prompts=ps))
    if reg["colmap"]:
        blocks.append(Block("colmap", ["empirical-v1"], ["easy"], ["gd", "gd-no-sn", "sjc-gs"], colmap=True,
                            steps=STEPS, prompts=ps))  # fmt: skip
    return blocks


def prereg_commit(root: Path | None = None) -> str | None:
    """The commit that added docs/decisive_v3.md's registration (its first commit carrying the
    line '## Registered'), or None where git cannot say."""
    root = root or Path(__file__).resolve().parents[2]
    try:
        out = subprocess.run(["git", "-C", str(root), "log", "--reverse", "--format=%h", "-S", "## Registered",
                              "--", "docs/decisive_v3.md"], capture_output=True, text=True, check=True)  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return None
    lines = out.stdout.split()
    return lines[0] if lines else None


def precedes(commit: str, later: str, root: Path | None = None) -> bool | None:
    """Whether ``commit`` is an ancestor of (or is) ``later``; None where git cannot say."""
    root = root or Path(__file__).resolve().parents[2]
    r = subprocess.run(["git", "-C", str(root), "merge-base", "--is-ancestor", commit, later.split("-dirty")[0]],
                       capture_output=True)  # fmt: skip
    return {0: True, 1: False}.get(r.returncode)
