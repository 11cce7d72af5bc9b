"""gdbench.app.export: every format read back within its quantisation, checked once per format by a
reader written here (plyfile as the Inria loader uses it; a numpy struct for .splat; plyfile and
bit arithmetic for the compressed PLY), byte-compared with gsplat 1.5.3's exporter, and the up-axis
rotation checked by rendering.

Quantisation bounds (per component):
- ply: exact for a float32 scene.
- .splat: position exact; scale float32 of exp (relative 1e-6); colour and opacity truncated
  to 1/255 (decoded <= original < decoded + 1/255); rotation of the unit quaternion truncated to
  1/128 (same one-sided bound).
- compressed PLY: position and log-scale half a step of their chunk's range (range / 2047 / 2 for
  x and z, / 1023 / 2 for y); colour range / 255 / 2; opacity 1/255 / 2; the three smaller
  quaternion components sqrt(2) / 1023 / 2, the largest (from the unit norm) ~3e-3; SH bands
  1/64 (bins of 1/32 read at their middle), but < 1/32 for values in [0, 1/32), read as 0 so that
  zeros stay zero.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from gdbench.app import export
from gdbench.app.export import export_scene, load_scene, rotate_scene, up_rotation
from gdbench.core.scene import GaussianScene, sphere_init
from renderers.splat import rasterize
from renderers.splat.project import quat_to_rotmat
from renderers.splat.sh import C0, eval_sh, rgb_to_sh0
from tests._util import ring_cameras

W = H = 32


def _scene(n: int = 300, degree: int = 3, seed: int = 0) -> GaussianScene:
    """Random Gaussians: colours in (0.05, 0.95), opacities in (0.05, 0.95) (no clipping in any
    format, none below gsplat's 1/255 cut), SH bands well inside (-4, 4)."""
    g = torch.Generator().manual_seed(seed)
    u = lambda *shape: torch.rand(*shape, generator=g)  # noqa: E731
    sh = torch.randn(n, (degree + 1) ** 2, 3, generator=g) * 0.3
    sh[:, 0] = rgb_to_sh0(0.05 + 0.9 * u(n, 3))
    return GaussianScene(
        torch.randn(n, 3, generator=g) * 0.25,
        torch.randn(n, 4, generator=g),
        torch.log(0.01 + 0.05 * u(n, 3)),
        torch.logit(0.05 + 0.9 * u(n)),
        sh,
    )


def _render(scene: GaussianScene, viewmats: torch.Tensor, Ks: torch.Tensor) -> torch.Tensor:
    with torch.no_grad():
        out = rasterize(**scene.render_args(), viewmats=viewmats, Ks=Ks, width=W, height=H, backend="torch")
    return out.rgb


def _assert_image_close(img: torch.Tensor, ref: torch.Tensor, max_err: float, mean_err: float) -> None:
    """Images of a quantised scene: a few pixels may move by up to ``max_err`` (a Gaussian's
    quantised rotation or position at its edge), the mean by ``mean_err`` (measured: docs/export.md)."""
    d = (img - ref).abs()
    assert float(d.max()) <= max_err and float(d.mean()) <= mean_err, (float(d.max()), float(d.mean()))


def _cams():
    c = ring_cameras(3, W, H, radius=1.2)
    return c.viewmats, c.Ks


def _rotated_viewmats(viewmats: torch.Tensor, r: torch.Tensor) -> torch.Tensor:
    """Cameras seeing the world rotated by r as the originals saw the original: V diag(R^T, 1)."""
    m = torch.eye(4, dtype=viewmats.dtype)
    m[:3, :3] = r.T.to(viewmats.dtype)
    return viewmats @ m


def _nearest(decoded: np.ndarray, original: np.ndarray) -> np.ndarray:
    """For each decoded mean the index of the nearest original; asserts a one-to-one match."""
    d = torch.cdist(torch.from_numpy(decoded).double(), torch.from_numpy(original).double())
    idx = d.argmin(1).numpy()
    assert len(set(idx.tolist())) == len(original)
    return idx


# ----------------------------------------------------------------------------- ply
def _inria_read(path, max_sh_degree: int = 3) -> dict[str, np.ndarray]:
    """The reading half of the Inria code's GaussianModel.load_ply (plyfile), at degree 3."""
    from plyfile import PlyData

    el = PlyData.read(str(path)).elements[0]
    xyz = np.stack((np.asarray(el["x"]), np.asarray(el["y"]), np.asarray(el["z"])), axis=1)
    opacities = np.asarray(el["opacity"])[..., np.newaxis]
    features_dc = np.zeros((xyz.shape[0], 3, 1))
    for i in range(3):
        features_dc[:, i, 0] = np.asarray(el[f"f_dc_{i}"])
    extra = sorted((p.name for p in el.properties if p.name.startswith("f_rest_")), key=lambda x: int(x.split("_")[-1]))
    assert len(extra) == 3 * (max_sh_degree + 1) ** 2 - 3  # the Inria loader's own assertion
    features_extra = np.zeros((xyz.shape[0], len(extra)))
    for i, name in enumerate(extra):
        features_extra[:, i] = np.asarray(el[name])
    features_extra = features_extra.reshape((xyz.shape[0], 3, (max_sh_degree + 1) ** 2 - 1))

    def names(prefix: str) -> list[str]:
        return sorted((p.name for p in el.properties if p.name.startswith(prefix)), key=lambda x: int(x.split("_")[-1]))

    scales = np.stack([np.asarray(el[n]) for n in names("scale_")], axis=1)
    rots = np.stack([np.asarray(el[n]) for n in names("rot")], axis=1)
    return {"xyz": xyz, "dc": features_dc[:, :, 0], "rest": features_extra, "opacity": opacities[:, 0],
            "scale": scales, "rot": rots}  # fmt: skip


def test_sh_padding_is_read_by_the_inria_loader_and_renders_identically(tmp_path):
    s = _scene(200, degree=0)
    path = export_scene(s, tmp_path / "s.ply", fmt="ply", sh_degree=3)
    inria = _inria_read(path)
    assert inria["rest"].shape == (200, 3, 15) and not inria["rest"].any()  # 45 f_rest, all zero
    np.testing.assert_array_equal(inria["xyz"], s.means.numpy())
    np.testing.assert_array_equal(inria["dc"], s.sh[:, 0].numpy())
    np.testing.assert_array_equal(inria["opacity"], s.opacity_logits.numpy())
    np.testing.assert_array_equal(inria["scale"], s.log_scales.numpy())
    np.testing.assert_array_equal(inria["rot"], s.quats.numpy())
    back = load_scene(path)
    assert back.sh_degree == 3 and torch.equal(back.sh[:, :1], s.sh) and not back.sh[:, 1:].any()
    vm, K = _cams()
    a, b = _render(s, vm, K), _render(back, vm, K)
    assert float(a.std()) > 0.05  # a scene, not a blank frame
    torch.testing.assert_close(b, a, atol=1e-6, rtol=0)
    # the scene's own degree unless asked; a lower degree truncates
    assert load_scene(export_scene(s, tmp_path / "d0.ply", fmt="ply")).sh_degree == 0
    s3 = _scene(50, degree=3)
    t = load_scene(export_scene(s3, tmp_path / "d1.ply", fmt="ply", sh_degree=1))
    assert torch.equal(t.sh, s3.sh[:, :4])
    # a compressed PLY keeps padded bands exactly zero
    c = load_scene(export_scene(s, tmp_path / "c.compressed.ply", fmt="ply-compressed", sh_degree=3))
    assert c.sh_degree == 3 and not c.sh[:, 1:].any()
    names = ["c.compressed.ply", "d0.ply", "d1.ply", "s.ply"]
    assert sorted(p.name for p in tmp_path.iterdir()) == names  # no temporaries left


def test_up_axis_minus_y_as_the_inria_loader_reads_it(tmp_path):
    """Independent of export.py: the Inria fields of a -Y-up export against (x, -z, y), scipy's
    rotation of the quaternions, and the SH colours evaluated in the rotated directions."""
    from scipy.spatial.transform import Rotation

    s = _scene(120, degree=3, seed=1)
    inria = _inria_read(export_scene(s, tmp_path / "s.ply", fmt="ply", up="-y"))
    x, y, z = s.means.numpy().T
    np.testing.assert_array_equal(inria["xyz"], np.stack([x, -z, y], 1))  # +Z up becomes -Y up
    q, q_new = s.quats.double().numpy(), inria["rot"].astype(np.float64)
    r_x = Rotation.from_euler("x", 90, degrees=True)
    want = (r_x * Rotation.from_quat(q[:, [1, 2, 3, 0]])).as_matrix()
    got = Rotation.from_quat(q_new[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(got, want, atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(q_new, axis=1), np.linalg.norm(q, axis=1), rtol=1e-6)
    np.testing.assert_array_equal(inria["scale"], s.log_scales.numpy())
    # the colour seen along R d in the file is the colour seen along d in the scene
    sh_new = np.concatenate([inria["dc"][:, None, :], inria["rest"].transpose(0, 2, 1)], axis=1)
    dirs = torch.nn.functional.normalize(torch.randn(120, 3, generator=torch.Generator().manual_seed(5)), dim=-1)
    want_c = eval_sh(3, s.sh.double(), dirs.double())
    got_c = eval_sh(3, torch.from_numpy(sh_new), dirs.double() @ torch.from_numpy(r_x.as_matrix()).T)
    torch.testing.assert_close(got_c, want_c, atol=1e-6, rtol=0)
    # the SH rotation is not the identity: unrotated coefficients give other colours
    assert (
        float((eval_sh(3, s.sh.double(), dirs.double() @ torch.from_numpy(r_x.as_matrix()).T) - want_c).abs().max())
        > 0.1
    )


@pytest.mark.parametrize("up", ["-y", "+y"])
@pytest.mark.parametrize("fmt", ["ply", "ply-compressed"])
def test_up_axis_round_trip_and_render(tmp_path, fmt, up):
    s = _scene(300, degree=3, seed=2)
    suffix = ".ply" if fmt == "ply" else ".compressed.ply"
    path = export_scene(s, tmp_path / f"s{suffix}", fmt=fmt, up=up)
    r = up_rotation(up)
    unit = lambda q: q / q.norm(dim=-1, keepdim=True)  # noqa: E731
    # read with the file's up axis: rotated back, the original scene
    back = load_scene(path, up=up)
    if fmt == "ply":
        for k in ("means", "log_scales", "opacity_logits", "sh"):
            torch.testing.assert_close(getattr(back, k), getattr(s, k), atol=1e-6, rtol=0)
        torch.testing.assert_close(quat_to_rotmat(unit(back.quats)), quat_to_rotmat(unit(s.quats)), atol=1e-6, rtol=0)
    else:
        o = s.subset(torch.from_numpy(_nearest(back.means.numpy(), s.means.numpy())))
        # quantised in the rotated frame: half a step of a chunk's range (at most the scene's
        # widest range, axes permuted by the rotation), SH bands 1/32 per coefficient rotated
        # back (an orthogonal map: sqrt(2l + 1) / 32 at most)
        widest = lambda x: float((x.amax(0) - x.amin(0)).max())  # noqa: E731
        assert float((back.means - o.means).abs().max()) <= widest(s.means) * 0.5 / 1023 + 1e-6
        assert float((back.log_scales - o.log_scales).abs().max()) <= widest(s.log_scales) * 0.5 / 1023 + 1e-6
        assert float((back.colors - o.colors).abs().max()) <= 0.5 / 255 + 1e-6
        assert float((back.sh[:, 1:] - o.sh[:, 1:]).abs().max()) <= 7**0.5 / 32
        assert float((quat_to_rotmat(unit(back.quats)) - quat_to_rotmat(unit(o.quats))).abs().max()) < 1e-2
    # read as written (the raw reader: load_scene turns it back by its recorded axis): the rotated
    # scene, which from the rotated cameras is the original image
    vm, K = _cams()
    rotated = GaussianScene.load_ply(path)
    assert load_scene(path).means.allclose(back.means)  # the recorded axis is the one asked for above
    img = _render(rotated, _rotated_viewmats(vm, r), K)
    ref = _render(s, vm, K)
    assert float(ref.std()) > 0.05
    if fmt == "ply":
        torch.testing.assert_close(img, ref, atol=1e-5, rtol=0)
        # and the test can fail: leaving the SH unrotated changes the image
        wrong = GaussianScene(rotated.means, rotated.quats, rotated.log_scales, rotated.opacity_logits, s.sh)
        assert float((_render(wrong, _rotated_viewmats(vm, r), K) - ref).abs().max()) > 0.05
    else:
        _assert_image_close(img, ref, max_err=0.1, mean_err=0.01)


def test_rotate_scene_any_rotation_and_zero_quaternions():
    from scipy.spatial.transform import Rotation

    s = _scene(100, degree=3, seed=3)
    s.quats[:3] = 0.0  # the identity in our convention
    r = torch.from_numpy(Rotation.from_rotvec([0.3, -1.1, 0.7]).as_matrix())
    t = rotate_scene(s, r)
    torch.testing.assert_close(quat_to_rotmat(t.quats[:3]), r.float().expand(3, 3, 3), atol=1e-6, rtol=0)
    vm, K = _cams()
    torch.testing.assert_close(_render(t, _rotated_viewmats(vm, r), K), _render(s, vm, K), atol=1e-5, rtol=0)
    back = rotate_scene(t, r.T)
    torch.testing.assert_close(back.sh, s.sh, atol=1e-5, rtol=0)
    torch.testing.assert_close(back.means, s.means, atol=1e-6, rtol=0)
    with pytest.raises(ValueError, match="rotation: expected a proper rotation"):
        rotate_scene(s, torch.diag(torch.tensor([1.0, 1.0, -1.0])))


# ----------------------------------------------------------------------------- .splat
SPLAT_ROW = np.dtype([("p", "<f4", 3), ("s", "<f4", 3), ("c", "u1", 4), ("r", "u1", 4)])


def test_splat_decoded_by_a_plain_numpy_struct(tmp_path):
    s = _scene(300, degree=2, seed=4)
    path = export_scene(s, tmp_path / "s.splat", fmt="splat")
    rows = np.frombuffer(path.read_bytes(), dtype=SPLAT_ROW)
    assert rows.itemsize == 32 and len(rows) == 300
    index = {r.tobytes(): i for i, r in enumerate(s.means.numpy())}
    idx = np.array([index[p.tobytes()] for p in rows["p"]])  # positions are exact float32
    assert sorted(idx.tolist()) == list(range(300))
    np.testing.assert_allclose(rows["s"], np.exp(s.log_scales.double().numpy()[idx]), rtol=1e-6)
    colour = np.concatenate([s.colors.double().numpy(), s.opacities.double().numpy()[:, None]], 1)[idx]
    err = colour - rows["c"] / 255.0  # truncated: 0 <= err < 1/255
    assert err.min() >= -1e-6 and err.max() < 1 / 255
    q = s.quats.double().numpy()[idx]
    err = q / np.linalg.norm(q, axis=1, keepdims=True) - (rows["r"].astype(np.float64) - 128) / 128
    assert err.min() >= -1e-6 and err.max() < 1 / 128 + 1e-6
    # antimatter15's order: descending volume * opacity
    key = np.exp(s.log_scales.double().numpy().sum(1)) / (1 + np.exp(-s.opacity_logits.double().numpy()))
    assert np.all(np.diff(key[idx]) <= 0)
    # load_scene reads what a viewer shows: the same bytes back
    back = load_scene(path)
    assert back.sh_degree == 0 and torch.equal(back.means, torch.from_numpy(rows["p"].copy()))
    torch.testing.assert_close(back.colors.double(), torch.from_numpy(rows["c"][:, :3] / 255.0), atol=1e-6, rtol=0)
    torch.testing.assert_close(back.opacities.double(), torch.from_numpy(rows["c"][:, 3] / 255.0), atol=1e-6, rtol=0)
    vm, K = _cams()
    ref = _render(s.with_sh_degree(0), vm, K)  # a .splat holds the DC colour only
    assert float(ref.std()) > 0.05
    _assert_image_close(_render(back, vm, K), ref, max_err=0.03, mean_err=0.005)


def test_splat_rows_equal_gsplats(tmp_path):
    exporter = pytest.importorskip("gsplat.exporter")
    s = _scene(200, degree=1, seed=5)
    ours = np.frombuffer(export_scene(s, tmp_path / "s.splat", fmt="splat").read_bytes(), dtype="V32")
    theirs = np.frombuffer(
        exporter.export_splats(
            s.means, s.log_scales, s.quats, s.opacity_logits, s.sh[:, :1], s.sh[:, 1:], format="splat"
        ),
        dtype="V32",
    )
    assert len(ours) == 200 and sorted(ours.tolist()) == sorted(theirs.tolist())  # gsplat orders by Morton code


# ----------------------------------------------------------------------------- compressed PLY
def _decode_compressed(path) -> dict[str, np.ndarray]:
    """The compressed PLY decoded here with plyfile and bit arithmetic (SuperSplat's layout)."""
    from plyfile import PlyData

    ply = PlyData.read(str(path))
    ch, v = ply["chunk"].data, ply["vertex"].data
    n = len(v)
    c = np.arange(n) // 256
    bits = lambda x, lo, width: ((x.astype(np.uint64) >> np.uint64(lo)) % (2**width)).astype(np.float64)  # noqa: E731
    out = {"chunk": c}

    def field(packed, names):
        ts = [bits(packed, 21, 11) / 2047, bits(packed, 11, 10) / 1023, bits(packed, 0, 11) / 2047]
        lo = np.stack([ch[f"min_{a}"][c] for a in names], 1).astype(np.float64)
        hi = np.stack([ch[f"max_{a}"][c] for a in names], 1).astype(np.float64)
        return lo + (hi - lo) * np.stack(ts, 1), (hi - lo)

    out["xyz"], out["xyz_range"] = field(v["packed_position"], "xyz")
    out["scale"], out["scale_range"] = field(v["packed_scale"], ["scale_x", "scale_y", "scale_z"])
    col = v["packed_color"]
    lo = np.stack([ch[f"min_{a}"][c] for a in "rgb"], 1).astype(np.float64)
    hi = np.stack([ch[f"max_{a}"][c] for a in "rgb"], 1).astype(np.float64)
    out["rgb"] = lo + (hi - lo) * np.stack([bits(col, 24, 8), bits(col, 16, 8), bits(col, 8, 8)], 1) / 255
    out["rgb_range"] = hi - lo
    out["alpha"] = bits(col, 0, 8) / 255
    rot = v["packed_rotation"]
    largest = bits(rot, 30, 2).astype(int)
    three = [(bits(rot, sh, 10) / 1023 - 0.5) / (np.sqrt(2) / 2) for sh in (20, 10, 0)]
    q = np.zeros((n, 4))
    for i in range(n):
        rest = [j for j in range(4) if j != largest[i]]
        q[i, rest] = [t[i] for t in three]
        q[i, largest[i]] = np.sqrt(max(0.0, 1 - sum(t[i] ** 2 for t in three)))
    out["rot"], out["largest"] = q, largest
    if "sh" in [e.name for e in ply.elements] and ply["sh"].data.dtype.names:
        s = ply["sh"].data
        raw = np.stack([s[f"f_rest_{i}"] for i in range(len(s.dtype.names))], 1).astype(np.float64)
        # trunc((f / 8 + 0.5) * 256): bins of 1/32, read at their middle but for [0, 1/32), read as 0
        out["rest_zero_bin"] = raw == 128
        out["rest"] = np.where(out["rest_zero_bin"], 0.0, (raw + 0.5) / 32 - 4)
    return out


def test_compressed_decoded_by_plyfile_and_bit_arithmetic(tmp_path):
    s = _scene(600, degree=3, seed=6)  # 3 chunks, the last one of 88
    path = export_scene(s, tmp_path / "s.compressed.ply", fmt="ply-compressed")
    d = _decode_compressed(path)
    i = _nearest(d["xyz"], s.means.numpy())
    half_step = np.array([0.5 / 2047, 0.5 / 1023, 0.5 / 2047])
    eps = 1e-6
    assert np.all(np.abs(d["xyz"] - s.means.double().numpy()[i]) <= d["xyz_range"] * half_step + eps)
    assert np.all(np.abs(d["scale"] - s.log_scales.double().numpy()[i]) <= d["scale_range"] * half_step + eps)
    assert np.all(np.abs(d["rgb"] - s.colors.double().numpy()[i]) <= d["rgb_range"] * 0.5 / 255 + eps)
    assert np.all(np.abs(d["alpha"] - s.opacities.double().numpy()[i]) <= 0.5 / 255 + eps)
    q = s.quats.double().numpy()[i]
    q = q / np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.sign(q[np.arange(600), d["largest"]])[:, None]  # the stored sign: largest component positive
    err = np.abs(d["rot"] - q)
    small = np.ones_like(err, dtype=bool)
    small[np.arange(600), d["largest"]] = False
    assert err[small].max() <= np.sqrt(2) * 0.5 / 1023 + eps and err.max() < 4e-3
    rest = s.sh[:, 1:].transpose(1, 2).reshape(600, 45).double().numpy()[i]
    err = rest - d["rest"]
    zero_bin = d["rest_zero_bin"]
    assert zero_bin.any() and np.abs(err[~zero_bin]).max() <= 1 / 64 + eps
    assert err[zero_bin].min() >= -eps and err[zero_bin].max() < 1 / 32
    # our reader agrees with this one; GaussianScene.load_ply (gdbench render) reads the file too
    ours = load_scene(path)
    np.testing.assert_allclose(ours.means.numpy(), d["xyz"], atol=1e-6)
    np.testing.assert_allclose(ours.log_scales.numpy(), d["scale"], atol=1e-6)
    np.testing.assert_allclose(ours.colors.double().numpy(), d["rgb"], atol=1e-6)
    np.testing.assert_allclose(ours.opacities.double().numpy(), d["alpha"], atol=1e-6)
    np.testing.assert_allclose(ours.quats.numpy(), d["rot"], atol=1e-6)
    np.testing.assert_allclose(ours.sh[:, 1:].transpose(1, 2).reshape(600, 45).numpy(), d["rest"], atol=1e-6)
    for k in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        assert torch.equal(getattr(GaussianScene.load_ply(path), k), getattr(ours, k))
    # rendered: the quantised scene is close to the original
    vm, K = _cams()
    ref = _render(s, vm, K)
    assert float(ref.std()) > 0.05
    _assert_image_close(_render(ours, vm, K), ref, max_err=0.1, mean_err=0.01)


def test_compressed_bytes_equal_gsplats_in_the_same_order(tmp_path, monkeypatch):
    """The order of the Gaussians (Morton codes, a choice of each writer) is not part of the
    format: with both orders fixed to the input order the files are byte-identical."""
    exporter = pytest.importorskip("gsplat.exporter")
    s = _scene(600, degree=3, seed=7)
    monkeypatch.setattr(export, "_morton_order", lambda means: torch.arange(len(means)))
    monkeypatch.setattr(exporter, "sort_centers", lambda centers, indices: indices)
    ours = export_scene(s, tmp_path / "s.ply", fmt="ply-compressed", run="abc").read_bytes()
    theirs = exporter.export_splats(
        s.means, s.log_scales, s.quats, s.opacity_logits, s.sh[:, :1], s.sh[:, 1:], format="ply_compressed"
    )
    tags = b"comment gdbench run abc\ncomment gdbench up +z\n"  # our header's comments, gsplat writes none
    assert tags in ours
    ours = ours.replace(tags, b"", 1)
    assert len(ours) == len(theirs) and ours == theirs


def test_compressed_constant_chunks_and_gsplats_degree_0_file(tmp_path):
    """A chunk whose values are all equal (the paper's initialisation: one scale, one colour) and
    a last chunk of a single Gaussian are read back exactly; gsplat's degree-0 file (an empty
    ``sh`` element) is read."""
    s = sphere_init(257, generator=torch.Generator().manual_seed(0))
    back = load_scene(export_scene(s, tmp_path / "s.compressed.ply", fmt="ply-compressed"))
    assert back.sh_degree == 0 and len(back) == 257
    torch.testing.assert_close(back.log_scales, s.log_scales, atol=0, rtol=0)
    torch.testing.assert_close(back.colors, s.colors, atol=1e-6, rtol=0)
    torch.testing.assert_close(back.opacities, s.opacities, atol=0.5 / 255, rtol=0)
    exporter = pytest.importorskip("gsplat.exporter")
    t = _scene(300, degree=0, seed=8)
    (tmp_path / "g.ply").write_bytes(
        exporter.export_splats(
            t.means, t.log_scales, t.quats, t.opacity_logits, t.sh[:, :1], t.sh[:, 1:], format="ply_compressed"
        )
    )
    g = load_scene(tmp_path / "g.ply")
    assert g.sh_degree == 0 and len(g) == 300
    i = _nearest(g.means.numpy(), t.means.numpy())
    torch.testing.assert_close(g.opacities, t.opacities[i], atol=0.5 / 255 + 1e-6, rtol=0)


def test_compressed_malformed_is_refused_naming_the_file(tmp_path):
    path = export_scene(_scene(300, degree=1), tmp_path / "s.ply", fmt="ply-compressed")
    data = path.read_bytes()
    (tmp_path / "chunks.ply").write_bytes(data.replace(b"element chunk 2\n", b"element chunk 1\n", 1))
    with pytest.raises(ValueError, match=r"chunks.ply: "):
        load_scene(tmp_path / "chunks.ply")
    (tmp_path / "cut.ply").write_bytes(data[:-10])
    with pytest.raises(ValueError, match=r"cut.ply: "):
        GaussianScene.load_ply(tmp_path / "cut.ply")


# ----------------------------------------------------------------------------- all formats
@pytest.mark.parametrize(("fmt", "name"), [("ply", "s.ply"), ("splat", "s.splat"), ("ply-compressed", "s.ply")])
def test_every_format_round_trips_zero_quaternions_and_empty_scenes(tmp_path, fmt, name):
    s = _scene(40, degree=0, seed=9)
    s.quats[0] = 0.0
    back = load_scene(export_scene(s.to(torch.float64), tmp_path / name, fmt=fmt))
    assert back.means.dtype == torch.float32 and len(back) == 40
    i = torch.from_numpy(_nearest(back.means.numpy(), s.means.numpy()))
    q = back.quats[i == 0][0]
    torch.testing.assert_close(q / q.norm(), torch.tensor([1.0, 0, 0, 0]), atol=1e-2, rtol=0)  # the identity
    empty = s.subset(torch.zeros(40, dtype=torch.bool))
    assert len(load_scene(export_scene(empty, tmp_path / f"e_{name}", fmt=fmt))) == 0


@pytest.mark.parametrize(
    ("kwargs", "name", "match"),
    [
        ({"fmt": "gif"}, "s.ply", "fmt: expected one of 'ply', 'splat', 'ply-compressed', got 'gif'"),
        ({"fmt": "ply", "up": "z"}, "s.ply", "up: expected one of"),
        ({"fmt": "splat"}, "s.ply", r"path: fmt 'splat' writes a \.splat file"),
        ({"fmt": "ply"}, "s.splat", r"path: fmt 'ply' writes a \.ply file"),
        ({"fmt": "ply-compressed"}, "s.plyc", r"conventionally \*\.compressed\.ply"),
        ({"fmt": "ply", "sh_degree": 4}, "s.ply", "sh_degree: expected None or an integer in 0..3, got 4"),
        ({"fmt": "ply", "sh_degree": -1}, "s.ply", "sh_degree"),
        ({"fmt": "ply", "sh_degree": True}, "s.ply", "sh_degree"),
        ({"fmt": "ply", "sh_degree": 1.0}, "s.ply", "sh_degree"),
        ({"fmt": "splat", "sh_degree": 3}, "s.splat", "sh_degree: a .splat file holds the DC colour only"),
    ],
)
def test_bad_arguments_name_the_argument(tmp_path, kwargs, name, match):
    with pytest.raises(ValueError, match=match):
        export_scene(_scene(5, degree=1), tmp_path / name, **kwargs)
    assert not any(tmp_path.iterdir())


def test_bad_paths(tmp_path):
    s = _scene(5, degree=0)
    (tmp_path / "dir.ply").mkdir()
    with pytest.raises(ValueError, match=r"path: .*dir\.ply is a folder"):
        export_scene(s, tmp_path / "dir.ply", fmt="ply")
    (tmp_path / "file").write_text("x")
    with pytest.raises(ValueError, match=r"path: .*file is a file; expected a folder"):
        export_scene(s, tmp_path / "file" / "s.ply", fmt="ply")
    with pytest.raises(TypeError, match="scene: expected a GaussianScene"):
        export_scene(s.means, tmp_path / "s.ply", fmt="ply")
    with pytest.raises(FileNotFoundError, match="path: no file at"):
        load_scene(tmp_path / "missing.splat")
    (tmp_path / "x.bin").write_bytes(b"\x00" * 64)
    with pytest.raises(ValueError, match=r"x.bin: neither a PLY file"):
        load_scene(tmp_path / "x.bin")
    (tmp_path / "short.splat").write_bytes(b"\x00" * 33)
    with pytest.raises(ValueError, match=r"short.splat: 33 bytes is not a whole number of 32-byte"):
        load_scene(tmp_path / "short.splat")
    rows = np.zeros(2, dtype=SPLAT_ROW)
    rows["s"] = 0.01
    rows["p"][1, 2] = np.nan
    (tmp_path / "nan.splat").write_bytes(rows.tobytes())
    with pytest.raises(ValueError, match=r"nan.splat: position of row 1"):
        load_scene(tmp_path / "nan.splat")
    rows["p"][1, 2] = 0.0
    rows["s"][0, 0] = 0.0
    (tmp_path / "zero.splat").write_bytes(rows.tobytes())
    with pytest.raises(ValueError, match=r"zero.splat: scale of row 0"):
        load_scene(tmp_path / "zero.splat")
    with pytest.raises(ValueError, match=r"up: expected one of \+z, -y, \+y, -z, \+x, -x, got '-w'"):
        load_scene(tmp_path / "x.bin", up="-w")


def test_colour_of_a_splat_row_is_the_dc_colour(tmp_path):
    """One hand-made Gaussian, every byte known."""
    s = GaussianScene(
        torch.tensor([[0.5, -1.0, 2.0]]),
        torch.tensor([[0.0, 0.0, 0.0, 2.0]]),  # 180 degrees about z, norm 2
        torch.log(torch.tensor([[0.1, 0.2, 0.4]])),
        torch.logit(torch.tensor([0.5])),
        rgb_to_sh0(torch.tensor([[[1.0, 0.5, 0.0]]])),
    )
    row = np.frombuffer(export_scene(s, tmp_path / "s.splat", fmt="splat").read_bytes(), dtype=SPLAT_ROW)[0]
    assert row["p"].tolist() == [0.5, -1.0, 2.0]
    np.testing.assert_allclose(row["s"], [0.1, 0.2, 0.4], rtol=1e-6)
    assert row["c"].tolist()[1:] == [127, 0, 127] and row["c"][0] >= 254  # 0.5 * 255 truncated; 1.0 to rounding
    assert row["r"].tolist() == [128, 128, 128, 255]  # (0, 0, 0, 1) * 128 + 128, clipped at 255
    back = load_scene(tmp_path / "s.splat")
    torch.testing.assert_close(back.sh[0, 0], (torch.tensor([row["c"][0], 127, 0]) / 255.0 - 0.5) / C0)


def test_export_command_names_files_and_round_trips(tmp_path, capsys):
    """``gdbench export``: default names beside the source per format and up axis, the file read
    back with its up axis equals the scene (float32 PLY: exactly), render reads a .splat; the
    source is never overwritten."""
    from gdbench.app.cli import main
    from gdbench.app.cmd_scenes import Export, Render
    from gdbench.core.builtin import demo_scene

    run = tmp_path / "run"
    run.mkdir()
    scene = demo_scene(200, seed=2)
    scene.save_ply(run / "scene.ply")
    r = main(Export(run, format="ply", up="-y", sh_degree=3))
    assert Path(r["path"]) == run / "scene.y_down.sh3.ply" and r["gaussians"] == 200  # not the degree-0 name
    back = load_scene(r["path"], up="-y")
    assert back.sh.shape[1] == 16 and torch.allclose(back.means, scene.means, atol=1e-6)
    s = main(Export(run, format="splat"))
    assert Path(s["path"]) == run / "scene.y_down.splat"
    c = main(Export(run / "scene.ply", format="ply-compressed", up="+z"))
    assert Path(c["path"]) == run / "scene.z_up.compressed.ply"
    main(Render(Path(s["path"]), frames=2, size=32, out=tmp_path / "r"))
    assert (tmp_path / "r" / "scene.y_down_turntable_sheet.png").is_file()
    with pytest.raises(ValueError, match=r"out: .* is the source file"):
        main(Export(run, format="ply", out=run / "scene.ply"))


def _write_vertex_ply(path, fields: dict):
    from plyfile import PlyData, PlyElement

    n = len(next(iter(fields.values())))
    v = np.zeros(n, dtype=[(k, "f4") for k in fields])
    for k, col in fields.items():
        v[k] = col
    PlyData([PlyElement.describe(v, "vertex")]).write(str(path))
    return path


def test_a_bare_point_cloud_says_how_to_start_a_run_from_it(tmp_path):
    """x, y, z and colours but no Gaussian properties: the error names the missing ones and the
    command that takes a point cloud (generate --init ply --init-ply)."""
    from gdbench.core.scene import GaussianScene

    xyz = {"x": [0.0, 0.1], "y": [0.0, 0.2], "z": [0.0, 0.3]}
    pts = _write_vertex_ply(tmp_path / "pts.ply", xyz | {"red": [1.0, 0.5], "green": [0.0, 0.5], "blue": [0.0, 0.5]})
    with pytest.raises(ValueError, match=r"a point cloud, not a 3DGS PLY \(missing .*f_dc_0.*--init ply --init-ply"):
        GaussianScene.load_ply(pts)


def test_a_mip_splatting_filter_3d_field_is_named_as_ignored(tmp_path):
    """A 3DGS PLY with Mip-Splatting's filter_3D property: read as plain Gaussians (the same values
    as without it), with a warning that names the field."""
    from plyfile import PlyData, PlyElement

    from gdbench.core.builtin import demo_scene
    from gdbench.core.ply import read_ply

    plain = demo_scene(20).save_ply(tmp_path / "plain.ply")

    v = PlyData.read(str(plain))["vertex"].data
    extra = np.zeros(len(v), dtype=v.dtype.descr + [("filter_3D", "f4")])
    for name in v.dtype.names:
        extra[name] = v[name]
    extra["filter_3D"] = 0.01
    mip = tmp_path / "mip.ply"
    PlyData([PlyElement.describe(extra, "vertex")]).write(str(mip))
    with pytest.warns(UserWarning, match="filter_3D property .* is ignored"):
        got = read_ply(mip)
    want = read_ply(plain)
    assert all(torch.equal(got[k], want[k]) for k in want)
