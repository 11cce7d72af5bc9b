"""``gdbench sweep``: train and score every (setting, prompt, preset, seed) cell; write the
ablation's tables (``experiments/tables.py``): per-cell rows, per-preset summaries and the verdict on
the paper's claims with bootstrap confidence intervals.

Settings (``SETTINGS``) dial the embedded prior's ambiguity: ``easy`` (the presets' own +-45
degree view window, one variant), ``janus`` (no view prompting and a front-heavy bank: the
multi-face mechanism) and ``instance`` (three procedural variants per caption). Cells pair by
(prompt, seed): every preset sees the same views and noise levels (``train/streams.py``).

Resumable: each cell lives in ``out/cells/<setting>/<prompt>/<preset>/seed<k>``; a finished cell
(its ``cell.json`` matching its spec) is skipped, and an interrupted one resumes from its
training checkpoint. The whole grid is validated before the first cell. Executors are
pluggable: ``local`` (a process pool, default one worker, since one training already uses both
cores here) or ``ray`` (``--address`` of a cluster, or a local instance when empty).
"""

from __future__ import annotations

import json
import math
import re
import sys
import time
from collections.abc import Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Literal

SETTINGS: dict[str, dict] = {
    "easy": {},
    "janus": {"view_prompting": "none", "front_bias": 1.0},
    "instance": {"variants": 3},
}
"""Ambiguity settings: overrides of every preset in the setting (docs/scoring.md)."""

LEARNED_SETTINGS: dict[str, dict] = {"janus": {"front_bias": 2.0}}
"""What changes in a setting under --prior learned: the janus setting takes the shipped model
trained on front-heavy views (kappa 2; the learned prior has no kappa-1 model)."""


@dataclass(frozen=True)
class CellSpec:
    prompt: str
    preset: str
    seed: int
    steps: int
    out: str
    colmap: bool = True
    colmap_views: int = 100
    overrides: dict = field(default_factory=dict)
    setting: str = "easy"
    group: str = ""
    """A named set of overrides the sweep crosses with everything else ('' when it has none)."""
    base: str = ""
    """For a preset the sweep file defines: the built-in preset it overlays ('' for a built-in)."""
    overlay: dict = field(default_factory=dict)
    """... and its overrides, applied to the base before the setting's and the sweep's."""

    @property
    def dir(self) -> Path:
        base = Path(self.out) / "cells" / self.group if self.group else Path(self.out) / "cells"
        return base / self.setting / cell_name(self.prompt) / self.preset / f"seed{self.seed}"


TABLES_EVERY_S = 300.0
"""Seconds between the tables a running sweep rewrites (and always once at its end): rewriting
them after every cell costs seconds per cell at hundreds of cells (each claim's 10,000 bootstrap
resamples and the figure of every cell), in the main process beside the workers."""


def cell_name(prompt: str) -> str:
    """A prompt as a cell's folder name (``io.prompt_slug``)."""
    from gdbench.core.io import prompt_slug

    return prompt_slug(prompt, "prompts")


