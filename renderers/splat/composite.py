"""Stage 3: front-to-back alpha compositing over tiles, forward and backward by hand.

For a pixel u and the Gaussians of its tile in depth order (i = 1, 2, ...):

    alpha_i = min(alpha_max, o_i exp(power_i(u)))      skipped (alpha_i = 0) below alpha_min
    T_i     = prod_{j<i} (1 - alpha_j)                  transmittance in front of i
    w_i     = alpha_i T_i                               blending weight
    kept    = T_i (1 - alpha_i) >= t_min                the Gaussian that would bring T below
                                                        t_min is not added and the pixel stops
    feat    = sum_kept w_i c_i      depth = sum_kept w_i z_i      weight_sq = sum_kept w_i^2
    T_final = prod_kept (1 - alpha_i)

Because T only decreases, "kept" is a prefix of the list, so it is computed for all
Gaussians of a tile at once with a cumulative product, exactly as the sequential kernel
of the Inria and gsplat renderers would.

Work is done tile by tile in chunks: tiles are sorted by list length and grouped so that
``tiles x longest list x pixels per tile`` stays under a budget of elements. Nothing of size
pixels x N is ever built. The backward recomputes each chunk's alphas instead of storing
them, so memory is O(chunk + intersections). Gradients (per pixel, then summed over the
tile's pixels and scattered to the Gaussians):

    dL/dc_i     = w_i dL/dfeat
    dL/dalpha_i = T_i v_i - (sum_{m>i} w_m v_m + T_final dL/dT_final) / (1 - alpha_i)
    with v_i = dL/dfeat . c_i + dL/ddepth z_i + 2 w_i dL/dweight_sq.

The clamp at alpha_max has zero derivative (as autograd through ``min`` gives).
"""

from __future__ import annotations

from typing import NamedTuple

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from .bin_tiles import TileBins


class BlendParams(NamedTuple):
    alpha_min: float = 1.0 / 255.0
    alpha_max: float = 0.99
    t_min: float = 1e-4


class Chunk(NamedTuple):
    tiles: Int[Tensor, " Tc"]
    """Global tile ids of this chunk."""
    gauss: Int[Tensor, "Tc L"]
    """Flat Gaussian ids, front to back; padding points at id 0 and is masked by ``valid``."""
    valid: Bool[Tensor, "Tc L"]


class Splats(NamedTuple):
    """Flat per (image, Gaussian) inputs of the compositor, indexed by ``img * N + n``."""

    means2d: Float[Tensor, "IN 2"]
    conics: Float[Tensor, "IN 3"]
    opacities: Float[Tensor, " IN"]
    features: Float[Tensor, "IN D"]
    depths: Float[Tensor, " IN"]


class Outputs(NamedTuple):
    """Compositor outputs, None when not requested: in tile layout [T, tile_size^2, ...] from this
    module's passes, as images [I, H, W, 1 or D] from ``autograd.composite``."""

    features: Tensor | None
    transmittance: Tensor | None
    depth: Tensor | None
    weight_sq: Tensor | None


def plan_chunks(bins: TileBins, budget: int) -> list[Chunk]:
    """Group non-empty tiles of similar list length so that Tc * L * tile_area <= budget.

    A single tile is never split, so a tile longer than the budget is a chunk on its own.
    """
    counts = bins.tile_start[1:] - bins.tile_start[:-1]
    nonempty = torch.nonzero(counts > 0).squeeze(1)
    if nonempty.numel() == 0:
        return []
    c_sorted, order = torch.sort(counts[nonempty])
    tiles_sorted = nonempty[order]
    area = bins.tile_size**2
    c_list = c_sorted.tolist()
    chunks: list[Chunk] = []
    start = 0
    device = counts.device
    while start < len(c_list):
        end = start + 1
        while end < len(c_list) and (end + 1 - start) * c_list[end] * area <= budget:
            end += 1
        tiles = tiles_sorted[start:end]
        L = c_list[end - 1]
        lane = torch.arange(L, device=device)
        valid = lane[None, :] < counts[tiles][:, None]
        idx = torch.where(valid, bins.tile_start[tiles][:, None] + lane[None, :], torch.zeros_like(lane)[None, :])
        chunks.append(Chunk(tiles, bins.gauss_ids[idx], valid))
        start = end
    return chunks


