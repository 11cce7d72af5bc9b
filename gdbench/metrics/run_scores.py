"""``gdbench score RUN``: all scores of a run folder, written to its ``scores.json``.

- ground truth (empirical-prior runs): PSNR/SSIM against the procedural asset at 12 held-out
  poses after the best azimuth alignment (``gt.py``);
- COLMAP consistency (``colmap_consistency.py``): registration rate, Var(theta) of adjacent
  relative-rotation angles (the headline), translation-direction error.

Every block records how it was made (``made``: its parameters, the commit, the UTC time, its
seconds; ``gdbench.core.provenance``). A block of an earlier ``scores.json`` is reused only when the
scene (its SHA-256), the block's parameters and the code all match (``provenance.same_code``:
the same commit, and for a tree with edits the same edits); the report marks it "reused".
Blocks that do not match are recomputed when asked for and dropped otherwise, so nothing made
by other code or on another scene is ever shown as current. A broken ``run.json`` or
``scores.json`` is reported (naming the file) before any scoring starts.
"""

from __future__ import annotations

import time
from pathlib import Path

import torch

from gdbench.core.io import jsonable, num, read_json, sha256_file, write_json
from gdbench.core.scene import GaussianScene

BLOCKS = ("gt", "views", "judge", "colmap")
"""The blocks of scores.json; ``gt`` and ``views`` are made together (the view metrics pick the
variant the GT PSNR is measured against); ``judge`` (the Janus judge's label, ``metrics/judge``)
with them, its version in its parameters, so that another judge judges again."""


def run_settings(config: dict) -> dict:
    """The settings of a run.json's config that scoring reads (background, variants), from either
    of its layouts: the prior's settings inside its mapping or beside the other fields."""
    prior = config.get("prior")
    return dict(config) | ({k: v for k, v in prior.items() if k != "kind"} if isinstance(prior, dict) else {})


def previous_scores(run: Path, scene_sha: str) -> dict:
    """The blocks of ``run/scores.json`` still valid for the scene with hash ``scene_sha``: made
    on that scene by this code (``provenance.same_code``); others are stale and left out."""
    from gdbench.core.provenance import same_code

    path = run / "scores.json"
    if not path.is_file():
        return {}
    old = read_json(path, what="scores.json")
    if old.get("scene_sha256") != scene_sha:
        return {}  # measured on another scene (or before scores were tied to scenes): stale
    return {k: old[k] for k in BLOCKS if same_code(_made(old.get(k)).get("commit"))}


def _made(block) -> dict:
    """A block's provenance, {} for a block that has none (or is not a block)."""
    made = block.get("made") if isinstance(block, dict) else None
    return made if isinstance(made, dict) else {}


def _reusable(previous: dict, name: str, params: dict) -> bool:
    return name in previous and _made(previous[name]).get("params") == jsonable(params)


def score_run(
    run: str | Path,
    *,
    gt: bool = True,
    colmap: bool = True,
    views: int = 100,
    size: int = 256,
    progress: bool = False,
    device: str = "cpu",
    judge: bool | None = None,
) -> dict:
    """Scores of a finished run folder into its scores.json; ``gt`` asks for the ground-truth
    blocks (PSNR/SSIM, and the view metrics: multi-face rate, instance consistency, floaters),
    ``judge`` for the Janus judge's block (default: with ``gt``), ``colmap`` for the COLMAP block
    (``views`` renders of ``size`` px). Returns the file's
    content plus ``reused``: the asked-for blocks taken from an earlier call (same scene,
    parameters and commit), and ``kept``: blocks not asked for that the file still holds.
    COLMAP's own output goes to the run folder's colmap.log; ``progress`` reports each stage.
    ``device``: where the scene is rendered ('cpu', 'cuda' or 'auto'); the images are compared on
    the CPU, and a score does not depend on the device beyond float rounding."""
    from gdbench.core.devices import resolve_device
    from gdbench.core.io import FolderLock

    dev = resolve_device(device, "device (--device)")
    run = Path(run)
    if not run.is_dir():
        raise FileNotFoundError(f"run: no run folder at {run}")
    with FolderLock(run, what="run"):  # one writer: not while a generate (--overwrite) writes here
        return _score_run(run, gt=gt, colmap=colmap, views=views, size=size, progress=progress, device=dev,
                          judge=gt if judge is None else judge)  # fmt: skip