def validate_grid(
    prompts: list[str],
    presets: list[str],
    seeds: list[int],
    specs: list[CellSpec],
    executor: str = "local",
    defined: set[str] = frozenset(),
) -> None:
    """Everything a sweep could fail on, checked before the first cell trains: presets, repeated
    entries, cell folders two prompts would share, prompts no asset matches (or that contradict
    it), and each cell's config and device (Ray's tasks get no GPU)."""
    from gdbench.assets.library import CAPTIONS
    from gdbench.priors.compose import resolve
    from gdbench.priors.text import CaptionMatcher
    from gdbench.train.config import PRESETS

    bad = [p for p in presets if p not in PRESETS and p not in defined]
    if bad:
        raise ValueError(
            f"presets: unknown {bad}; expected names from {sorted(PRESETS)}"
            + (f" or the sweep's own {sorted(defined)}" if defined else " (or define them: define_presets)")
        )
    if not prompts or not presets or not seeds:
        raise ValueError("prompts, presets, seeds: expected at least one of each")
    for name, items in (("presets", presets), ("seeds", seeds)):
        if len(set(items)) != len(items):
            raise ValueError(f"{name}: {sorted({x for x in items if items.count(x) > 1})} listed more than once")
    from gdbench.core.devices import resolve_device

    configs = [cell_config(spec) for spec in specs]  # a bad override raises here, naming the setting
    for device in sorted({cfg.device for cfg in configs}):  # before any bank or palette
        if resolve_device(device, "device (--device)").type == "cuda" and executor == "ray":
            raise ValueError(
                "device: Ray runs a sweep's cells as tasks without a GPU (it hides the GPUs from them); "
                "use --executor local with --device cuda"
            )
    names: dict[str, str] = {}
    for pr in prompts:
        n = cell_name(pr)
        if n in names:
            raise ValueError(
                f"prompts: {names[n]!r} and {pr!r} would share the cell folder {n!r}; list each prompt once"
            )
        names[n] = pr
    matcher = CaptionMatcher(list(CAPTIONS))
    for pr in prompts:
        try:
            resolve(pr, matcher)
        except ValueError as e:
            raise ValueError(f"prompts: {str(e).removeprefix('prompt: ')}") from None


def inert_overrides(specs: list[CellSpec]) -> list[str]:
    """Options of the sweep (its overrides and its groups') that do nothing in some of the cells
    given them, one line each (naming the cells' presets, groups and settings); an option that
    does nothing in every cell given it raises ValueError."""
    from gdbench.experiments.claims import label
    from gdbench.train.options import inert_options

    given: dict[str, int] = {}
    where: dict[str, list[tuple[str, str, str]]] = {}
    why: dict[str, str] = {}
    for spec in specs:
        cfg = cell_config(spec)
        for key in spec.overrides:
            given[key] = given.get(key, 0) + 1
            for line in inert_options(cfg, [key]):
                where.setdefault(key, []).append((spec.preset, spec.group, spec.setting))
                why[key] = line
    lines = []
    for key, cells in where.items():
        if len(cells) == given[key]:
            raise ValueError(f"{why[key]}, in every cell of the sweep: drop the option, or set the one it needs")
        names = sorted({f"{p} ({label({'group': g, 'setting': s})})" for p, g, s in cells})
        opt, rest = why[key].split(" ", 1)
        lines.append(f"{opt} does nothing in {', '.join(names)}: it {rest}")
    return lines


def define_presets(defined: Mapping[str, Mapping] | None) -> dict[str, tuple[str, dict]]:
    """A sweep file's presets: name -> (the built-in base, its overrides), each checked (a name not a
    built-in's, a known base, overrides that apply: ``train.config.apply_overrides``)."""
    from gdbench.train.config import PRESETS, apply_overrides

    out = {}
    for name, d in (defined or {}).items():
        where = f"define_presets: {name}"
        if not isinstance(name, str) or not re.fullmatch(r"[a-z][a-z0-9_.-]*", name) or name in PRESETS:
            raise ValueError(f"{where}: expected a new name (lower-case letters, digits, '_-.'; not a built-in's)")
        if not isinstance(d, Mapping) or set(d) - {"base", "overrides"} or d.get("base") not in PRESETS:
            raise ValueError(f"{where}: expected {{base: one of {sorted(PRESETS)}, overrides: {{...}}}}, got {d!r}")
        over = dict(d.get("overrides") or {})
        try:
            apply_overrides(PRESETS[d["base"]], over)
        except ValueError as e:
            raise ValueError(f"{where}: {e}") from None
        out[name] = (d["base"], over)
    return out


