"""GaussianScene (validation, transforms) and 3DGS PLY input/output."""

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from gdbench.core.scene import GaussianScene, sphere_init
from renderers.splat.sh import C0


def _scene(n=20, degree=1, seed=0, dtype=torch.float32):
    g = torch.Generator().manual_seed(seed)
    k = (degree + 1) ** 2
    return GaussianScene(
        torch.randn(n, 3, generator=g, dtype=dtype),
        torch.randn(n, 4, generator=g, dtype=dtype),
        torch.randn(n, 3, generator=g, dtype=dtype),
        torch.randn(n, generator=g, dtype=dtype),
        torch.randn(n, k, 3, generator=g, dtype=dtype),
    )


def _fields(s):
    return [s.means, s.quats, s.log_scales, s.opacity_logits, s.sh]


@pytest.mark.parametrize(
    ("field", "value", "match"),
    [
        ("quats", torch.zeros(20, 3), r"GaussianScene.quats: expected shape \[20, 4\], got \[20, 3\]"),
        ("means", torch.zeros(20, 2), r"GaussianScene.means: expected shape \[N, 3\]"),
        ("sh", torch.zeros(20, 5, 3), r"GaussianScene.sh: expected shape \[20, K, 3\] with K in"),
        ("opacity_logits", torch.zeros(19), r"GaussianScene.opacity_logits: expected shape \[20\]"),
        ("log_scales", torch.full((20, 3), float("nan")), "GaussianScene.log_scales: expected finite"),
        ("means", torch.zeros(20, 3, dtype=torch.int64), "GaussianScene.means: expected dtype"),
        ("sh", torch.zeros(20, 4, 3, dtype=torch.float64), "GaussianScene.sh: expected torch.float32"),
        ("quats", np.zeros((20, 4)), "GaussianScene.quats: expected a torch.Tensor"),
    ],
)
def test_validation_names_the_field(field, value, match):
    s = _scene()
    kw = {f: getattr(s, f) for f in ("means", "quats", "log_scales", "opacity_logits", "sh")}
    kw[field] = value
    with pytest.raises((ValueError, TypeError), match=match):
        GaussianScene(**kw)


def test_activations_and_render_args():
    s = _scene()
    torch.testing.assert_close(s.scales, torch.exp(s.log_scales))
    torch.testing.assert_close(s.opacities, torch.sigmoid(s.opacity_logits))
    torch.testing.assert_close(s.colors, s.sh[:, 0] * C0 + 0.5)
    args = s.render_args()
    assert args["sh_degree"] == 1 and args["colors"] is s.sh
    rgb = torch.rand(5, 3)
    t = GaussianScene.from_activated(torch.zeros(5, 3), torch.full((5, 3), 0.1), torch.full((5,), 0.3), rgb)
    torch.testing.assert_close(t.colors, rgb)
    torch.testing.assert_close(t.opacities, torch.full((5,), 0.3))


def test_subset_cat_detach_to():
    a, b = _scene(10, degree=0, seed=1), _scene(7, degree=2, seed=2)
    c = GaussianScene.cat([a, b])
    assert len(c) == 17 and c.sh_degree == 2
    torch.testing.assert_close(c.sh[:10, 1:], torch.zeros(10, 8, 3))  # padded bands
    torch.testing.assert_close(c.subset(torch.arange(10, 17)).means, b.means)
    mask = torch.zeros(17, dtype=torch.bool)
    mask[3] = True
    assert len(c.subset(mask)) == 1
    with pytest.raises(ValueError, match="index: expected a boolean mask"):
        c.subset(torch.ones(3, dtype=torch.bool))
    p = _scene()
    p = GaussianScene(*(x.requires_grad_(True) for x in _fields(p)))
    assert not any(x.requires_grad for x in _fields(p.detach()))
    d = p.detach().to(torch.float64)
    assert d.means.dtype == torch.float64 and d.sh.dtype == torch.float64
    assert p.with_sh_degree(0).sh.shape == (20, 1, 3) and p.with_sh_degree(3).sh.shape == (20, 16, 3)


def test_sphere_init_paper_defaults():
    s = sphere_init(4096, generator=torch.Generator().manual_seed(0))
    assert len(s) == 4096 and float(s.means.norm(dim=-1).max()) <= 0.5
    torch.testing.assert_close(s.opacities, torch.full((4096,), 0.1))
    torch.testing.assert_close(s.colors, torch.full((4096, 3), 0.5))
    # uniform in the ball: the fraction inside radius 0.25 is (1/2)^3
    inside = float((s.means.norm(dim=-1) < 0.25).float().mean())
    assert abs(inside - 0.125) < 4 * (0.125 * 0.875 / 4096) ** 0.5


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_ply_round_trip_is_exact(tmp_path, degree):
    s = _scene(33, degree=degree)
    path = s.save_ply(tmp_path / "s.ply")
    r = GaussianScene.load_ply(path)
    for a, b in zip(_fields(s), _fields(r)):
        assert torch.equal(a, b)