def one_run(run: Path) -> tuple[dict, str]:
    """(run.json's content, scene.ply's SHA-256), checked to belong to one run: the PLY header's
    ``gdbench run <id>`` and the scene's hash must be those run.json records (a folder whose
    files come from two runs is refused, naming both)."""
    from gdbench.core.ply import header_comments

    ply = run / "scene.ply"
    if not ply.is_file():
        raise FileNotFoundError(f"run: no scene.ply in {run} (is the run finished?)")
    info = read_json(run / "run.json", what="run.json") if (run / "run.json").is_file() else {}
    _check_run_json(info, run / "run.json")
    scene_sha = sha256_file(ply)
    ids = [c.split()[2] for c in header_comments(ply) if c.startswith("gdbench run ") and len(c.split()) == 3]
    rid = info.get("run_id")
    if rid is not None and ids and ids[0] != rid:
        raise ValueError(
            f"run: {ply} is from run {ids[0]} but {run / 'run.json'} describes run {rid}; the folder mixes two "
            "runs: run `gdbench generate` again with --overwrite, or score the PLY's own folder"
        )
    want = info.get("scene_sha256")
    if want is not None and want != scene_sha:
        raise ValueError(
            f"run: {ply} is not the scene {run / 'run.json'} records (SHA-256 {scene_sha[:12]}... against "
            f"{str(want)[:12]}...); it was changed after the run: run `gdbench generate` again with --overwrite"
        )
    return info, scene_sha


def _check_run_json(info: dict, path: Path) -> None:
    """The fields of run.json that scoring reads, by type: a hand-edited or foreign file is named,
    not met by an AttributeError halfway."""
    want = {"run_id": str, "scene_sha256": str, "caption": str, "config": dict}
    for key, kind in want.items():
        if info.get(key) is not None and not isinstance(info[key], kind):
            raise ValueError(
                f"run.json: {path}: '{key}' should be a {kind.__name__}, got {info[key]!r}; fix or delete it"
            )
    config = run_settings(info.get("config") or {})
    bg = config.get("background", (1.0, 1.0, 1.0))
    ok_bg = isinstance(bg, (list, tuple)) and len(bg) == 3 and all(isinstance(c, (int, float)) for c in bg)
    variants = config.get("variants", 1)
    if not ok_bg or not isinstance(variants, int) or isinstance(variants, bool) or variants < 1:
        raise ValueError(
            f"run.json: {path}: config.background should be 3 numbers and config.variants an int >= 1, got "
            f"{bg!r} and {variants!r}; fix or delete it"
        )


def _score_run(
    run: Path,
    *,
    gt: bool,
    colmap: bool,
    views: int,
    size: int,
    progress: bool = False,
    device: torch.device,
    judge: bool = True,
) -> dict:
    from gdbench.core.progress import Phases

    ply = run / "scene.ply"
    info, scene_sha = one_run(run)
    previous = previous_scores(run, scene_sha)  # a broken scores.json fails here, before the work
    scene = GaussianScene.load_ply(ply).to(device)
    out: dict = {
        "run": str(run),
        "run_id": info.get("run_id"),
        "scene_sha256": scene_sha,
        "gaussians": len(scene),
        "caption": info.get("caption"),
    }
    t_call = time.perf_counter()
    config = info.get("config", {})
    bg = tuple(float(c) for c in config.get("background", (1.0, 1.0, 1.0)))  # the run's own background
    blocks: dict = {}
    reused: list[str] = []
    want_gt = bool(gt and info.get("caption"))
    stages = int(want_gt) + int(judge and bool(info.get("caption"))) + 4 * int(colmap)
    with Phases(stages, "score", disable=not progress) as phases:
        _blocks(scene, info, previous, blocks, reused, want_gt, colmap, views, size, bg, run, phases)
        if judge:
            _judge(scene, info.get("caption"), previous, blocks, reused, phases)
    kept = {k: v for k, v in previous.items() if k not in blocks}
    out |= kept | blocks
    out["seconds"] = time.perf_counter() - t_call  # this call's, reuse included
    write_json(out, run / "scores.json")
    return out | {"reused": reused, "kept": sorted(kept)}