def cell_config(spec: CellSpec):
    """The TrainConfig of a cell: the preset (a sweep file's: its base with its overrides), its
    setting's overrides, then the sweep's."""
    from gdbench.train.config import PRESETS, apply_overrides, preset

    if spec.base:
        start = apply_overrides(PRESETS[spec.base], spec.overlay | {"preset": spec.preset})
        run = {"prompt": spec.prompt, "steps": spec.steps, "seed": spec.seed, "out": spec.dir, "progress": False}
        setting = setting_overrides(spec.setting, (spec.overlay | spec.overrides).get("prior"))
        return apply_overrides(start, run | setting | spec.overrides)
    return preset(
        spec.preset,
        prompt=spec.prompt,
        steps=spec.steps,
        seed=spec.seed,
        out=spec.dir,
        progress=False,
        **(setting_overrides(spec.setting, spec.overrides.get("prior")) | spec.overrides),
    )


def prior_name(cfg) -> str:
    """The prior of a config as a table names it: 'empirical', 'sd', or 'learned:<model>' (the
    shipped model 'auto' resolves to, or the model's path)."""
    return "learned:" + cfg.prior.model if cfg.prior.kind == "learned" else cfg.prior.kind


def setting_overrides(setting: str, prior: str | None) -> dict:
    """The overrides of an ambiguity setting for a prior ('empirical' when None)."""
    return SETTINGS[setting] | (LEARNED_SETTINGS.get(setting, {}) if prior == "learned" else {})


def turned_failure(views: dict, front_defined: bool) -> float:
    """1.0 when a result is turned by more than 45 degrees, 0.0 when not; NaN where that is no
    failure: view prompting does not define the front, or the result has none to turn (mostly
    featureless views: a blob's turn is arbitrary), or the views were not scored."""
    from gdbench.core.io import num

    if not front_defined or "turned_deg" not in views or not num(views.get("featureless_rate")) <= 0.5:
        return math.nan
    return float(abs(num(views["turned_deg"])) > 45)


