"""scripts/carry_cells.py: a sweep's finished cells packed, their folder lost, unpacked: the sweep
then finds each cell finished with the row it had (without figures), and asks for it again where
the figures are wanted (the turntable GIF is not carried)."""

import json
import shutil
import tarfile

import pytest

from gdbench.experiments.sweep import CellSpec, SweepConfig, _done, sweep
from tests._util import TINY_CELL, script


def test_packed_cells_come_back_finished_with_their_rows(tmp_path):
    carry = script("carry_cells")
    out = tmp_path / "sweep"
    cfg = SweepConfig(
        ["a yellow duck"], ["gd"], [0], steps=4, out=out, colmap=False, overrides=TINY_CELL, progress=False
    )
    (row,) = sweep(cfg)
    spec = CellSpec("a yellow duck", "gd", 0, 4, str(out), colmap=False, overrides=TINY_CELL)
    cell = json.loads((spec.dir / "cell.json").read_text())
    archive = tmp_path / "carry" / "cells.tar.xz"
    assert carry.pack(out, archive) == 1
    with tarfile.open(archive) as tar:  # only the small files, by their path under the sweep folder
        names = sorted(tar.getnames())
    rel = spec.dir.relative_to(out)
    assert names == sorted(str(rel / n) for n in carry.KEEP)
    shutil.rmtree(out)
    carry.unpack(archive, out)
    assert json.loads((spec.dir / "cell.json").read_text()) == cell
    back = _done(spec, figures=False)  # the same row, so the sweep skips the cell
    assert back is not None and json.dumps(back, sort_keys=True) == json.dumps(row, sort_keys=True)
    assert _done(spec, figures=True) is None  # no GIF came back: a --figures sweep would train it again
    assert not (spec.dir / "checkpoint.pt").exists()


def test_unpack_refuses_paths_outside_the_sweep_folder(tmp_path):
    carry = script("carry_cells")
    bad = tmp_path / "bad.tar.xz"
    (tmp_path / "x.json").write_text("{}")
    with tarfile.open(bad, "w:xz") as tar:
        tar.add(tmp_path / "x.json", arcname="../x.json")
    with pytest.raises(SystemExit, match="outside the sweep folder"):
        carry.unpack(bad, tmp_path / "out")
    with pytest.raises(SystemExit, match=r"ARCHIVE .* is not a file"):
        carry.main(["unpack", str(tmp_path / "missing.tar.xz"), str(tmp_path / "out")])
