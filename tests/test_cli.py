"""The CLI's main job (demo turntable) and the package's import cost."""

import json
import subprocess
import sys

import imageio.v3 as iio
import numpy as np
import pytest
import torch

from gdbench.app.cli import main
from gdbench.app.cmd_tools import Demo
from gdbench.core.builtin import demo_scene
from gdbench.core.camera import SphericalPoses
from renderers.splat import rasterize
from tests._util import import_edges, option_helps


def test_demo_writes_turntable_that_matches_a_direct_render(tmp_path):
    cmd = Demo(out=tmp_path / "demo", frames=4, size=48, gaussians=400)
    summary = main(cmd)
    sheet = iio.imread(tmp_path / "demo" / "turntable_sheet.png")
    assert sheet.shape == (48, 4 * 48, 3)
    gif = iio.imread(tmp_path / "demo" / "turntable.gif")
    assert gif.shape[0] == 4
    assert (tmp_path / "demo" / "turntable.mp4").stat().st_size > 0
    # oracle: the first tile equals a direct render of the first orbit camera
    scene = demo_scene(400, seed=0)
    cams = SphericalPoses.orbit(4, radius=1.3, elevation=20.0, fovy=45.0).cameras(48, 48)
    out = rasterize(
        **scene.render_args(), viewmats=cams.viewmats[:1], Ks=cams.Ks[:1], width=48, height=48, background=torch.ones(3)
    )
    direct = (out.rgb[0].clamp(0, 1) * 255 + 0.5).to(torch.uint8).numpy()
    assert np.array_equal(sheet[:, :48], direct)
    assert direct.std() > 10  # not a blank frame
    s = json.loads((tmp_path / "demo" / "summary.json").read_text())
    assert s["frames"] == 4 and s["gaussians"] == 400 and s["median_frame_s"] > 0
    assert summary["outputs"]["ply"].endswith("scene.ply")