def run_cell(spec: CellSpec, figures: bool = False) -> dict:
    """Train (or resume) and score one cell; writes and returns its row. ``figures``: also the
    run's turntable and curves (``train.run.train``); cell.json records the cell's timings."""
    from gdbench.core.io import num, read_json, write_json
    from gdbench.core.provenance import code_commit
    from gdbench.metrics.run_scores import score_run
    from gdbench.train.checkpoint import CheckpointError
    from gdbench.train.run import train

    t0 = time.perf_counter()
    cfg = cell_config(spec)
    try:
        r = train(cfg, figures=figures)
    except (CheckpointError, FileExistsError) as e:  # the sweep has no --overwrite: say what to delete
        raise CheckpointError(
            f"{str(e).split(';')[0]}; delete {spec.dir} to retrain this cell, or sweep into another --out"
        ) from None
    train_s = sum(h["seconds"] for h in r.state.history)
    t_score = time.perf_counter()
    scores = score_run(spec.dir, colmap=spec.colmap, views=spec.colmap_views, device=cfg.device)
    t_scored = time.perf_counter()
    run_info = read_json(spec.dir / "run.json", what="run.json")
    front_defined = cfg.prior.view_prompting != "none"
    # only what this cell asked for: a COLMAP block the file keeps from an earlier pass is not the sweep's
    col = scores.get("colmap", {}) if spec.colmap else {}
    views, gt, judged = scores.get("views", {}), scores.get("gt", {}), scores.get("judge") or {}
    get = lambda block, key: num(block.get(key))  # noqa: E731  (null in a file: NaN)
    row = {
        "group": spec.group,
        "setting": spec.setting,
        "prompt": spec.prompt,
        "preset": spec.preset,
        "seed": spec.seed,
        "variants": getattr(cfg.prior, "variants", 1),
        "prior": prior_name(cfg),
        "views_per_step": cfg.views.per_step,
        "views_spread_deg": math.nan if cfg.views.spread_deg is None else cfg.views.spread_deg,
        "iterations": r.state.step,
        "train_time_s": train_s,
        "gaussians": scores["gaussians"],
        "gt_psnr": get(gt, "psnr"),
        "gt_ssim": get(gt, "ssim"),
        "gt_offset_deg": get(gt, "offset_deg"),
        "gt_psnr_unaligned": get(gt, "psnr_unaligned"),
        "judge_label": judged.get("label") or "",  # the Janus judge's class ('': not judged)
        "judge_confidence": get(judged, "confidence"),
        "judge_janus": get(judged, "judge_janus"),  # 1: front_everywhere or second_face
        "judge_failure": get(judged, "judge_failure"),  # 1: not fine
        # the view classes (superseded by the judge: at chance against the raters, docs/scoring.md)
        "multi_face_rate": get(views, "multi_face_rate"),  # second_face (NaN: the asset has no front)
        "front_everywhere_rate": get(views, "front_everywhere_rate"),
        "blob_rate": get(views, "blob_rate"),
        "janus_rate": get(views, "janus_rate"),  # front_everywhere + second_face
        "featureless_rate": get(views, "featureless_rate"),  # front_everywhere + blob
        # older tables' sum: views with no face or a second one (disjoint classes)
        "janus_failure_rate": get(views, "featureless_rate") + get(views, "multi_face_rate"),
        "front_share": get(views, "front_share"),
        "instance_inconsistency": 1.0 - get(views, "instance_consistency"),
        "majority_variant": int(views.get("majority_variant", -1)),
        "floaters": get(views, "floaters"),
        "turned_deg": get(views, "turned_deg"),
        "turned": turned_failure(views, front_defined),
        "registration_rate": get(col, "registration_rate"),
        "var_theta_deg2": get(col, "var_theta_deg2"),
        "colmap_failure_rate": get(col, "failure_rate"),
        "translation_dir_err_deg": get(col, "translation_dir_err_deg"),
        "cell_s": time.perf_counter() - t0,
        "run_id": run_info.get("run_id"),  # the hash of the config that changes the result
        "threads": run_info.get("threads"),  # results may depend on it (reduction order; 1 and 2 agree)
        "device": run_info.get("device", "cpu"),  # and on the device, by float rounding
        "train_commit": run_info.get("commit", "unknown"),
        "score_commit": code_commit(),
        "versions": "; ".join(f"{k} {v}" for k, v in run_info.get("versions", {}).items()),
    }
    # run.json's timings are this call's only if it finished the run (a run found finished keeps
    # those of the call that trained it)
    made = run_info.get("timings", {}) if r.resumed_from is None or r.resumed_from < cfg.steps else {}
    timings = {  # where this call's time went (a resumed or finished run trains little or nothing)
        "train_call_s": t_score - t0,
        "setup_s": made.get("setup_s"),
        "steps_s": sum(h["seconds"] for h in r.state.history[r.resumed_from or 0 :]),  # this call's
        "outputs_s": made.get("outputs_s"),
        "score_s": t_scored - t_score,
        "score_blocks_s": {k: v["made"].get("seconds") for k, v in scores.items()  # made in this call
                           if isinstance(v, dict) and "made" in v and k not in scores.get("reused", [])},
        "cell_s": time.perf_counter() - t0,
    }  # fmt: skip
    write_json({"spec": asdict(spec), "row": row, "timings": timings}, spec.dir / "cell.json")
    return row


def _done(spec: CellSpec, figures: bool = False) -> dict | None:
    """The row of a cell finished with this spec and scored by this code (with its figures, when
    ``figures``); None otherwise (the cell is then scored again: its training resumes, or is found
    finished, from its folder)."""
    from gdbench.core.io import read_json
    from gdbench.core.provenance import same_code

    p = spec.dir / "cell.json"
    if not p.is_file() or (figures and not (spec.dir / "turntable.gif").is_file()):
        return None
    blob = read_json(p, what="cell.json")
    row = blob.get("row")
    if not isinstance(row, dict):
        raise ValueError(f"cell.json: {p} holds no 'row' object; delete it to score the cell again")
    if blob.get("spec") != json.loads(json.dumps(asdict(spec))) or not same_code(row.get("score_commit")):
        return None
    return {k: math.nan if v is None else v for k, v in row.items()}  # null: a missing number


