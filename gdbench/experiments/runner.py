"""One runner for the experiments made of blocks (docs/decisive.md, docs/decisive_v3.md): a block is
one sweep (groups x settings x prompts x presets x seeds); ``run_blocks`` runs an experiment's
blocks, seeds in rounds; ``collect`` reads every finished cell's row back. An experiment is a
definition file (its blocks, seeds and claims: ``decisive.py`` for the 068b215 experiment,
``v3_design.py`` for v3) and its report (``decisive.py``'s ``report``, ``v3_report.py``).

A group is a prior with a number of views per step, named ``<prior>-v<views per step>``
('learned-v4': the learned prior, four views per step); the names are the ones stored in every
cell's row, so they stay.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

VIEWS_SPREAD_DEG = 10.0
"""Degrees the views of one step stay within (views per step 4): structured noise at the same
surface point correlates 0.75 at 5 degrees, 0.41 at 10 and 0.10 at 30 (coupling.csv)."""

GROUPS = {
    "empirical-v1": {"prior": "empirical"},
    "empirical-v4": {"prior": "empirical", "views_per_step": 4, "views_spread_deg": VIEWS_SPREAD_DEG},
    "learned-v1": {"prior": "learned"},
    "learned-v4": {"prior": "learned", "views_per_step": 4, "views_spread_deg": VIEWS_SPREAD_DEG},
    # the control: structured noise without a shared source (new colours every step, so no two
    # steps' views share noise; only its spatial statistics remain)
    "learned-v1-step": {"prior": "learned", "noise.redraw": "step"},
}
"""The prior x views-per-step factor, one group each (cells pair within a group): ``<prior>-v<views per
step>``, and the redraw control of the 068b215 pilot."""


@dataclass(frozen=True)
class Block:
    """One sweep: groups x settings x prompts x presets x seeds, its COLMAP scoring and steps."""

    name: str
    groups: list[str]
    settings: list[str]
    presets: list[str]
    colmap: bool = False
    steps: int = 1000
    prompts: list[str] = field(default_factory=list)
    overrides: dict = field(default_factory=dict)
    """Overrides of every cell (under the groups')."""

    def __post_init__(self) -> None:
        from gdbench.experiments.sweep import SETTINGS
        from gdbench.train.config import PRESETS

        if not isinstance(self.colmap, bool) or not isinstance(self.steps, int) or self.steps < 1:
            raise ValueError(f"Block {self.name!r}: expected colmap a bool and steps an int >= 1, "
                             f"got {self.colmap!r} and {self.steps!r}")  # fmt: skip
        for what, items, known in (("groups", self.groups, GROUPS), ("settings", self.settings, SETTINGS),
                                   ("presets", self.presets, PRESETS)):  # fmt: skip
            unknown = [x for x in items if x not in known]
            if unknown or not items or len(set(items)) != len(items):
                raise ValueError(f"Block {self.name!r}: {what} {items}: expected distinct names from {list(known)}")
        if not self.prompts:
            raise ValueError(f"Block {self.name!r}: expected prompts, got none")


def run_blocks(blocks: list[Block], seeds: list[int], out: Path, args, rounds: int) -> dict[str, list[dict]]:
    """Each block's sweep into ``out/blocks/<name>``, the seeds in ``rounds`` rounds (every block
    gets its first seeds before any block its last); returns each block's rows."""
    from gdbench.experiments.sweep import SweepConfig, sweep

    rows: dict[str, list[dict]] = {}
    per = max(1, -(-len(seeds) // rounds))
    for k in range(per, len(seeds) + per, per):
        for b in blocks:
            print(f"blocks: block {b.name}, seeds {seeds[:k]}", flush=True)
            rows[b.name] = sweep(SweepConfig(
                b.prompts, b.presets, seeds[: min(k, len(seeds))], steps=b.steps, out=out / "blocks" / b.name,
                executor=args.executor, address=args.address, workers=args.workers, colmap=b.colmap,
                settings=b.settings, groups={g: GROUPS[g] for g in b.groups}, overrides=b.overrides,
                progress=args.progress, figures=True,  # the turntable grids read the cells' GIFs
            ))  # fmt: skip
    return rows


def collect(out: Path, plain: list[tuple[Path, str]] = (), fix: Callable[[dict], None] | None = None) -> list[dict]:
    """Every finished cell's row under ``out/blocks`` (read from its cell.json), and those of plain
    ``gdbench sweep`` folders (no groups) given the group name they stand for; ``fix(row)``, where
    an experiment gives one, reads its older rows as today's (``decisive.old_rows``). Cells run for
    other than 1000 steps say so after the group (', 2000 steps'), so they never pair with
    1000-step cells; a cell found twice is an error."""
    import math

    from gdbench.core.io import read_json

    rows = []
    for root, group in [(out / "blocks", None), *plain]:
        for p in sorted(Path(root).glob("**/cells/**/cell.json")):
            row = read_json(p, what="cell.json")["row"]
            row = {k: math.nan if v is None else v for k, v in row.items()}
            rows.append(row if group is None else row | {"group": group})
    for r in rows:
        if fix is not None:
            fix(r)
        if int(r["iterations"]) != 1000:
            r["group"] = f"{r['group']}, {int(r['iterations'])} steps"
    seen: dict[tuple, int] = {}
    for r in rows:
        key = tuple(r[k] for k in ("group", "setting", "prompt", "preset", "seed"))
        seen[key] = seen.get(key, 0) + 1
    twice = [k for k, n in seen.items() if n > 1]
    if twice:
        raise ValueError(f"collect: {len(twice)} cells found twice (e.g. {twice[0]}): a --plain folder overlaps a "
                         f"block, or pilot and sweep share {out}")  # fmt: skip
    order = {s: i for i, s in enumerate(("easy", "janus", "instance"))}
    return sorted(rows, key=lambda r: (r["group"], order.get(r["setting"], 9), r["prompt"], r["seed"]))
