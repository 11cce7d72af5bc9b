"""One up axis wherever a file goes (gdbench.core.filetags): every scene file gdbench writes records
its up axis and run, every command that reads one reads them back, the same axes are accepted
everywhere, a disagreeing axis is refused, and an overwrite removes what was made from the run.

Oracles: the scene itself (a float32 PLY round-trips exactly; a .splat within its quantisation),
the rotation's closed form, and files named by hand."""

from __future__ import annotations

import json
import typing
from pathlib import Path

import numpy as np
import pytest
import torch

from gdbench.app.export import export_scene, load_scene
from gdbench.core.filetags import UP_AXES, read_tags, resolve_up, sidecar, up_rotation
from gdbench.core.scene import GaussianScene


def _scene(n: int = 120, seed: int = 0) -> GaussianScene:
    from gdbench.core.builtin import demo_scene

    return demo_scene(n, seed=seed)


def _run_folder(tmp_path: Path, rid: str = "0123456789abcdef") -> Path:
    """A run folder as ``generate`` leaves it: scene.ply with its header comments, and a run.json."""
    from gdbench.core.filetags import ply_comments
    from gdbench.core.io import sha256_file, write_json

    run = tmp_path / "run"
    run.mkdir()
    _scene().save_ply(run / "scene.ply", comments=ply_comments("+z", rid))
    write_json({"run_id": rid, "config": {"seed": 0}, "scene_sha256": sha256_file(run / "scene.ply")}, run / "run.json")
    return run


@pytest.mark.parametrize("up", UP_AXES)
def test_every_axis_is_a_proper_rotation_taking_z_to_it(up):
    r = up_rotation(up)
    torch.testing.assert_close(r @ r.T, torch.eye(3, dtype=torch.float64))
    assert float(torch.linalg.det(r)) == pytest.approx(1.0)
    axis = {"x": 0, "y": 1, "z": 2}[up[1]]
    want = torch.zeros(3, dtype=torch.float64)
    want[axis] = 1.0 if up[0] == "+" else -1.0
    torch.testing.assert_close(r[:, 2], want)
    if up[1] != "x":  # about +X: an asset's front (+X) stays +X
        torch.testing.assert_close(r[:, 0], torch.tensor([1.0, 0, 0], dtype=torch.float64))


@pytest.mark.parametrize("fmt,name", [("ply", "s.ply"), ("ply-compressed", "s.compressed.ply"), ("splat", "s.splat")])
def test_every_written_file_records_its_axis_and_run_and_reads_back_upright(tmp_path, fmt, name):
    s = _scene()
    path = export_scene(s, tmp_path / name, fmt=fmt, up="-y", run="feedbeef01234567")
    tags = read_tags(path)
    assert (tags.up, tags.run) == ("-y", "feedbeef01234567")
    assert tags.source == ("sidecar" if fmt == "splat" else "header")
    if fmt == "splat":
        assert json.loads(sidecar(path).read_text()) == {"gdbench": {"up": "-y", "run": "feedbeef01234567"}}
    back = load_scene(path)  # no axis given: the recorded one, turned back to +Z
    raw = load_scene(path, up="-y")
    torch.testing.assert_close(back.means, raw.means)
    if fmt == "ply":  # float32: exactly, in order
        torch.testing.assert_close(back.means, s.means, atol=1e-6, rtol=0)
    else:  # reordered (Morton, or by size); each mean within the format's quantisation of one of the scene's
        d = torch.cdist(back.means.double(), s.means.double()).amin(1)
        assert float(d.max()) < 3e-3
    upside = s.means.double() @ up_rotation("-y").T  # and not the file's -Y-up coordinates
    assert float(torch.cdist(back.means.double(), upside).amin(1).max()) > 1e-2


def test_an_axis_that_disagrees_with_the_file_is_refused_naming_the_flag(tmp_path):
    path = export_scene(_scene(), tmp_path / "s.splat", fmt="splat", up="-y")
    want = r"src_up \(--src-up\): .*s\.splat records up axis -y \(its sidecar s\.splat\.json\)"
    with pytest.raises(ValueError, match=want):
        resolve_up(path, "+z", "--src-up")
    assert resolve_up(path, "-y") == "-y" and resolve_up(path, None) == "-y"
    sidecar(path).unlink()  # a copy without its sidecar: no axis but the default +z ...
    assert resolve_up(path, None) == "+z"
    named = path.rename(tmp_path / "scene.y_down.splat")  # ... unless its name is an export's
    assert read_tags(named).source == "name" and resolve_up(named, None) == "-y"
    with pytest.raises(ValueError, match=r"records up axis -y \(its name\)"):
        resolve_up(named, "+y")


