"""Procedural assets and their image banks (pyrender), with trimesh ray casting as the depth oracle."""

import numpy as np
import pytest
import torch

from gdbench.assets import bank as bank_mod
from gdbench.assets.bank import BankConfig, bank_key, load_bank, render_bank
from gdbench.assets.library import ASSETS, build
from renderers.pyrender_points._lib import available

needs_pyrender = pytest.mark.skipif(not available()[0], reason=f"pyrender unavailable: {available()[1]}")


@pytest.mark.parametrize("caption", sorted(ASSETS))
def test_assets_fit_and_carry_colours(caption):
    m = build(caption)
    assert np.linalg.norm(m.vertices, axis=1).max() <= 0.45 + 1e-6
    cols = np.asarray(m.visual.vertex_colors)[:, :3].astype(float)
    assert cols.std(0).max() > 20  # patterned, not one flat colour
    assert len(m.vertices) > 2000


@needs_pyrender
@pytest.mark.parametrize("caption", sorted(ASSETS))
def test_front_differs_from_back(caption):
    """Each asset has a canonical front at azimuth 0: its front and back views differ."""
    b = render_bank(caption, BankConfig(resolution=32, azimuths=2, elevations=(10.0,), fovy=55.0))
    front, back = b.images[b.azimuth == 0][0], b.images[b.azimuth.abs() == 180][0]
    assert float((front - back).abs().mean()) > 0.01
    assert float(b.alpha[0].mean()) > 0.1  # the asset fills part of the view


@needs_pyrender
def test_bank_depth_matches_ray_casting():
    cfg = BankConfig(resolution=17, azimuths=4, elevations=(0.0, 30.0))
    b = render_bank("a yellow duck", cfg)
    mesh = build("a yellow duck")
    cams = b.cameras()
    centres = cams.centers.double().numpy()
    checked = 0
    for i in range(len(b)):
        # the centre pixel (8, 8) of an odd image looks along the optical axis
        fwd = cams.viewmats[i, 2, :3].double().numpy()  # third row of R: camera z in world
        locs, _, _ = mesh.ray.intersects_location(centres[i : i + 1], fwd[None], multiple_hits=False)
        if len(locs) == 0:
            assert float(b.depth[i, 8, 8]) == 0.0
            continue
        z = float(np.dot(locs[0] - centres[i], fwd))
        assert abs(float(b.depth[i, 8, 8]) - z) < 0.01 * z
        checked += 1
    assert checked >= 4


@needs_pyrender
def test_bank_cache_hits_and_keys(tmp_path, monkeypatch):
    monkeypatch.setenv("GDBENCH_CACHE", str(tmp_path))
    cfg = BankConfig(resolution=16, azimuths=3, elevations=(0.0,))
    first = load_bank("a sofa", cfg, verbose=False)
    monkeypatch.setattr(bank_mod, "render_bank", lambda *a, **k: pytest.fail("cache miss"))
    second = load_bank("a sofa", cfg, verbose=False)
    assert torch.equal(first.images, second.images) and len(second) == 3
    assert bank_key("a sofa", cfg) != bank_key("a sofa", BankConfig(resolution=16, azimuths=4, elevations=(0.0,)))
    # a corrupt cache entry is rebuilt, not trusted
    path = next((tmp_path / "banks").glob("*.npz"))
    path.write_bytes(b"garbage")
    monkeypatch.setattr(bank_mod, "render_bank", render_bank)
    assert torch.equal(load_bank("a sofa", cfg, verbose=False).images, first.images)


def test_bad_captions_and_configs():
    with pytest.raises(ValueError, match="caption: unknown asset 'a spaceship'; nearest: "):
        build("a spaceship")
    with pytest.raises(ValueError, match="caption: unknown asset"):
        load_bank("a spaceship")
    with pytest.raises(ValueError, match="elevations"):
        BankConfig(elevations=(95.0,))
    with pytest.raises(ValueError, match="resolution"):
        BankConfig(resolution=2)