@dataclass(frozen=True)
class SweepConfig:
    """A sweep's grid: groups x settings x prompts x presets x seeds, and how its cells run."""

    prompts: Sequence[str]
    presets: Sequence[str]
    seeds: Sequence[int]
    steps: int = 2000
    """Training steps per cell."""
    out: str | Path = "runs/sweep"
    """Folder of the cells (one run folder each) and the tables."""
    executor: Literal["local", "ray"] = "local"
    address: str = ""
    """Ray cluster address (ray executor); empty starts a local Ray instance."""
    workers: int = 1
    """Cells run at once."""
    colmap: bool = True
    """Score cells with COLMAP consistency."""
    colmap_views: int = 100
    overrides: Mapping[str, object] | None = None
    """Training overrides of every cell (``train.config.apply_overrides``'s keys), after its setting's."""
    progress: bool = True
    settings: Sequence[str] | None = None
    """Ambiguity settings (default: easy)."""
    setting_presets: Mapping[str, Sequence[str]] | None = None
    """Restricts the presets of a setting (default: all ``presets``)."""
    colmap_presets: Sequence[str] | None = None
    """Restrict COLMAP scoring to these presets (default: every cell, when ``colmap``)."""
    colmap_settings: Sequence[str] | None = None
    """... and to these settings."""
    groups: Mapping[str, Mapping[str, object]] | None = None
    """Named sets of overrides applied on top of ``overrides`` (a factor the ambiguity settings do
    not cover: the prior, views per step); each group's cells live in ``out/cells/<group>/`` and
    claims pair within a group (default: one unnamed group)."""
    figures: bool = False
    """Each cell also writes its turntable and training curves (what ``turntable_grid`` reads), and
    the sweep ablation.png; off, only what the tables need (a finished sweep run again with
    ``figures`` draws them without training)."""
    defined_presets: Mapping[str, Mapping] | None = None
    """Presets of the sweep's own: name -> {base: a built-in preset, overrides: {...}} (a user's
    method enters here: guidance or noise.source as a reference), usable in ``presets``."""
    claims: Sequence | None = None
    """Claims of the sweep's own (``claims.Claim``s or their mappings: text, a, b, metric,
    fails_at), between any two of its presets, verdicts in their own family beside the paper's."""
    labels: Sequence[str | Path] | None = None
    """Rater label files (run_id, label: ``gdbench.metrics.label_sheets --unblind``): the claims on
    the Janus outcome read them; without, the shipped judge (summary.md says which)."""


def grid(cfg: SweepConfig) -> tuple[list[CellSpec], dict, dict]:
    """The cells of ``cfg`` (seeds outermost), the claim families its tables read (the paper's, and
    the sweep's own where it has some) and the presets it defines; its settings, groups and
    per-setting presets checked."""
    prompts, presets, seeds = list(cfg.prompts), list(cfg.presets), list(cfg.seeds)
    out = Path(cfg.out)
    from gdbench.experiments.claims import CLAIMS, user_claims

    defined = define_presets(cfg.defined_presets)
    own = user_claims(cfg.claims, presets)
    families = {"": CLAIMS} | ({"sweep": own} if own else {})  # the sweep's own claims: a family of their own
    settings = list(cfg.settings or ["easy"])
    bad = [s for s in settings if s not in SETTINGS]
    if bad or len(set(settings)) != len(settings):
        raise ValueError(f"settings: expected distinct names from {sorted(SETTINGS)}, got {settings}")
    per = {s: list((cfg.setting_presets or {}).get(s, presets)) for s in settings}
    groups = dict(cfg.groups or {"": {}})
    bad = [g for g in groups if not re.fullmatch(r"[a-z][a-z0-9_.-]*", g)] if list(groups) != [""] else []
    if bad or not groups:
        raise ValueError(
            f"groups: expected names of a lower-case letter, then letters, digits, '_', '-' or '.', got {bad}"
        )
    for s, ps in per.items():
        if not set(ps) <= set(presets):
            raise ValueError(f"setting_presets: {s} lists presets outside --presets: {sorted(set(ps) - set(presets))}")
    # seeds outermost: a sweep cut short still has every (setting, prompt, preset) for its first seeds
    specs = [
        CellSpec(
            pr,
            p,
            sd,
            cfg.steps,
            str(out),
            cfg.colmap
            and (cfg.colmap_presets is None or p in cfg.colmap_presets)
            and (cfg.colmap_settings is None or st in cfg.colmap_settings),
            cfg.colmap_views,
            dict(cfg.overrides or {}) | dict(gov),
            st,
            g,
            *defined.get(p, ("", {})),
        )
        for sd in seeds
        for g, gov in groups.items()
        for st in settings
        for pr in prompts
        for p in per[st]
    ]
    return specs, families, defined