def test_a_runs_scene_from_before_the_up_comment_is_z_up(tmp_path):
    _scene().save_ply(tmp_path / "scene.ply", comments=["gdbench run 0123456789abcdef"])
    assert read_tags(tmp_path / "scene.ply") == read_tags(tmp_path / "scene.ply").__class__(
        "+z", "0123456789abcdef", "header"
    )
    _scene().save_ply(tmp_path / "other.ply")  # from elsewhere: nothing recorded
    assert read_tags(tmp_path / "other.ply").up is None


def test_every_command_accepts_the_same_axes():
    from gdbench.app.cmd_scenes import Export, Render, View

    def choices(cls, field):
        hint = typing.get_type_hints(cls)[field]
        return {a for arg in typing.get_args(hint) for a in (typing.get_args(arg) or (arg,)) if a is not type(None)}

    want = set(UP_AXES)
    assert choices(Render, "up") == choices(View, "up") == choices(Export, "up") == choices(Export, "src_up") == want


def test_export_of_an_export_converts_once_and_render_reads_it_upright(tmp_path, capsys):
    """The issue's case: `export scene.y_down.splat --up +z` wrote the -Y-up scene again (rotated
    twice). Now the source's recorded axis is used: the result is the +Z-up scene, named z_up."""
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export, Render

    run = _run_folder(tmp_path)
    original = GaussianScene.load_ply(run / "scene.ply")
    y = main(Export(run, format="ply"))  # -y by default
    assert y["run"] == "0123456789abcdef" and read_tags(y["path"]).run == "0123456789abcdef"
    z = main(Export(Path(y["path"]), format="ply", up="+z"))
    assert Path(z["path"]) == run / "scene.z_up.ply"  # the axis in the name is replaced, not stacked
    back = GaussianScene.load_ply(z["path"])  # raw: +Z up as written
    torch.testing.assert_close(back.means, original.means, atol=1e-6, rtol=0)
    assert read_tags(z["path"]).run == "0123456789abcdef"  # the run travels with every conversion
    with pytest.raises(ValueError, match=r"src_up \(--src-up\): .* records up axis -y"):
        main(Export(Path(y["path"]), format="splat", up="+z", src_up="+z"))
    # render reads the axis: the exported file gives the run's own turntable
    a = main(Render(run, frames=2, size=24, radius=1.3, out=tmp_path / "a"))
    b = main(Render(Path(y["path"]), frames=2, size=24, radius=1.3, out=tmp_path / "b"))
    from PIL import Image

    ia = np.asarray(Image.open(a["sheet"]), dtype=np.float64)
    ib = np.asarray(Image.open(b["sheet"]), dtype=np.float64)
    assert ia.std() > 10 and np.abs(ia - ib).max() <= 2  # the same images (8-bit rounding)
    with pytest.raises(ValueError, match=r"up \(--up\): .* records up axis -y"):
        main(Render(Path(y["path"]), frames=2, size=24, out=tmp_path / "c", up="+z"))


def test_export_names_the_sh_degree_and_warns_when_a_compressed_file_is_padded(tmp_path, capsys):
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export

    run = _run_folder(tmp_path)  # SH degree 0
    plain = main(Export(run, format="ply"))
    padded = main(Export(run, format="ply", sh_degree=3))
    assert Path(plain["path"]).name == "scene.y_down.ply" and Path(padded["path"]).name == "scene.y_down.sh3.ply"
    assert GaussianScene.load_ply(plain["path"]).sh_degree == 0  # the degree-0 file is left as it was
    capsys.readouterr()
    main(Export(run, format="ply-compressed", sh_degree=2))
    out = capsys.readouterr().out
    assert "warning: SH degree 0 padded to 2 with zeros" in out and "0.0157" in out
    main(Export(run, format="ply-compressed"))
    assert "warning" not in capsys.readouterr().out


def test_init_from_an_exported_ply_turns_its_points_upright(tmp_path):
    pytest.importorskip("open3d", reason="init='ply' reads point clouds with Open3D")
    from gdbench.train.init import from_ply_points

    s = _scene(200)
    path = export_scene(s, tmp_path / "s.ply", fmt="ply", up="-y")
    g = torch.Generator().manual_seed(0)
    init = from_ply_points(path, 200, 0.5, generator=g)
    # every initial mean is one of the scene's points (+Z up), none a -Y-up one
    d = torch.cdist(init.means.double(), s.means.double()).amin(1)
    assert float(d.max()) < 1e-5
    rotated = s.means.double() @ up_rotation("-y").T
    assert float(torch.cdist(init.means.double(), rotated).amin(1).max()) > 1e-2


