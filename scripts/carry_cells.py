"""Carry a long sweep's finished cells from one sitting to the next.

    python scripts/carry_cells.py pack /work/runs/v3 docs/results/v3/carry/cells.tar.xz
    python scripts/carry_cells.py unpack docs/results/v3/carry/cells.tar.xz /work/runs/v3
    PYTHONPATH=<clone at the sweep's commit> python scripts/carry_cells.py resume /work/runs/v3

A sitting's machine keeps only what is committed; a sweep's run folders (turntables, checkpoints:
about 0.7 MB a cell) are too large to commit, its cells' results are not. ``pack`` stores each
finished cell's cell.json, run.json and scores.json (what ``collect`` and the sweep's finished
test read, and the run's provenance) under their paths relative to the sweep folder; ``unpack``
puts them back. A cell's cell.json names its folder by absolute path in its spec, so unpack into
the same folder the sweep ran in.

``resume`` runs the rest of the registered v3 sweep (``gdbench.experiments.v3``) like its
``sweep`` stage but without the turntable GIFs: the sweep skips a finished cell only when its GIF
is there (for the figures), and an unpacked cell has none, so ``v3 sweep`` would train it again.
A cell's row does not depend on the figures. Run it with the frozen clone's code on the path
(PYTHONPATH), so the cells carry the registered commit.
"""

from __future__ import annotations

import sys
import tarfile
from pathlib import Path

KEEP = ("cell.json", "run.json", "scores.json")


def pack(out: Path, archive: Path) -> int:
    cells = sorted(out.glob("**/cell.json"))
    archive.parent.mkdir(parents=True, exist_ok=True)
    tmp = archive.with_suffix(".tmp")
    with tarfile.open(tmp, "w:xz") as tar:
        for c in cells:
            for name in KEEP:
                if (c.parent / name).is_file():
                    tar.add(c.parent / name, arcname=str((c.parent / name).relative_to(out)))
    tmp.replace(archive)  # atomic: a pack cut short leaves the previous archive
    print(f"pack: {len(cells)} finished cells of {out} -> {archive} ({archive.stat().st_size / 1e6:.1f} MB)")
    return len(cells)


def unpack(archive: Path, out: Path) -> None:
    with tarfile.open(archive) as tar:
        names = tar.getnames()
        bad = [n for n in names if n.startswith("/") or ".." in Path(n).parts]
        if bad:
            raise SystemExit(f"unpack: {archive} holds paths outside the sweep folder: {bad[:3]}")
        tar.extractall(out, filter="data")
    print(f"unpack: {sum(n.endswith('cell.json') for n in names)} cells -> {out}")


def resume(out: Path, workers: int = 2) -> None:
    from gdbench.experiments.runner import GROUPS
    from gdbench.experiments.sweep import SweepConfig, sweep
    from gdbench.experiments.v3 import REGISTERED, sweep_blocks

    seeds = list(range(REGISTERED["seeds"]))
    for b in sweep_blocks(REGISTERED):  # as runner.run_blocks, one round, figures off
        print(f"resume: block {b.name}, seeds {seeds}", flush=True)
        sweep(SweepConfig(
            b.prompts, b.presets, seeds, steps=b.steps, out=out / "blocks" / b.name, executor="local",
            address="", workers=workers, colmap=b.colmap, settings=b.settings,
            groups={g: GROUPS[g] for g in b.groups}, overrides=b.overrides, progress=True, figures=False,
        ))  # fmt: skip


def main(argv: list[str]) -> int:
    usage = "usage: carry_cells.py pack OUT ARCHIVE | unpack ARCHIVE OUT | resume OUT"
    if len(argv) < 2 or argv[0] not in ("pack", "unpack", "resume"):
        raise SystemExit(usage)
    if argv[0] == "resume":
        resume(Path(argv[1]).resolve())
        return 0
    if len(argv) != 3:
        raise SystemExit(usage)
    a, b = Path(argv[1]), Path(argv[2])
    if argv[0] == "pack":
        pack(a.resolve(), b)
    else:
        if not a.is_file():
            raise SystemExit(f"unpack: ARCHIVE {a} is not a file")
        unpack(a, b.resolve())
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