def test_import_is_cheap():
    code = (
        "import sys, gdbench, renderers.splat; "
        "heavy = [m for m in ('mitsuba', 'drjit', 'pyrender', 'pycolmap', 'open3d', 'diffusers', 'tyro', 'matplotlib', "
        "'scipy', 'imageio', 'gsplat') if m in sys.modules]; print(','.join(heavy))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


def test_no_two_modules_import_each_other():
    """No import circle between two modules of the package (ply and scene, sweep and sweep_tables
    had one): each shared piece has one home. Checked on the source, lazy imports included; a
    module and its own package do not count."""
    edges = import_edges("gdbench")
    assert len(edges) > 50 and "gdbench.core.ply" in edges["gdbench.core.scene"]  # the walk sees imports
    nested = lambda a, b: a.startswith(b + ".") or b.startswith(a + ".")  # noqa: E731
    circles = sorted(
        {tuple(sorted((a, b))) for a, bs in edges.items() for b in bs if a in edges[b] and not nested(a, b)}
    )
    assert sorted(circles) == []


def test_noise_preview_writes_figure_with_unit_variance(tmp_path, monkeypatch):
    from gdbench.app.cmd_tools import Noise
    from gdbench.core import plotting

    inside, real = [], plotting.save

    def save(fig, path, **kw):  # every title lies inside the figure once it is laid out
        fig.canvas.draw()
        frame = fig.bbox
        for text in [fig._suptitle] + [ax.title for ax in fig.axes]:
            box = text.get_window_extent()
            inside.append(frame.x0 <= box.x0 and box.x1 <= frame.x1 and frame.y0 <= box.y0 and box.y1 <= frame.y1)
        return real(fig, path, **kw)

    monkeypatch.setattr(plotting, "save", save)
    stats = main(Noise(preview=True, out=tmp_path / "p.png", res=48, n_gaussians=800, scale=0.04))
    assert len(inside) == 6 and all(inside), inside
    assert (tmp_path / "p.png").stat().st_size > 10_000
    assert 0.3 < stats["coverage"] <= 1.0
    assert abs(stats["var"] - 1.0) < 0.05 and abs(stats["mean"]) < 0.05
    assert stats["ks_statistic"] < 0.02


def test_generate_then_render(tmp_path):
    from gdbench.app.cmd_generate import Generate
    from gdbench.app.cmd_scenes import Render
    from gdbench.core.scene import GaussianScene

    out = tmp_path / "duck"
    from gdbench.app.cmd_generate import GenerateTrain

    s = main(
        Generate("A Yellow Duck", out=out, score=False, progress=False, train=GenerateTrain(steps=3, resolution=16))
    )
    assert s["steps"] == 3 and (out / "scene.ply").is_file() and (out / "run.json").is_file()
    scene = GaussianScene.load_ply(out / "scene.ply")
    assert len(scene) == s["gaussians"]
    r = main(Render(out, frames=3, size=32))
    sheet = iio.imread(r["sheet"])
    assert sheet.shape == (32, 96, 3) and sheet.std() > 1  # the grey initial sphere is visible
    again = main(
        Generate("A Yellow Duck", out=out, score=False, progress=False, train=GenerateTrain(steps=3, resolution=16))
    )
    assert again["resumed_from"] == 3  # finished run: resumes at its end, trains nothing


def test_render_bad_path(tmp_path):

    from gdbench.app.cmd_scenes import Render

    with pytest.raises(FileNotFoundError, match=r"run: no scene at .*nothing .pass a run folder, a .ply or a .splat"):
        main(Render(tmp_path / "nothing"))


def test_every_option_says_what_it_does():
    """Each option's help says more than its own name and its default (a docstring placed under
    another field used to leave --front-bias with 'front bias' alone)."""
    import re

    for command in ("generate", "sweep"):
        helps = option_helps(command)
        assert {"--steps", "--front-bias", "--densify-stop", "--noise-ou-beta"} <= set(helps)
        for name, text in helps.items():
            if name in ("--help",):
                continue
            own = set(name.strip("-").split("-")) | {"default", "none", "true", "false", "the"}
            words = set(re.findall(r"[a-z]+", text.lower())) - own
            assert len(words) >= 3, (command, name, text)
    assert "kappa" in option_helps("generate")["--front-bias"]


def test_options_that_would_do_nothing_are_refused_naming_both(tmp_path):
    """An option that acts only under another setting is refused when that setting is off, with
    the option it needs named; nothing is written."""

    from gdbench.app.cmd_generate import Generate, GenerateTrain

    cases = [
        (dict(train=GenerateTrain(noise_ou_beta=0.2)), r"--noise-ou-beta acts only with --noise-redraw ou "
         r"\(this run: --noise-redraw run\)"),
        (dict(train=GenerateTrain(log_every=5), progress=False), r"--log-every acts only with --progress "
         r"or --log-dir \(this run: --no-progress, no --log-dir\)"),
        (dict(train=GenerateTrain(vgs_gamma=0.1), preset="sjc-gs"), r"--vgs-gamma acts only with --vgs"),
        (dict(train=GenerateTrain(view_window_deg=30.0, view_prompting="none")), r"--view-window-deg acts only "
         r"with --view-prompting window"),
        (dict(train=GenerateTrain(noise_redraw="step"), preset="gd-no-sn"), r"--noise-redraw acts only with "
         r"--structured-noise \(this run: --no-structured-noise\)"),
    ]  # fmt: skip
    for kw, match in cases:
        with pytest.raises(ValueError, match=match):
            main(Generate("a yellow duck", out=tmp_path / "x", score=False, **kw))
        assert not (tmp_path / "x").exists()
    # the same options where they act are taken
    from gdbench.train.config import preset
    from gdbench.train.options import inert_options

    cfg = preset("gd", **{"noise.redraw": "ou", "noise.ou_beta": 0.2})
    assert inert_options(cfg, {"noise.redraw": "ou", "noise.ou_beta": 0.2}) == []


def test_field_docs_read_from_each_file_once_are_the_docs_of_each_class():
    """The help's field docs come from one parse per source file (``options._module_tree``); the
    oracle is the docstring under each field of the class's own source (``inspect.getsource``),
    for every class the CLI reads, and a nested class is found by its qualified name."""
    import ast
    import inspect
    import itertools

    from gdbench.app import cli
    from gdbench.train import options

    def oracle(cls):
        body = ast.parse(inspect.cleandoc("\n" + inspect.getsource(cls))).body[0].body
        pairs = itertools.pairwise(body)
        return {a.target.id: " ".join(b.value.value.split()) for a, b in pairs
                if isinstance(a, ast.AnnAssign) and isinstance(b, ast.Expr)
                and isinstance(getattr(b, "value", None), ast.Constant) and isinstance(b.value.value, str)}  # fmt: skip

    from gdbench.train.config import NESTED

    classes = [kind for kind, _ in cli.COMMANDS.values()] + [options.TrainConfig, *NESTED.values()]
    classes += [_Outer.Inner]
    for cls in classes:
        assert options._field_docs.__wrapped__(cls) == oracle(cls), cls
    assert options._field_docs(_Outer.Inner) == {"b": "the inner field"}
    assert sum(len(options._field_docs(c)) for c in classes) > 100  # not vacuous: 145 docs


class _Outer:
    a: int = 0
    """the outer field"""

    class Inner:
        b: int = 0
        """the inner field"""


def test_plain_progress_lines_in_a_log():
    """Piped to a file, progress is a line per tenth of the work or per ``every_s`` seconds, and
    one at the end, each with the count, the rate and the time left (a fake clock: one step per
    second)."""
    import io

    from gdbench.core.progress import PlainProgress

    t = [0.0]
    buf = io.StringIO()
    bar = PlainProgress(100, "gd 'a duck'", "step", every_s=1e9, file=buf, clock=lambda: t[0])
    for _ in range(100):
        t[0] += 1.0
        bar.update(1)
    bar.close()
    lines = buf.getvalue().splitlines()
    assert len(lines) == 10  # 10, 20, ..., 90 and the end
    assert lines[0] == "gd 'a duck': 10/100 step (10%), 10s elapsed, 1.00 step/s, 1m30s left"
    assert lines[-1] == "gd 'a duck': 100/100 step (100%), 1m40s elapsed, 1.00 step/s"
    buf2 = io.StringIO()  # by time: one line every 5 s of a 1000-step run
    bar = PlainProgress(1000, "x", every_s=5.0, file=buf2, clock=lambda: t[0])
    for _ in range(20):
        t[0] += 1.0
        bar.update(1)
    assert len(buf2.getvalue().splitlines()) == 4


def test_stage_lines_count_only_the_stages_that_run(capsys, monkeypatch):
    """A score's stages in a log: one line per stage that runs, numbered out of those that run
    (a reused block drops its stages from the count), and one at the end."""
    from gdbench.core.progress import Phases

    monkeypatch.setenv("GDBENCH_PROGRESS", "plain")
    t = [0.0]
    with Phases(5, "score", clock=lambda: t[0]) as ph:
        ph.total -= 1  # the ground-truth block was reused
        for name in ("COLMAP views", "COLMAP features", "COLMAP matching", "COLMAP mapping"):
            ph.start(name)
            t[0] += 30.0
    err = capsys.readouterr().err.splitlines()
    assert err == [
        "score: COLMAP views (1/4), 0s elapsed",
        "score: COLMAP features (2/4), 30s elapsed",
        "score: COLMAP matching (3/4), 1m00s elapsed",
        "score: COLMAP mapping (4/4), 1m30s elapsed",
        "score: done in 2m00s",
    ]