def _blocks(scene, info, previous, blocks, reused, want_gt, colmap, views, size, bg, run, phases) -> None:
    """The asked-for score blocks into ``blocks``: reused from ``previous`` where they match."""
    from gdbench.core.provenance import made

    config = run_settings(info.get("config", {}))
    if want_gt:
        variants = int(config.get("variants", 1))
        params = {"caption": info["caption"], "variants": variants, "background": list(bg)}
        if _reusable(previous, "gt", params) and _reusable(previous, "views", params):
            blocks |= {"gt": previous["gt"], "views": previous["views"]}
            reused += ["gt", "views"]
            phases.total -= 1  # nothing to report there
        else:
            from gdbench.metrics.gt import score_against_asset, turned_deg
            from gdbench.metrics.views import score_scene as view_scores

            phases.start("ground truth and view metrics")
            t0 = time.perf_counter()
            v = view_scores(scene, info["caption"], variants=variants, background=bg).as_dict()
            # the instance the run converged to is its ground truth
            s = score_against_asset(scene, info["caption"], variant=v["majority_variant"], background=bg)
            g = {
                "psnr": s.psnr,
                "ssim": s.ssim,
                "offset_deg": s.offset_deg,
                "turned_deg": turned_deg(s.offset_deg),
                "psnr_unaligned": s.psnr_unaligned,
                "variant": v["majority_variant"],
                "background": list(bg),
            }
            stamp = made(params, time.perf_counter() - t0, scene.means.device.type)
            blocks |= {"gt": g | {"made": stamp}, "views": v | {"made": stamp}}
    if colmap:
        params = {"views": views, "size": size, "background": list(bg)}
        if _reusable(previous, "colmap", params):
            blocks["colmap"] = previous["colmap"]
            reused.append("colmap")
            phases.total -= 4
        else:
            from gdbench.metrics.colmap_consistency import score_scene

            t0 = time.perf_counter()
            log = run / "colmap.log"  # COLMAP's own lines, not the console's
            c = score_scene(scene, views=views, size=size, background=bg, log=log, phase=phases.start).as_dict()
            blocks["colmap"] = c | {"made": made(params, time.perf_counter() - t0, scene.means.device.type)}


def _judge(scene, caption, previous, blocks, reused, phases) -> None:
    """The judge's block: reused where the scene, the code and the judge's version match; for an
    asset without a front, the view metrics' blob or fine (``no_front``) from this call's views
    block or the file's, applied to a reused block too."""
    from gdbench.core.provenance import made
    from gdbench.metrics.judge.judge import judge_block, judge_version

    views = blocks.get("views") or previous.get("views")
    params = {"caption": caption, "judge": judge_version()}
    if _reusable(previous, "judge", params):
        blocks["judge"] = no_front(previous["judge"], caption, views)
        reused.append("judge")
        phases.total -= int(bool(caption))
        return
    if caption:
        phases.start("the Janus judge")
    t0 = time.perf_counter()
    j = no_front(judge_block(scene, caption), caption, views)
    blocks["judge"] = j | {"made": made(params, time.perf_counter() - t0, scene.means.device.type)}


