"""The CLI's main job (demo turntable) and the package's import cost."""

import json
import subprocess
import sys
from pathlib import Path

import imageio.v3 as iio
import numpy as np
import torch

from gdbench.builtin import demo_scene
from gdbench.camera import SphericalPoses
from gdbench.cli import Demo, main
from renderers.splat import rasterize


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


def _imports(package: Path) -> dict[str, set[str]]:
    """Every module of ``package`` and the package modules it imports, at the top or inside a
    function (a lazy import closes a circle too)."""
    import ast

    mods = {".".join(p.relative_to(package.parent).with_suffix("").parts).removesuffix(".__init__"): p
            for p in package.rglob("*.py")}  # fmt: skip
    edges = {}
    for name, path in mods.items():
        pkg = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        found = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom):
                base = ".".join(pkg.split(".")[: len(pkg.split(".")) - node.level + 1]) if node.level else ""
                mod = ".".join(x for x in (base, node.module) if x)
                found |= {m for m in [mod, *(f"{mod}.{a.name}" for a in node.names)] if m in mods}
            elif isinstance(node, ast.Import):
                found |= {a.name for a in node.names if a.name in mods}
        edges[name] = found - {name}
    return edges


def test_no_two_modules_import_each_other():
    """No import circle between two modules of the package (ply and scene, sweep and sweep_tables
    had one): each shared piece has one home. Checked on the source, lazy imports included; a
    module and its own package do not count."""
    edges = _imports(Path(__file__).resolve().parents[1] / "gdbench")
    assert len(edges) > 50 and "gdbench.ply" in edges["gdbench.scene"]  # the walk sees imports
    nested = lambda a, b: a.startswith(b + ".") or b.startswith(a + ".")  # noqa: E731
    circles = sorted(
        {tuple(sorted((a, b))) for a, bs in edges.items() for b in bs if a in edges[b] and not nested(a, b)}
    )
    assert sorted(circles) == []


def test_noise_preview_writes_figure_with_unit_variance(tmp_path, monkeypatch):
    from gdbench import plotting
    from gdbench.cli import Noise

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
    from gdbench.cli import Generate, Render
    from gdbench.scene import GaussianScene

    out = tmp_path / "duck"
    from gdbench.cli import GenerateTrain

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
    import pytest

    from gdbench.cli import Render

    with pytest.raises(FileNotFoundError, match="run: no PLY"):
        main(Render(tmp_path / "nothing"))


def _option_helps(command: str) -> dict[str, str]:
    """Each option of ``gdbench COMMAND --help`` with its help text (tyro's boxed layout)."""
    import os
    import re

    env = dict(os.environ, COLUMNS="100")  # one column (tyro lays out two at ~200)
    text = subprocess.run(
        [sys.executable, "-m", "gdbench.cli", command, "--help"], capture_output=True, text=True, check=True, env=env
    ).stdout
    helps: dict[str, str] = {}
    name = None
    for line in text.splitlines():
        body = line.strip().strip("│").rstrip()
        m = re.match(r"\s*(--[a-z0-9-]+)", body)
        if m:
            name = m.group(1)
            helps[name] = ""
        elif name and body.startswith("      "):
            helps[name] += " " + body.strip()
        else:
            name = None
    return helps


def test_every_option_says_what_it_does():
    """Each option's help says more than its own name and its default (a docstring placed under
    another field used to leave --front-bias with 'front bias' alone)."""
    import re

    for command in ("generate", "sweep"):
        helps = _option_helps(command)
        assert {"--steps", "--front-bias", "--densify-stop", "--noise-ou-beta"} <= set(helps)
        for name, text in helps.items():
            if name in ("--help",):
                continue
            own = set(name.strip("-").split("-")) | {"default", "none", "true", "false", "the"}
            words = set(re.findall(r"[a-z]+", text.lower())) - own
            assert len(words) >= 3, (command, name, text)
    assert "kappa" in _option_helps("generate")["--front-bias"]


def test_options_that_would_do_nothing_are_refused_naming_both(tmp_path):
    """An option that acts only under another setting is refused when that setting is off, with
    the option it needs named; nothing is written."""
    import pytest

    from gdbench.cli import Generate, GenerateTrain, MethodOptions

    cases = [
        (dict(method=MethodOptions(noise_ou_beta=0.2)), r"--noise-ou-beta acts only with --noise-redraw ou "
         r"\(this run: --noise-redraw run\)"),
        (dict(train=GenerateTrain(log_every=5), progress=False), r"--log-every acts only with the progress bar"),
        (dict(train=GenerateTrain(vgs_gamma=0.1), preset="sjc-gs"), r"--vgs-gamma acts only with --vgs True"),
        (dict(train=GenerateTrain(view_window_deg=30.0, view_prompting="none")), r"--view-window-deg acts only "
         r"with --view-prompting window"),
        (dict(method=MethodOptions(noise_redraw="step"), preset="gd-no-sn"), r"--noise-redraw acts only with "
         r"structured noise"),
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