def sweep(cfg: SweepConfig, *, on_valid=None) -> list[dict]:
    """Train and score the grid of ``cfg``; returns the rows. ``on_valid()``, if given, is called
    once the grid is validated, before any cell runs. ``out/timings.json`` records where the
    call's time went (validation, cells, tables)."""
    from gdbench.experiments.tables import tables

    out = Path(cfg.out)
    specs, families, defined = grid(cfg)
    t_start = time.perf_counter()
    validate_grid(list(cfg.prompts), list(cfg.presets), list(cfg.seeds), specs, cfg.executor, set(defined))
    t_valid = time.perf_counter()
    if cfg.executor == "ray" and cfg.address:
        check_ray_address(cfg.address)
    for line in inert_overrides(specs):
        print(f"sweep: note: {line}", file=sys.stderr)
    if on_valid is not None:
        on_valid()
    rows: dict[int, dict] = {}
    todo = []
    for i, spec in enumerate(specs):
        done = _done(spec, cfg.figures)
        if done is not None:
            rows[i] = done
        else:
            todo.append(i)
    if cfg.progress:
        print(f"sweep: {len(specs)} cells, {len(rows)} already finished, {len(todo)} to run ({cfg.executor})")
    from gdbench.core.progress import progress as progress_bar

    bar = progress_bar(len(todo), "sweep", "cell", disable=not cfg.progress or not todo)
    written = time.monotonic()
    tables_s = 0.0
    t_cells = time.perf_counter()
    try:
        for i, row in _execute([specs[i] for i in todo], cfg.executor, cfg.address, cfg.workers, cfg.figures):
            rows[todo[i]] = row
            if time.monotonic() - written >= TABLES_EVERY_S:  # a look at a long sweep's tables
                t0 = time.perf_counter()
                tables([rows[k] for k in sorted(rows)], out, cfg.figures, claims=families, labels=cfg.labels)
                tables_s += time.perf_counter() - t0
                written = time.monotonic()
            if bar is not None:
                bar.write(cell_line(row))
                bar.update(1)
    finally:
        if bar is not None:
            bar.close()
    t_end = time.perf_counter()
    cells_s = t_end - t_cells - tables_s  # without the periodic rewrites of the tables
    ordered = [rows[k] for k in sorted(rows)]
    tables(ordered, out, cfg.figures, claims=families, labels=cfg.labels)
    tables_s += time.perf_counter() - t_end
    from gdbench.core.io import write_json
    from gdbench.core.provenance import code_commit

    timings = {"commit": code_commit(), "cells": len(specs), "ran": len(todo), "workers": cfg.workers,
               "validate_s": t_valid - t_start, "cells_s": cells_s, "tables_s": tables_s,
               "sweep_s": time.perf_counter() - t_start}  # fmt: skip
    write_json(timings, out / "timings.json")
    return ordered


def _worker_threads(threads: int) -> None:
    """A local worker's start: torch (and the OpenMP compositor) on ``threads`` threads."""
    import torch

    torch.set_num_threads(threads)


