"""Mesh export (gdbench.app.mesh) and its scores (gdbench.metrics.mesh_scores).

Oracles: concentric spheres (every nearest distance is the difference of the radii, every normal
parallel), flat Gaussians laid on a known surface (the fused mesh must be that surface, in its
colours), the glTF/OBJ files read back by trimesh with the rotation's closed form."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

trimesh = pytest.importorskip("trimesh")


def _sphere(radius: float, subdivisions: int = 5):
    return trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)


def _surface_gaussians(mesh, n: int = 20000, colour_fn=None, seed: int = 0):
    """Flat opaque Gaussians on ``mesh``'s surface, coloured by ``colour_fn(points)`` (grey by default)."""
    from gdbench.metrics.mesh_scores import surface_gaussians

    grey = lambda p: np.full((len(p), 3), 0.5)  # noqa: E731
    return surface_gaussians(mesh, n, colours=colour_fn or grey, seed=seed)


def test_chamfer_of_concentric_spheres_is_the_difference_of_their_radii():
    from gdbench.metrics.mesh_scores import mesh_scores

    a, b = _sphere(0.30), _sphere(0.33)
    s = mesh_scores(a, b, samples=4000)
    # no two points of the spheres are nearer than 0.33 - 0.30; samples 0.02 apart add at most 10%
    assert 0.0297 <= s.chamfer <= 0.033
    assert s.normal_consistency > 0.99
    same = mesh_scores(a, a, samples=4000)
    assert same.chamfer < 0.01 and same.normal_consistency > 0.98  # two samplings of one surface, 0.017 apart


def test_the_best_turn_is_found_with_the_view_metrics_sign():
    """An off-centre box turned by +40 degrees about +Z: found at 40 (the reference's point at
    azimuth a lies at a + 40 in the mesh), where the Chamfer distance drops to the sampling's."""
    from gdbench.metrics.mesh_scores import mesh_scores

    ref = trimesh.creation.box(extents=(0.4, 0.1, 0.2))
    ref.apply_translation((0.15, 0.0, 0.0))
    turned = ref.copy()
    turned.apply_transform(trimesh.transformations.rotation_matrix(math.radians(40), (0, 0, 1)))
    s = mesh_scores(turned, ref, samples=3000)
    assert s.turned_deg == pytest.approx(40.0)
    assert s.chamfer < 0.01 < s.chamfer_unturned


def test_fused_mesh_of_gaussians_on_a_sphere_is_that_sphere_in_its_colours():
    pytest.importorskip("open3d", reason="mesh export fuses depth with Open3D")
    from gdbench.app.mesh import extract_mesh
    from gdbench.metrics.mesh_scores import mesh_scores

    sphere = _sphere(0.3)

    def colours(p):  # red above the equator, blue below
        return np.where(p[:, 2:3] > 0, [[0.9, 0.1, 0.1]], [[0.1, 0.1, 0.9]])

    m = extract_mesh(_surface_gaussians(sphere, n=40000, colour_fn=colours), views=24, size=128, resolution=96)
    s = mesh_scores(m, sphere, samples=5000)
    # two samplings of one surface give ~0.006 at 5000 samples, a sphere 10% larger 0.03
    assert s.chamfer < 0.012 and s.normal_consistency > 0.95
    r = np.linalg.norm(m.vertices, axis=1)
    assert abs(float(np.median(r)) - 0.3) < 0.006
    c = np.asarray(m.visual.vertex_colors[:, :3], dtype=np.float64) / 255
    top, bottom = m.vertices[:, 2] > 0.05, m.vertices[:, 2] < -0.05
    np.testing.assert_allclose(c[top].mean(0), [0.9, 0.1, 0.1], atol=0.08)
    np.testing.assert_allclose(c[bottom].mean(0), [0.1, 0.1, 0.9], atol=0.08)


@pytest.mark.parametrize("suffix", [".glb", ".obj"])
def test_written_mesh_reads_back_rotated_to_its_up_axis_with_its_tags(tmp_path, suffix):
    from gdbench.app.mesh import write_mesh
    from gdbench.core.filetags import read_tags, up_rotation

    m = trimesh.creation.box(extents=(0.4, 0.2, 0.1))
    m.apply_translation((0.0, 0.0, 0.3))  # above the origin: +Z up
    m.visual.vertex_colors = np.tile([[200, 40, 10, 255]], (len(m.vertices), 1)).astype(np.uint8)
    path = write_mesh(m, tmp_path / f"box{suffix}", up="+y", run="0123456789abcdef")
    tags = read_tags(path)
    assert (tags.up, tags.run, tags.source) == ("+y", "0123456789abcdef", "header")
    back = trimesh.load(path, force="mesh", process=False)
    want = m.vertices @ up_rotation("+y").numpy().T
    got = np.asarray(back.vertices)
    assert got[:, 1].min() > 0.2  # above the origin along +Y, glTF's up
    d = np.linalg.norm(got[:, None, :] - want[None, :, :], axis=-1).min(1)
    assert d.max() < 1e-6  # every vertex where the rotation puts it
    assert (np.asarray(back.visual.vertex_colors)[:, :3] == [200, 40, 10]).all()
    with pytest.raises(ValueError, match=r"path: a mesh is written as \.glb or \.obj"):
        write_mesh(m, tmp_path / "box.stl")


def test_export_command_writes_a_mesh_beside_the_run(tmp_path):
    pytest.importorskip("open3d", reason="mesh export fuses depth with Open3D")
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export
    from gdbench.core.filetags import ply_comments, read_tags

    run = tmp_path / "run"
    run.mkdir()
    _surface_gaussians(_sphere(0.3), n=8000).save_ply(
        run / "scene.ply", comments=ply_comments("+z", "abcdef0123456789")
    )
    r = main(Export(run, format="glb", mesh_resolution=48))
    assert Path(r["path"]) == run / "scene.y_up.glb" and r["up"] == "+y"
    assert read_tags(r["path"]).run == "abcdef0123456789"
    with pytest.raises(ValueError, match=r"sh_degree \(--sh-degree\): --format obj writes vertex colours"):
        main(Export(run, format="obj", sh_degree=3))