def test_ply_layout_is_the_inria_one(tmp_path):
    from plyfile import PlyData

    s = _scene(4, degree=1)
    s.save_ply(tmp_path / "s.ply")
    v = PlyData.read(str(tmp_path / "s.ply"))["vertex"].data
    names = list(v.dtype.names)
    assert names[:9] == ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
    assert names[-8:] == ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    # f_rest is channel-major: f_rest_0..2 are the red coefficients of bands 1, f_rest_3.. green
    assert float(v["f_rest_1"][2]) == float(s.sh[2, 2, 0]) and float(v["f_rest_3"][2]) == float(s.sh[2, 1, 1])
    assert float(v["opacity"][1]) == float(s.opacity_logits[1]) and float(v["scale_2"][0]) == float(s.log_scales[0, 2])


@pytest.mark.parametrize(
    ("content", "match"),
    [
        (b"not a ply at all\n", "not a readable PLY"),
        (b"ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n", "no 'vertex'"),
        (
            b"ply\nformat ascii 1.0\nelement vertex 1\nproperty float x\nproperty float y\nproperty float z\n"
            b"end_header\n0 0 0\n",
            "missing vertex properties",
        ),
    ],
)
def test_malformed_ply(tmp_path, content, match):
    p = tmp_path / "bad.ply"
    p.write_bytes(content)
    with pytest.raises(ValueError, match=match):
        GaussianScene.load_ply(p)


def test_truncated_ply(tmp_path):
    path = _scene(50, degree=2).save_ply(tmp_path / "s.ply")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) - 100])
    with pytest.raises(ValueError, match="not a readable PLY"):
        GaussianScene.load_ply(path)
    with pytest.raises(FileNotFoundError, match="no PLY file"):
        GaussianScene.load_ply(tmp_path / "missing.ply")


def test_header_count_and_trailing_bytes_are_checked(tmp_path):
    """A header that declares fewer vertices than the file holds, or bytes after the last vertex,
    used to drop vertices silently."""
    path = _scene(30, degree=1).save_ply(tmp_path / "s.ply")
    data = path.read_bytes()
    (tmp_path / "short.ply").write_bytes(data.replace(b"element vertex 30", b"element vertex 29"))
    with pytest.raises(ValueError, match=r"short.ply: \d+ bytes follow the 29 vertex rows the header declares \(1 v"):
        GaussianScene.load_ply(tmp_path / "short.ply")
    commented = _scene(30, degree=1).save_ply(tmp_path / "c.ply", comments=["see end_header below"])
    assert len(GaussianScene.load_ply(commented)) == 30  # end_header is a line of its own, not a word
    (tmp_path / "tail.ply").write_bytes(data + b"junk")
    with pytest.raises(ValueError, match=r"tail.ply: 4 bytes follow the 30 vertex rows"):
        GaussianScene.load_ply(tmp_path / "tail.ply")
    from plyfile import PlyData

    text = PlyData.read(str(path))
    text.text = True
    text.write(str(tmp_path / "text.ply"))
    assert len(GaussianScene.load_ply(tmp_path / "text.ply")) == 30  # ASCII: rows counted too
    lines = (tmp_path / "text.ply").read_bytes().replace(b"element vertex 30", b"element vertex 28")
    (tmp_path / "text_short.ply").write_bytes(lines)
    with pytest.raises(ValueError, match=r"declares 28 rows \(28 vertex\) but the file has 30 rows"):
        GaussianScene.load_ply(tmp_path / "text_short.ply")