def tile_pixels(tiles: Tensor, bins: TileBins, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """Pixel-centre coordinates (x, y), each [Tc, tile_area], of the given global tiles."""
    ts = bins.tile_size
    local = tiles % (bins.tiles_x * bins.tiles_y)
    ty = torch.div(local, bins.tiles_x, rounding_mode="floor")
    tx = local % bins.tiles_x
    lane = torch.arange(ts * ts, device=tiles.device)
    px = (tx[:, None] * ts + lane[None, :] % ts).to(dtype) + 0.5
    py = (ty[:, None] * ts + torch.div(lane, ts, rounding_mode="floor")[None, :]).to(dtype) + 0.5
    return px, py


class _ChunkState(NamedTuple):
    dx: Tensor  # [Tc, L, P]
    dy: Tensor
    G: Tensor  # exp(power)
    alpha: Tensor  # kept alphas (0 where skipped or past the stop)
    unclamped: Tensor  # bool: alpha = o G (derivative flows)
    T: Tensor  # transmittance in front, [Tc, L, P]
    w: Tensor  # blending weights
    T_final: Tensor  # [Tc, P]


def _chunk_weights(chunk: Chunk, splats: Splats, bins: TileBins, blend: BlendParams) -> _ChunkState:
    g = chunk.gauss
    px, py = tile_pixels(chunk.tiles, bins, splats.means2d.dtype)
    m = splats.means2d[g]  # [Tc, L, 2]
    con = splats.conics[g]  # [Tc, L, 3]
    o = torch.where(chunk.valid, splats.opacities[g], torch.zeros_like(splats.opacities[g]))
    dx = px[:, None, :] - m[..., 0, None]
    dy = py[:, None, :] - m[..., 1, None]
    A, B, C = (con[..., k, None] for k in range(3))
    G = torch.exp(-0.5 * (A * dx * dx + C * dy * dy) - B * dx * dy)
    raw = o[..., None] * G
    unclamped = raw < blend.alpha_max
    alpha = torch.where(unclamped, raw, torch.full_like(raw, blend.alpha_max))
    alpha = torch.where(alpha >= blend.alpha_min, alpha, torch.zeros_like(alpha))
    T_incl = torch.cumprod(1.0 - alpha, dim=1)
    kept = T_incl >= blend.t_min
    alpha = torch.where(kept, alpha, torch.zeros_like(alpha))
    T = torch.cat([torch.ones_like(T_incl[:, :1]), T_incl[:, :-1]], dim=1)
    w = alpha * T
    T_final = torch.where(kept, T_incl, torch.ones_like(T_incl)).amin(dim=1)
    return _ChunkState(dx, dy, G, alpha, unclamped & (alpha > 0), T, w, T_final)


@torch.no_grad()
def composite_forward(
    splats: Splats,
    bins: TileBins,
    chunks: list[Chunk],
    n_images: int,
    blend: BlendParams,
    *,
    features: bool = True,
    depth: bool = False,
    weight_sq: bool = False,
) -> Outputs:
    """Composite every tile; outputs in tile layout [T, tile_area(, D)]."""
    n_tiles = n_images * bins.tiles_x * bins.tiles_y
    area = bins.tile_size**2
    ref = splats.means2d
    D = splats.features.shape[-1]
    feat = ref.new_zeros(n_tiles, area, D) if features else None
    trans = ref.new_ones(n_tiles, area)
    dep = ref.new_zeros(n_tiles, area) if depth else None
    wsq = ref.new_zeros(n_tiles, area) if weight_sq else None
    for chunk in chunks:
        st = _chunk_weights(chunk, splats, bins, blend)
        trans[chunk.tiles] = st.T_final
        if feat is not None:
            feat[chunk.tiles] = torch.einsum("tlp,tld->tpd", st.w, splats.features[chunk.gauss])
        if dep is not None:
            dep[chunk.tiles] = torch.einsum("tlp,tl->tp", st.w, splats.depths[chunk.gauss])
        if wsq is not None:
            wsq[chunk.tiles] = (st.w * st.w).sum(1)
    return Outputs(feat, trans, dep, wsq)


@torch.no_grad()
def composite_backward(
    splats: Splats, bins: TileBins, chunks: list[Chunk], blend: BlendParams, grads: Outputs
) -> Splats:
    """Gradients of a scalar loss with respect to the flat splat inputs, given output grads."""
    g_means = torch.zeros_like(splats.means2d)
    g_conics = torch.zeros_like(splats.conics)
    g_opac = torch.zeros_like(splats.opacities)
    g_feat = torch.zeros_like(splats.features)
    g_depth = torch.zeros_like(splats.depths)
    for chunk in chunks:
        st = _chunk_weights(chunk, splats, bins, blend)
        g = chunk.gauss
        v = torch.zeros_like(st.w)
        if grads.features is not None:
            gf = grads.features[chunk.tiles]  # [Tc, P, D]
            v = v + torch.einsum("tpd,tld->tlp", gf, splats.features[g])
            g_feat.index_add_(0, g.reshape(-1), torch.einsum("tlp,tpd->tld", st.w, gf).reshape(-1, gf.shape[-1]))
        if grads.depth is not None:
            gd = grads.depth[chunk.tiles]  # [Tc, P]
            v = v + gd[:, None, :] * splats.depths[g][..., None]
            g_depth.index_add_(0, g.reshape(-1), torch.einsum("tlp,tp->tl", st.w, gd).reshape(-1))
        if grads.weight_sq is not None:
            v = v + 2.0 * st.w * grads.weight_sq[chunk.tiles][:, None, :]
        wv = st.w * v
        behind = wv.sum(1, keepdim=True) - torch.cumsum(wv, dim=1)  # sum_{m>l} w_m v_m
        tail = behind + (st.T_final * grads.transmittance[chunk.tiles])[:, None, :]
        g_alpha = st.T * v - tail / (1.0 - st.alpha)
        g_alpha = torch.where(st.unclamped, g_alpha, torch.zeros_like(g_alpha))
        g_power = g_alpha * st.alpha  # d alpha / d power = o G = alpha where unclamped
        flat = g.reshape(-1)
        g_opac.index_add_(0, flat, (g_alpha * st.G).sum(-1).reshape(-1))
        dx, dy = st.dx, st.dy
        con = splats.conics[g]
        A, B, C = (con[..., k, None] for k in range(3))
        gm = torch.stack([((A * dx + B * dy) * g_power).sum(-1), ((B * dx + C * dy) * g_power).sum(-1)], -1)
        g_means.index_add_(0, flat, gm.reshape(-1, 2))
        gc = torch.stack(
            [(-0.5 * dx * dx * g_power).sum(-1), (-dx * dy * g_power).sum(-1), (-0.5 * dy * dy * g_power).sum(-1)], -1
        )
        g_conics.index_add_(0, flat, gc.reshape(-1, 3))
    return Splats(g_means, g_conics, g_opac, g_feat, g_depth)


def finish_images(
    features: Tensor | None, transmittance: Tensor, depth: Tensor | None, background: Tensor | None
) -> tuple[Tensor | None, Tensor, Tensor | None]:
    """(rgb, alpha, depth) from the compositor's sums: the background seen through the final
    transmittance, alpha = 1 - T, and the expected depth sum_i w_i z_i / alpha (0 where alpha is 0).
    Images are [..., H, W, D] and [..., H, W, 1]; ``background`` is [D] or [..., D] per image.
    One formula for the fast path, the float64 twin and the gsplat peer."""
    alpha = 1.0 - transmittance
    rgb = features
    if features is not None and background is not None:
        bg = background if background.dim() == 1 else background[..., None, None, :]
        rgb = features + transmittance * bg
    if depth is not None:
        covered = alpha > 0
        depth = torch.where(
            covered, depth / torch.where(covered, alpha, torch.ones_like(alpha)), torch.zeros_like(depth)
        )
    return rgb, alpha, depth