def test_overwrite_removes_what_was_made_from_the_old_run_and_nothing_else(tmp_path):
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export, Render
    from gdbench.train.run import files_of_run

    run = _run_folder(tmp_path)
    made = [Path(main(Export(run, format=f))["path"]) for f in ("ply", "splat", "ply-compressed")]
    made.append(sidecar(made[1]))
    sheet = Path(main(Render(made[1], frames=2, size=16))["sheet"])
    legacy = run / "scene.y_up.splat"  # an export from before exports recorded their run
    legacy.write_bytes(made[1].read_bytes())
    others = [
        run / "notes.txt",
        run / "mine.ply",
        run / "old_scene_backup.ply",
        run / "scene.y_down_turntable_todo.txt",
    ]
    others[0].write_text("keep")
    export_scene(_scene(), others[1], fmt="ply", run="ffffffffffffffff")  # another run's export
    export_scene(_scene(), others[2], fmt="ply", run="0123456789abcdef")  # this run's, under the user's name
    others[3].write_text("keep: not a name render writes")
    inria = Path(main(Export(run, format="inria"))["path"])  # a folder, recording the run in its PLY
    made.append(inria)
    found = set(files_of_run(run, "0123456789abcdef"))
    turntable = {sheet, run / "scene.y_down_turntable.gif"} | set(run.glob("scene.y_down_turntable.mp4"))
    assert found == {*made, *turntable, legacy}
    from gdbench.train.run import _check_finished

    _check_finished(run, None, overwrite=True, resume=False)
    assert sorted(p.name for p in run.iterdir() if not p.name.startswith(".")) == sorted(p.name for p in others)


def test_the_viewer_reads_the_axis_too(tmp_path):
    from gdbench.app.viewer import resolve_inputs

    s = _scene()
    path = export_scene(s, tmp_path / "s.ply", fmt="ply", up="+y")
    scene, name, run = resolve_inputs(path, None)
    torch.testing.assert_close(scene.means, s.means, atol=1e-6, rtol=0)  # turned back to +Z up
    assert run is None and name == str(path)
    with pytest.raises(ValueError, match=r"up \(--up\): .* records up axis \+y"):
        resolve_inputs(path, None, "-y")


def test_export_refuses_bad_out_names_before_any_work(tmp_path, monkeypatch):
    from gdbench.app import mesh as mesh_mod
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export

    run = _run_folder(tmp_path)
    monkeypatch.setattr(mesh_mod, "extract_mesh", lambda *a, **k: pytest.fail("meshed before --out was checked"))
    (tmp_path / "a_file").write_text("x")
    with pytest.raises(ValueError, match=r"out \(--out\): .*a_file is a file"):
        main(Export(run, format="glb", out=tmp_path / "a_file" / "x.glb"))
    (tmp_path / "d.obj").mkdir()
    with pytest.raises(ValueError, match=r"out \(--out\): .*d\.obj is a folder"):
        main(Export(run, format="obj", out=tmp_path / "d.obj"))
    (tmp_path / "copy.ply").write_bytes((run / "scene.ply").read_bytes())
    with pytest.raises(ValueError, match=r"out \(--out\): .*scene\.ply is one of the run's own outputs"):
        main(Export(tmp_path / "copy.ply", format="ply", up="+z", out=run / "scene.ply"))
    with pytest.raises(ValueError, match=r"out \(--out\): x\.compressed\.ply names a compressed PLY"):
        main(Export(run, format="ply", out=tmp_path / "x.compressed.ply"))


def test_an_unknown_recorded_axis_is_refused_not_read_as_z(tmp_path):
    path = export_scene(_scene(), tmp_path / "s.splat", fmt="splat", up="-y")
    sidecar(path).write_text(json.dumps({"gdbench": {"up": "+w", "run": None}}))
    with pytest.raises(ValueError, match=r"s\.splat\.json: its gdbench tags name up axis '\+w'"):
        load_scene(path)


def test_the_command_line_names_a_bad_axis_in_one_line():
    import subprocess
    import sys

    r = subprocess.run(
        [sys.executable, "-m", "gdbench.app.cli", "render", "nowhere", "--up", "+q"], capture_output=True, text=True
    )
    assert r.returncode == 2 and r.stderr.strip() == (
        "gdbench render: error: --up: unknown axis '+q'; expected one of +z, -y, +y, -z, +x, -x"
    )