RAY_CONNECT_TIMEOUT = 10.0
"""Seconds a Ray cluster's address may take to accept a connection before the sweep gives up."""


def check_ray_address(address: str, timeout: float = RAY_CONNECT_TIMEOUT) -> None:
    """A cluster address (``host:port`` or ``ray://host:port``; ``auto`` finds a local one) must
    accept a TCP connection within ``timeout`` seconds: ``ray.init`` itself waits for minutes on an
    address nobody answers."""
    import socket

    if address in ("auto", "local"):
        return
    host, _, port = address.removeprefix("ray://").rpartition(":")
    if not host or not (port.isascii() and port.isdigit() and 0 < int(port) < 65536):
        raise ValueError(f"address: expected HOST:PORT or ray://HOST:PORT (or 'auto'), got {address!r}")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout).close()
    except OSError as e:
        raise ValueError(
            f"address: nothing answers at {host}:{port} within {timeout:g} s ({e.strerror or e}); start the cluster "
            "(ray start --head) or leave --address empty for a local Ray instance"
        ) from None


def _execute(specs: list[CellSpec], executor: str, address: str, workers: int, figures: bool = False):
    """Yield (index, row) as cells finish."""
    import functools

    cell = functools.partial(run_cell, figures=figures)  # picklable: a module function and a bool
    if executor == "local":
        if workers <= 1:
            for i, s in enumerate(specs):
                yield i, cell(s)
            return
        import multiprocessing
        import os
        from concurrent.futures import ProcessPoolExecutor, as_completed

        # fresh interpreters (not forks of one that ran OpenMP), each on its share of the cores:
        # two-thread workers on two cores spin-wait for each other (measured 10x slower steps)
        threads = max(1, (os.cpu_count() or 1) // workers)
        ctx = multiprocessing.get_context("spawn")
        pool = ProcessPoolExecutor(workers, mp_context=ctx, initializer=_worker_threads, initargs=(threads,))
        try:
            futs = {pool.submit(cell, s): i for i, s in enumerate(specs)}
            for f in as_completed(futs):
                yield futs[f], f.result()
        finally:  # a stop signal or an error: queued cells are cancelled, not run to the end
            pool.shutdown(wait=True, cancel_futures=True)
        return
    if executor == "ray":
        try:
            import ray
        except ImportError as e:
            raise ImportError("executor='ray' needs Ray: pip install 'ray[default]'") from e
        started = not ray.is_initialized()
        if started:
            ray.init(
                address=address or None,
                include_dashboard=False,
                num_cpus=None if address else max(workers, 1),
                log_to_driver=False,
            )
        try:
            remote = ray.remote(run_cell)
            refs = {remote.remote(s, figures): i for i, s in enumerate(specs)}
            pending = list(refs)
            while pending:
                ready, pending = ray.wait(pending, num_returns=1)
                yield refs[ready[0]], ray.get(ready[0])
        finally:
            if started:
                ray.shutdown()
        return
    raise ValueError(f"executor: expected 'local' or 'ray', got {executor!r}")


def cell_line(row: dict) -> str:
    """A finished cell in one line: its GT PSNR, the judge's label (the failure class, with its
    confidence), floaters, and COLMAP's failure rate where the cell was scored with COLMAP."""
    from gdbench.core.io import num
    from gdbench.experiments.claims import label

    judged = row.get("judge_label") or "not judged"
    sure = num(row.get("judge_confidence"))
    judged += f" ({sure:.2f})" if sure == sure else ""
    colmap = num(row.get("colmap_failure_rate"))
    return (
        f"  done {label(row)} {row['prompt']!r} {row['preset']} seed {row['seed']}: PSNR {num(row['gt_psnr']):.2f}, "
        f"judge {judged}, floaters {num(row['floaters']):.3f}"
        + (f", COLMAP failure {colmap:.2f}" if colmap == colmap else "")
        + f" ({num(row['cell_s']):.0f} s)"
    )