def _ply_bytes(scene, tmp, *, faces: int, comment_bytes: int, text: bool) -> bytes:
    """A 3DGS PLY of ``scene``, optionally with a face element after the vertices and a header
    padded with comments (the vertex rows ours, the file written by plyfile)."""
    import io

    from plyfile import PlyData, PlyElement

    vertices = PlyData.read(str(scene.save_ply(tmp / "base.ply")))["vertex"].data
    els = [PlyElement.describe(vertices, "vertex")]
    if faces:
        f = np.empty(faces, dtype=[("vertex_indices", "O")])
        f["vertex_indices"] = [np.arange(k % 3 + 3, dtype=np.int32) for k in range(faces)]
        els.append(PlyElement.describe(f, "face"))
    comments = ["x" * 1000] * (comment_bytes // 1000)
    buf = io.BytesIO()
    PlyData(els, text=text, comments=comments).write(buf)
    return buf.getvalue()


@settings(max_examples=40, deadline=None, derandomize=True, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    n=st.integers(1, 12),
    faces=st.sampled_from([0, 0, 3]),
    comment_bytes=st.sampled_from([0, 70_000]),
    text=st.booleans(),
    change=st.sampled_from(["none", "count", "tail", "cut"]),
    delta=st.sampled_from([-2, -1, 1, 2]),
    tail=st.sampled_from([b"\x00", b"junk", b"\x00" * 59]),
    cut=st.sampled_from([1, 7]),
)
def test_any_ply_loads_exactly_or_is_refused_naming_the_file(
    tmp_path, n, faces, comment_bytes, text, change, delta, tail, cut
):
    """PLY headers and bodies by property: vertices alone or followed by faces, headers over
    64 KiB, binary or ASCII, and one change: a vertex count off by delta, trailing bytes, or a
    truncated end (ASCII: the last newline only, since a cut inside the last number can leave a
    valid shorter number). The file loads to exactly the scene written when nothing changed,
    and is refused with one ValueError naming the file when something did; never another
    exception, never a different scene."""
    delta, tail, cut = (
        (delta if change == "count" else 0),
        (tail if change == "tail" else b""),
        ((1 if text else cut) if change == "cut" else 0),
    )
    scene = _scene(n, degree=0)
    data = _ply_bytes(scene, tmp_path, faces=faces, comment_bytes=comment_bytes, text=text)
    original = data
    if delta:
        data = data.replace(f"element vertex {n}\n".encode(), f"element vertex {n + delta}\n".encode(), 1)
    data = data[: len(data) - cut] + tail
    path = tmp_path / f"p{n}_{faces}_{comment_bytes}_{int(text)}_{delta}_{len(tail)}_{cut}.ply"
    path.write_bytes(data)
    # ASCII: whitespace at the end (the last newline cut, say) changes nothing
    changed = delta != 0 or (data.rstrip() != original.rstrip() if text else data != original)
    try:
        loaded = GaussianScene.load_ply(path)
    except ValueError as e:
        assert str(path) in str(e), e
        assert changed, f"an unchanged file was refused: {e}"
        return
    assert not changed, f"a changed file loaded (delta {delta}, tail {tail!r}, cut {cut})"
    for k in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(loaded, k), getattr(scene, k)), k


@pytest.mark.parametrize(("value", "ok"), [(12.0, True), (-30.0, True), (12.5, False), (100.0, False), (-31.0, False)])
def test_log_scale_range_is_checked_on_read(tmp_path, value, ok):
    """Log-scales above 12 lose float32 precision and above ~43 vanish (docs/reliability.md)."""
    from gdbench.core.ply import LOG_SCALE_RANGE

    assert LOG_SCALE_RANGE == (-30.0, 12.0)
    s = _scene(12, degree=0)
    s.log_scales[5, 0] = value
    path = s.save_ply(tmp_path / "s.ply")
    if ok:
        assert float(GaussianScene.load_ply(path).log_scales[5, 0]) == value
    else:
        with pytest.raises(ValueError, match=rf"s.ply: scale_0 of vertex 5 is {value:g} \(a log-scale\)"):
            GaussianScene.load_ply(path)


def test_reads_and_is_read_by_open3d(tmp_path):
    o3d = pytest.importorskip("open3d", reason="open3d-cpu is installed by `make setup`")
    o3c = o3d.core
    g = np.random.default_rng(0)
    n = 9
    arrays = {
        "positions": g.normal(size=(n, 3)),
        "scale": g.uniform(0.01, 1.0, size=(n, 3)),
        "rot": g.normal(size=(n, 4)),
        "opacity": g.normal(size=(n, 1)),
        "f_dc": g.normal(size=(n, 3)),
        "f_rest": g.normal(size=(n, 15, 3)),
    }
    pc = o3d.t.geometry.PointCloud()
    for k, a in arrays.items():
        pc.point[k] = o3c.Tensor(a.astype(np.float32))
    assert o3d.t.io.write_point_cloud(str(tmp_path / "o3d.ply"), pc)
    s = GaussianScene.load_ply(tmp_path / "o3d.ply")
    f32 = lambda a: torch.from_numpy(a.astype(np.float32))  # noqa: E731
    assert torch.equal(s.means, f32(arrays["positions"]))
    assert torch.equal(s.sh[:, 0], f32(arrays["f_dc"]))
    assert torch.equal(s.sh[:, 1:], f32(arrays["f_rest"]))
    assert torch.equal(s.quats, f32(arrays["rot"]))
    # Open3D holds linear scales in memory and writes their log, as the 3DGS layout wants
    torch.testing.assert_close(s.log_scales, torch.log(f32(arrays["scale"])))
    assert torch.equal(s.opacity_logits, f32(arrays["opacity"][:, 0]))
    # and Open3D reads ours
    s.save_ply(tmp_path / "ours.ply")
    back = o3d.t.io.read_point_cloud(str(tmp_path / "ours.ply"))
    np.testing.assert_array_equal(back.point["f_rest"].numpy(), arrays["f_rest"].astype(np.float32))
    np.testing.assert_array_equal(back.point["opacity"].numpy()[:, 0], arrays["opacity"][:, 0].astype(np.float32))