def judge_only(run: str | Path) -> dict:
    """``gdbench judge``: the judge's block of a finished run folder into its scores.json, every
    other block of the file left as it was (only the judge was asked for: a block made by older
    code is kept, not dropped as ``score`` drops what it was not asked to remake). Returns the
    file's content plus ``reused``."""
    from gdbench.core.io import FolderLock
    from gdbench.core.progress import Phases

    run = Path(run)
    with FolderLock(run, what="run"):
        info, scene_sha = one_run(run)
        path = run / "scores.json"
        old = read_json(path, what="scores.json") if path.is_file() else {}
        if old.get("scene_sha256") not in (None, scene_sha):
            old = {}  # measured on another scene: none of its blocks describe this one
        previous = previous_scores(run, scene_sha) | ({"views": old["views"]} if "views" in old else {})
        scene = GaussianScene.load_ply(run / "scene.ply")
        blocks: dict = {}
        reused: list[str] = []
        with Phases(1, "judge", disable=True) as phases:
            _judge(scene, info.get("caption"), previous, blocks, reused, phases)
        out = old | {"run": str(run), "run_id": info.get("run_id"), "scene_sha256": scene_sha,
                     "gaussians": len(scene), "caption": info.get("caption")} | blocks  # fmt: skip
        write_json(out, path)
    return out | {"reused": reused}


def no_front(j: dict, caption, views: dict | None) -> dict:
    """An asset without a front (the hamburger) leaves the judge's eye nothing to read: its readings
    of a whole hamburger are as unsure as of a blob, and no labelled result of such an asset exists
    to fit it on. There the label is the view metrics' blob or fine (``views.result_class``, which
    compares the result's views with each other and with the asset's), and says so; with no views
    block, the judge's own label stands, marked unvalidated. The eye's own label is kept
    (``eye_label``), so that the block can be decided again from other views."""
    from gdbench.assets.library import FRONTS

    if j.get("label") is None or not caption or FRONTS.get(caption, "") is not None:
        return j
    eye = j.get("eye_label", j["label"])
    if views:
        from gdbench.metrics.views import result_class

        label = "blob" if result_class(views) == "blob" else "fine"
        return j | {"label": label, "confidence": None, "judge_failure": int(label != "fine"), "eye_label": eye,
                    "decided_by": "the view metrics: the asset has no front for the judge to read"}  # fmt: skip
    return j | {"label": eye, "judge_failure": int(eye != "fine"), "eye_label": eye,
                "decided_by": "the judge, unvalidated on an asset without a front"}  # fmt: skip


def _mark(s: dict, name: str) -> str:
    m = _made(s[name])
    if name in s.get("reused", ()):
        return f" (reused: made {m.get('utc', '?')} at {m.get('commit', '?')})"
    return ""


JUDGE_WORDS = {
    "blob": "a blob: no front from any side, or profiles with the asset's front drawn nowhere",
    "front_everywhere": "the asset's front seen from every side (Janus)",
    "second_face": "a second face (Janus)",
    "fine": "one front where the asset has it, and sides and a back like the asset's",
}
"""How ``generate`` names the judge's labels (the labelling rule's classes, docs/scoring.md)."""


def _rate(x) -> str:
    """A class rate as printed: two decimals, 'n/a' where the class is undefined (no front)."""
    return "n/a" if x is None else f"{num(x):.2f}"


def gt_text(g: dict) -> str:
    """The GT block in words: the PSNR after the best turn, the turn (``gt.turned_deg``: one sign
    convention with the view metrics' turned_deg) and the PSNR as the result stands."""
    from gdbench.metrics.gt import turned_deg

    return (
        f"PSNR {num(g['psnr']):.2f} dB turned to its best match (turned {turned_deg(num(g['offset_deg'])):.0f} deg; "
        f"{num(g.get('psnr_unaligned')):.2f} dB as it stands), SSIM {num(g['ssim']):.3f}"
    )


