"""Stage 2, tile binning, against a brute-force per-tile listing."""

import torch

from renderers.splat.bin_tiles import bin_tiles
from renderers.splat.project import project
from tests._util import random_gaussians, ring_cameras


def _setup(n=150, W=70, H=45, C=2, seed=0):
    gs = random_gaussians(n, seed=seed, dtype=torch.float64, scale=(0.005, 0.12))
    cams = ring_cameras(C, W, H, dtype=torch.float64, seed=seed)
    p = project(gs["means"], gs["quats"], gs["scales"], gs["opacities"], cams.viewmats, cams.Ks, W, H)
    return gs, p, W, H, C


def test_lists_match_brute_force_and_are_depth_sorted():
    _, p, W, H, C = _setup()
    ts = 16
    bins = bin_tiles(p.means2d, p.radii, p.depths, p.visible, W, H, ts)
    tx, ty = bins.tiles_x, bins.tiles_y
    assert (tx, ty) == (5, 3)
    N = p.depths.shape[1]
    total = 0
    for img in range(C):
        for j in range(ty):
            for i in range(tx):
                t = img * tx * ty + j * tx + i
                listed = bins.gauss_ids[bins.tile_start[t] : bins.tile_start[t + 1]]
                assert bool((listed // N == img).all())
                n = listed % N
                # brute force: visible Gaussians whose (margin-free) box overlaps the tile's pixel rectangle
                lo = p.means2d[img] - p.radii[img]
                hi = p.means2d[img] + p.radii[img]
                overlap = (
                    (hi[:, 0] >= i * ts) & (lo[:, 0] < (i + 1) * ts) & (hi[:, 1] >= j * ts) & (lo[:, 1] < (j + 1) * ts)
                )
                expected = set(torch.nonzero(overlap & p.visible[img]).squeeze(1).tolist())
                got = n.tolist()
                assert len(set(got)) == len(got)
                assert expected <= set(got)  # conservative: nothing needed is dropped
                assert len(set(got) - expected) <= 2  # and only boundary slivers are added
                d = p.depths[img][n]
                assert bool((d[1:] >= d[:-1]).all())
                total += len(got)
    assert total == bins.gauss_ids.numel() and total > 50


def test_every_contributing_pixel_is_in_a_listed_tile():
    """Dense oracle: each (pixel, Gaussian) with alpha >= 1/255 has the Gaussian in the pixel's tile."""
    gs, p, W, H, C = _setup(seed=1)
    bins = bin_tiles(p.means2d, p.radii, p.depths, p.visible, W, H, 16)
    N = p.depths.shape[1]
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    pix = torch.stack([xs, ys], -1).reshape(-1, 2).double()
    tile_of_pix = (ys.reshape(-1).long() // 16) * bins.tiles_x + (xs.reshape(-1).long() // 16)
    checked = 0
    for img in range(C):
        d = pix[None] - p.means2d[img][:, None]
        A, B, Cc = p.conics[img].unbind(-1)
        power = -0.5 * (A[:, None] * d[..., 0] ** 2 + Cc[:, None] * d[..., 1] ** 2) - B[:, None] * d[..., 0] * d[..., 1]
        hit = (gs["opacities"][:, None] * torch.exp(power) >= 1 / 255) & (p.depths[img] > 0.01)[:, None]
        members = torch.zeros(bins.tiles_x * bins.tiles_y, N, dtype=torch.bool)
        for t in range(bins.tiles_x * bins.tiles_y):
            g = img * bins.tiles_x * bins.tiles_y + t
            members[t, bins.gauss_ids[bins.tile_start[g] : bins.tile_start[g + 1]] % N] = True
        gi, pi = torch.nonzero(hit, as_tuple=True)
        assert bool(members[tile_of_pix[pi], gi].all())
        checked += gi.numel()
    assert checked > 1000


def test_empty_and_all_culled():
    _, p, W, H, C = _setup()
    bins = bin_tiles(p.means2d, p.radii, p.depths, torch.zeros_like(p.visible), W, H, 16)
    assert bins.gauss_ids.numel() == 0 and int(bins.tile_start.max()) == 0
    assert bins.tile_start.numel() == C * bins.tiles_x * bins.tiles_y + 1
    e = torch.zeros(C, 0)
    bins = bin_tiles(e[..., None].expand(C, 0, 2), e[..., None].expand(C, 0, 2), e, e.bool(), W, H, 16)
    assert bins.gauss_ids.numel() == 0


def test_equal_depths_keep_gaussian_order():
    means2d = torch.tensor([[[8.0, 8.0], [8.0, 8.0], [8.0, 8.0]]])
    radii = torch.full((1, 3, 2), 2.0)
    depths = torch.tensor([[1.0, 0.5, 1.0]])
    bins = bin_tiles(means2d, radii, depths, torch.ones(1, 3, dtype=torch.bool), 16, 16, 16)
    assert bins.gauss_ids.tolist() == [1, 0, 2]


def test_cpu_binning_gives_the_same_lists(cpp_extension):
    from renderers.splat.bin_tiles import bin_tiles_cpu

    for dtype, C in ((torch.float32, 3), (torch.float64, 3), (torch.float32, 1)):  # one image: no division
        gs = random_gaussians(400 * 3 // C, seed=4, dtype=dtype, scale=(0.002, 0.2))
        cams = ring_cameras(C, 70, 45, dtype=dtype, seed=2)
        p = project(gs["means"], gs["quats"], gs["scales"], gs["opacities"], cams.viewmats, cams.Ks, 70, 45)
        a = bin_tiles(p.means2d, p.radii, p.depths, p.visible, 70, 45, 16)
        b = bin_tiles_cpu(p.means2d, p.radii, p.depths, p.visible, 70, 45, 16)
        assert a.gauss_ids.numel() > 1000
        assert torch.equal(a.tile_start, b.tile_start) and torch.equal(a.gauss_ids, b.gauss_ids)
        assert (a.tiles_x, a.tiles_y) == (b.tiles_x, b.tiles_y)


def test_cpu_binning_in_parallel_chunks_keeps_ties_in_order(cpp_extension):
    """The C++ binning's radix sort and its chunked count and scatter (3 threads, lists longer
    than one chunk) against bin_tiles.py, with depths rounded so that many Gaussians tie."""
    from renderers.splat.bin_tiles import bin_tiles_cpu

    threads = torch.get_num_threads()
    torch.set_num_threads(3)
    try:
        for dtype in (torch.float32, torch.float64):
            g = torch.Generator().manual_seed(7)
            n = 30_000
            means2d = torch.rand(2, n, 2, generator=g, dtype=dtype) * torch.tensor([100.0, 60.0], dtype=dtype)
            radii = torch.rand(2, n, 2, generator=g, dtype=dtype) * 12
            depths = torch.round(torch.rand(2, n, generator=g, dtype=dtype) * 20) / 4 + 0.5  # 81 distinct values
            visible = torch.rand(2, n, generator=g) > 0.1
            a = bin_tiles(means2d, radii, depths, visible, 100, 60, 16)
            b = bin_tiles_cpu(means2d, radii, depths, visible, 100, 60, 16)
            assert a.gauss_ids.numel() > 50_000
            assert torch.equal(a.tile_start, b.tile_start) and torch.equal(a.gauss_ids, b.gauss_ids)
    finally:
        torch.set_num_threads(threads)
