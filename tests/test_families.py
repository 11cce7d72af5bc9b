"""The world's procedural objects (gdbench.assets.families): at least 30 named objects of at least
10 kinds, each fitted to the ball of radius 0.45, centred, with its marked front parts facing +X.

Oracles: the mesh's own vertices (fit, centring), and pyrender's views of the marked parts alone
(they show from the front and hide from the back: the front is where the caption says it is)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from gdbench.assets.families import COLOURS, KINDS, WORLD, WORLD_FRONTS, Spec
from tests._util import script


def test_the_default_set_is_at_least_30_objects_of_10_kinds_with_compositional_captions():
    assert len(WORLD) >= 30 and len({s.kind for s in WORLD.values()}) >= 10
    assert set(WORLD_FRONTS) == set(WORLD) and all(WORLD_FRONTS.values())
    for caption, spec in WORLD.items():
        words = caption.split()
        assert words[0] in ("a", "an") and words[1] in COLOURS and words[2] == spec.kind, caption
        if spec.hat or spec.scarf:
            assert words[3:5] == ["wearing", "a"] and words[5] == (spec.hat or spec.scarf), caption


@pytest.mark.parametrize("caption", sorted(WORLD))
def test_every_object_is_fitted_centred_and_shows_its_front_at_plus_x(caption):
    from gdbench.core.camera import SphericalPoses
    from renderers.pyrender_points.mesh import render_mesh

    mesh = WORLD[caption].build()
    v = np.asarray(mesh.vertices)
    assert np.linalg.norm(v, axis=1).max() == pytest.approx(0.45, abs=1e-9)  # combine's fit
    lo, hi = v.min(0), v.max(0)
    np.testing.assert_allclose((lo + hi) / 2, 0, atol=1e-9)
    marks = np.asarray(mesh.metadata["front"], bool)
    assert marks.any() and not marks.all()
    rgba = np.zeros((len(v), 4), np.uint8)
    rgba[:, 3] = 255
    rgba[marks, :3] = 255
    mesh.visual.vertex_colors = rgba
    az = torch.tensor([0.0, 180.0], dtype=torch.float64)
    poses = SphericalPoses(az, torch.full_like(az, 15.0), torch.ones_like(az), torch.full_like(az, 50.0))
    pose_gl, K = poses.cameras(64, 64).to_opengl()
    rgb, _, alpha = render_mesh(mesh, pose_gl.double().numpy(), K.double().numpy(), 64, 64,
                                background=(0, 0, 0), ambient=1.0, headlight=0.0)  # fmt: skip
    front, back = (rgb[..., 0] > 0.5).reshape(2, -1).sum(1)
    assert alpha[1].sum() > 100  # the back view is not empty
    assert front >= 20 and back <= 0.1 * front, (front, back)


def test_same_spec_same_mesh_and_bad_specs_are_refused():
    a, b = Spec("pig", "pink", hat="blue").build(), Spec("pig", "pink", hat="blue").build()
    assert np.array_equal(a.vertices, b.vertices) and np.array_equal(a.visual.vertex_colors, b.visual.vertex_colors)
    assert not np.array_equal(Spec("pig", "pink").build().vertices.shape, a.vertices.shape)  # the hat is there
    with pytest.raises(ValueError, match="kind: expected one of chick, owl"):
        Spec("dragon", "red")
    with pytest.raises(ValueError, match="colour: expected one of red, orange"):
        Spec("cat", "vermilion")
    with pytest.raises(ValueError, match="hat, scarf: one accessory per object"):
        Spec("cat", "red", hat="blue", scarf="green")
    assert set(KINDS) >= {"duck", "cat", "dog", "pig", "bear", "rabbit", "frog", "fish", "robot", "car", "teapot"}


def test_world_turntables_script_writes_a_sheet_per_family_and_the_table(tmp_path):
    """scripts/world_turntables.py on a two-cell sweep (a white duck and a blue duck, their sheets
    drawn here): one figure for the duck family, and a table whose rows are the cells' own values."""
    import csv

    import matplotlib.pyplot as plt

    from gdbench.experiments.sweep import cell_name

    mod = script("world_turntables")
    sweep = tmp_path / "sweep"
    fields = ["setting", "prompt", "preset", "seed", "gt_psnr", "gt_ssim", "multi_face_rate", "featureless_rate",
              "floaters", "turned_deg", "gaussians", "train_commit", "score_commit"]  # fmt: skip
    rows = [
        ["easy", "a white duck", "gd", "0", "22.36", "0.554", "0", "1", "0.006", "5", "2097", "abc", "abc"],
        ["easy", "a blue duck", "gd", "0", "28.27", "0.869", "0", "0", "0", "-25", "9504", "abc", "abc"],
    ]
    sweep.mkdir()
    with open(sweep / "cells.csv", "w", newline="") as f:
        w = csv.writer(f)
        w.writerow(fields)
        w.writerows(rows)
    for r in rows:
        folder = sweep / "cells" / "easy" / cell_name(r[1]) / "gd" / "seed0"
        folder.mkdir(parents=True)
        plt.imsave(folder / "turntable_sheet.png", np.full((20, 60, 3), 0.5 if "white" in r[1] else 0.2))
    assert mod.main(["--sweep", str(sweep), "--name", "t", "--figures", str(tmp_path / "f"), "--out",
                     str(tmp_path / "o")]) == 0  # fmt: skip
    assert [p.name for p in (tmp_path / "f").iterdir()] == ["world_turntables_t_duck.png"]
    text = (tmp_path / "o" / "text_to_3d_t.md").read_text()
    assert "| a white duck | 22.36 | 0.554 | 0.00 | 1.00 | 0.006 | 5 | 2097 |" in text
    assert "| a blue duck | 28.27 | 0.869 | 0.00 | 0.00 | 0.000 | -25 | 9504 |" in text and "abc" in text
    # --labels adds what a person saw as a last column, n/a for a caption left unlabelled
    labels = tmp_path / "eye.tsv"
    labels.write_text("caption\tby eye\na white duck\tfaint blob\n")
    assert mod.main(["--sweep", str(sweep), "--name", "t", "--figures", str(tmp_path / "f"), "--out",
                     str(tmp_path / "o"), "--labels", str(labels)]) == 0  # fmt: skip
    text = (tmp_path / "o" / "text_to_3d_t.md").read_text()
    assert "| Gaussians | by eye |" in text and "| 2097 | faint blob |" in text and "| 9504 | n/a |" in text
    with pytest.raises(SystemExit):
        mod.main(["--sweep", str(sweep), "--name", "t", "--labels", str(tmp_path / "missing.tsv")])