def judge_text(j: dict | None) -> str:
    """The judge's block in words: its label and confidence, or why there is none."""
    if not j:
        return "not judged"
    if j.get("label") is None:
        return f"no label ({j.get('reason', 'nothing to judge')})"
    if j.get("decided_by"):
        return f"{j['label']} (decided by {j['decided_by']}; judge {j.get('version')})"
    turn = f"turned {num(j.get('turn_deg')):.0f} deg; " if j["label"] in ("fine", "second_face") else ""
    return (  # the turn of a result with no front of its own, or the same from every side, means nothing
        f"{j['label']} (confidence {num(j.get('confidence')):.2f}; from {j.get('mode', '?')}, {turn}"
        f"judge {j.get('version')})"
    )


def result_lines(gt: dict, views: dict | None, judge: dict | None = None) -> list[str]:
    """What a finished run's scores say, for ``generate``'s summary: the GT PSNR after the best
    turn and before it, the turn, the Janus judge's label and, when the judge calls the result a
    failure, a one-line warning with its confidence. The old view classes (``views``) are shown
    as superseded: they agreed with the raters at chance (docs/scoring.md, "The Janus judge")."""
    lines = [f"  against the asset at 12 held-out views: {gt_text(gt)}"]
    if judge is not None:
        lines.append(f"  judge: {judge_text(judge)}")
    if views:
        from gdbench.metrics.views import result_class

        janus = views.get("janus_rate")
        lines.append(
            f"  view classes (superseded by the judge): {result_class(views)}; Janus {_rate(janus)}"
            f"{' (no front)' if janus is None else ''} and blob {_rate(views.get('blob_rate'))} of 36 turntable "
            f"views, floaters {num(views.get('floaters')):.3f} of the opacity"
        )
    label = (judge or {}).get("label")
    if label is not None and label != "fine":
        sure = judge.get("confidence")
        how = f"with confidence {num(sure):.2f}" if sure is not None else f"decided by {judge.get('decided_by')}"
        lines.append(
            f"  warning: the judge calls this result {JUDGE_WORDS[label]}, {how}; the PSNR above is of that "
            "shape (docs/scoring.md, 'The Janus judge')"
        )
    return lines


def report(s: dict) -> str:
    """The lines ``gdbench score`` prints: the blocks asked for (reused ones marked), and the
    names of those the file keeps from earlier calls of the same code."""
    lines = [f"gdbench score: {s['run']} ({s['gaussians']} Gaussians) -> {Path(s['run']) / 'scores.json'}"]
    kept = set(s.get("kept", ()))
    if "gt" in s and "gt" not in kept:
        g = s["gt"]
        lines.append(f"  GT: {gt_text(g)}" + _mark(s, "gt"))
    if "views" in s and "views" not in kept:
        v = s["views"]
        lines.append(
            f"  view classes (superseded by the judge): Janus {_rate(v.get('janus_rate'))} "
            f"(front everywhere {_rate(v.get('front_everywhere_rate'))}, "
            f"second face {_rate(v.get('multi_face_rate'))}), blob {_rate(v.get('blob_rate'))}, "
            f"front share {num(v['front_share']):.2f}, "
            f"instance consistency {num(v['instance_consistency']):.2f}, floaters {num(v['floaters']):.3f}, "
            f"turned {num(v.get('turned_deg')):.0f} deg" + _mark(s, "views")
        )
    if "judge" in s and "judge" not in kept:
        lines.append(f"  judge: {judge_text(s['judge'])}" + _mark(s, "judge"))
    if "colmap" in s and "colmap" not in kept:
        c = s["colmap"]
        lines.append(
            f"  COLMAP: registered {num(c['registration_rate']):.2f}, Var(theta) {num(c['var_theta_deg2']):.4g} deg^2, "
            f"failure rate {num(c.get('failure_rate')):.2f}, "
            f"translation-direction error {num(c['translation_dir_err_deg']):.3g} deg" + _mark(s, "colmap")
        )
    if len(lines) == 1:
        lines.append("  nothing scored (--no-gt --no-colmap, or a run without a caption for the GT scores)")
    if kept:
        lines.append(f"  scores.json also keeps, not recomputed now: {', '.join(sorted(kept))} (same scene and commit)")
    return "\n".join(lines)
