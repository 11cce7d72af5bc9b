"""Stage 2: tile binning. Each visible Gaussian is listed in every 16x16 tile its
screen extent touches; each tile's list is sorted front to back by camera-space depth.

Images are the flattened ``*B C`` leading dims, I of them. Tiles are numbered
``tile = img * (tiles_y * tiles_x) + ty * tiles_x + tx``. The result is CSR-like:
``gauss_ids[tile_start[t]:tile_start[t+1]]`` are the flat Gaussian ids (``img * N + n``)
of tile t, nearest first; ties in depth keep the Gaussian order (a stable sort).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

# Pixels exactly on the boundary of a Gaussian's extent can flip with rounding; a tiny
# margin keeps the tile test conservative (it only ever adds tiles, never drops one).
_BBOX_MARGIN = 1e-3


class TileBins(NamedTuple):
    gauss_ids: Int[Tensor, " P"]
    """Flat Gaussian id (img * N + n) of each tile-Gaussian intersection, sorted by (tile, depth)."""
    tile_start: Int[Tensor, " T+1"]
    """Offsets into ``gauss_ids``: tile t owns ``[tile_start[t], tile_start[t+1])``."""
    tiles_x: int
    tiles_y: int
    tile_size: int


def tile_ranges(
    means2d: Float[Tensor, "I N 2"], radii: Float[Tensor, "I N 2"], tiles_x: int, tiles_y: int, tile_size: int
) -> tuple[Int[Tensor, "I N"], Int[Tensor, "I N"], Int[Tensor, "I N"], Int[Tensor, "I N"]]:
    """Inclusive tile index ranges [x0, x1] x [y0, y1] of each Gaussian's screen box."""
    lo = torch.floor((means2d - radii - _BBOX_MARGIN) / tile_size).long()
    hi = torch.floor((means2d + radii + _BBOX_MARGIN) / tile_size).long()
    x0 = lo[..., 0].clamp(0, tiles_x - 1)
    y0 = lo[..., 1].clamp(0, tiles_y - 1)
    x1 = hi[..., 0].clamp(0, tiles_x - 1)
    y1 = hi[..., 1].clamp(0, tiles_y - 1)
    return x0, x1, y0, y1


@torch.no_grad()
def bin_tiles(
    means2d: Float[Tensor, "I N 2"],
    radii: Float[Tensor, "I N 2"],
    depths: Float[Tensor, "I N"],
    visible: Bool[Tensor, "I N"],
    width: int,
    height: int,
    tile_size: int = 16,
) -> TileBins:
    """List the Gaussians of each tile, front to back. Work and memory are O(intersections)."""
    device = means2d.device
    I, N = depths.shape
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    n_tiles = I * tiles_x * tiles_y

    # Visible Gaussians, sorted by (image, depth): a stable depth sort, then a stable image sort.
    ids = torch.nonzero(visible.reshape(-1), as_tuple=False).squeeze(1)
    order = torch.sort(depths.reshape(-1)[ids], stable=True).indices
    ids = ids[order]
    if I > 1:
        ids = ids[torch.sort(torch.div(ids, N, rounding_mode="floor"), stable=True).indices]

    x0, x1, y0, y1 = (r.reshape(-1)[ids] for r in tile_ranges(means2d, radii, tiles_x, tiles_y, tile_size))
    w = x1 - x0 + 1
    counts = w * (y1 - y0 + 1)
    total = int(counts.sum()) if counts.numel() else 0

    if total == 0:
        empty = torch.zeros(0, dtype=torch.long, device=device)
        return TileBins(empty, torch.zeros(n_tiles + 1, dtype=torch.long, device=device), tiles_x, tiles_y, tile_size)

    owner = torch.repeat_interleave(torch.arange(ids.numel(), device=device), counts, output_size=total)
    first = torch.cumsum(counts, 0) - counts
    k = torch.arange(total, device=device) - first[owner]
    tx = x0[owner] + k % w[owner]
    ty = y0[owner] + torch.div(k, w[owner], rounding_mode="floor")
    img = torch.div(ids[owner], N, rounding_mode="floor")
    tile = img * (tiles_x * tiles_y) + ty * tiles_x + tx

    tile, perm = torch.sort(tile, stable=True)  # stable: depth order survives within a tile
    gauss_ids = ids[owner[perm]]
    tile_start = torch.zeros(n_tiles + 1, dtype=torch.long, device=device)
    tile_start[1:] = torch.cumsum(torch.bincount(tile, minlength=n_tiles), 0)
    return TileBins(gauss_ids, tile_start, tiles_x, tiles_y, tile_size)


def bin_tiles_cpu(
    means2d: Float[Tensor, "I N 2"],
    radii: Float[Tensor, "I N 2"],
    depths: Float[Tensor, "I N"],
    visible: Bool[Tensor, "I N"],
    width: int,
    height: int,
    tile_size: int = 16,
) -> TileBins:
    """``bin_tiles`` in C++ (``csrc/project_cpu.cpp``): the same lists in the same order."""
    from ._ext import load_extension

    I, N = depths.shape
    gids, starts = load_extension().bin_tiles(
        means2d.detach().contiguous(),
        radii.detach().contiguous(),
        depths.detach().contiguous(),
        visible.contiguous(),
        I,
        N,
        width,
        height,
        tile_size,
    )
    tiles_x = (width + tile_size - 1) // tile_size
    tiles_y = (height + tile_size - 1) // tile_size
    return TileBins(gids, starts, tiles_x, tiles_y, tile_size)
