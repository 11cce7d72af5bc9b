"""``rasterize``: the entry point of the splat renderer (project -> bin_tiles -> composite)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from . import _checks as ck
from ._checks import OUTPUTS
from ._ext import load_extension
from .autograd import _cpp_forward, _flat, composite, resolve_backend
from .bin_tiles import TileBins, bin_tiles, bin_tiles_cpu
from .composite import Splats, finish_images
from .gsplat_backend import rasterize_gsplat, unsupported
from .project import Projection, project, project_cpu, view_dirs
from .settings import RasterSettings, resolve_settings
from .sh import C0, eval_sh

__all__ = [
    "OUTPUTS",
    "Prepared",
    "RasterSettings",
    "RenderOutput",
    "composite_features",
    "normalised_features",
    "prepare",
    "rasterize",
]


class RenderOutput(NamedTuple):
    """Renderer outputs; a field is None unless it was asked for in ``outputs``."""

    rgb: Float[Tensor, "*B C H W D"] | None = None
    """Composited features (RGB or any D channels), background blended in."""
    alpha: Float[Tensor, "*B C H W 1"] | None = None
    """1 - T_final."""
    depth: Float[Tensor, "*B C H W 1"] | None = None
    """Expected camera-space z, sum_i w_i z_i / alpha (0 where alpha is 0)."""
    weight_sq: Float[Tensor, "*B C H W 1"] | None = None
    """sum_i w_i^2, the variance of a composite of unit-variance iid colours."""
    means2d: Float[Tensor, "*B C N 2"] | None = None
    """Projected means, part of the graph (call ``retain_grad()`` for densification)."""
    radii: Float[Tensor, "*B C N 2"] | None = None
    """Screen half-extents in pixels, 0 where culled."""
    visible: Bool[Tensor, "*B C N"] | None = None


class Prepared(NamedTuple):
    """The colour-independent part of a render: projection and tile lists of N Gaussians in
    C cameras. Render any number of feature sets with ``composite_features``; the tile lists
    are reused, and gradients reach the geometry through ``projection``."""

    projection: Projection
    bins: TileBins
    opacities: Tensor
    """[I * N] opacities, one copy per image."""
    batch: tuple[int, ...]
    n_cameras: int
    n: int
    width: int
    height: int
    settings: RasterSettings


def _prepare(means, quats, scales, opacities, viewmats, Ks, width, height, batch, C, N, s: RasterSettings) -> Prepared:
    # the C++ projection and binning go with the C++ compositor (CPU); they give no gradients for
    # the cameras, so cameras that need them take the torch path
    fused = resolve_backend(s.backend, means.device) == "cpp" and not (viewmats.requires_grad or Ks.requires_grad)
    proj = (project_cpu if fused else project)(means, quats, scales, opacities, viewmats, Ks, width, height,
                                               **s.projection())  # fmt: skip
    I = C * int(torch.Size(batch).numel())
    bins = (bin_tiles_cpu if fused else bin_tiles)(
        proj.means2d.detach().reshape(I, N, 2),
        proj.radii.reshape(I, N, 2),
        proj.depths.detach().reshape(I, N),
        proj.visible.reshape(I, N),
        width,
        height,
        s.tile_size,
    )
    opac = opacities[..., None, :].expand(batch + (C, N)).reshape(I * N)
    return Prepared(proj, bins, opac, batch, C, N, width, height, s)


def prepare(
    means: Float[Tensor, "*B N 3"],
    quats: Float[Tensor, "*B N 4"],
    scales: Float[Tensor, "*B N 3"],
    opacities: Float[Tensor, "*B N"],
    viewmats: Float[Tensor, "*B C 4 4"],
    Ks: Float[Tensor, "*B C 3 3"],
    width: int,
    height: int,
    *,
    settings: RasterSettings | None = None,
    check_values: bool = True,
    **overrides,
) -> Prepared:
    """Project and bin once; then ``composite_features(prepared, features)`` per feature set.

    Same arguments and checks as ``rasterize`` minus the colours. ``check_values=False``
    skips the value scans (finite, ranges) for geometry that was checked before, such as a
    fixed noise cloud rendered every step; types and shapes are always checked.
    """
    s = resolve_settings(settings, overrides)
    batch, N, C = ck.check_geometry(means, quats, scales, opacities, viewmats, Ks, width, height, {})
    if check_values:
        geometry = {"means": means, "quats": quats, "scales": scales, "opacities": opacities}
        ck.check_values(geometry | {"viewmats": viewmats, "Ks": Ks}, scales, opacities)
    resolve_backend(s.backend, means.device)
    return _prepare(means, quats, scales, opacities, viewmats, Ks, width, height, batch, C, N, s)


def composite_features(
    prepared: Prepared,
    features: Tensor,
    *,
    background: Tensor | None = None,
    outputs: Sequence[str] = ("rgb", "alpha"),
) -> RenderOutput:
    """Blend per-Gaussian features ``[*B, (C,) N, D]`` over a ``prepare``d projection."""
    p = prepared
    outputs = ck.check_outputs(outputs)
    ck.check_tensor("features", features, finite=False)
    if background is not None:
        ck.check_tensor("background", background, finite=False)
    D, per_camera = ck.check_colors(features, background, p.batch, p.n, p.n_cameras, None)
    extra = {"features": features} | ({"background": background} if background is not None else {})
    ck.check_same({"means2d": p.projection.means2d, **extra})
    ck.check_values(extra, None, None)
    return _composite_images(p, features, per_camera, D, background, set(outputs))


def normalised_features(
    prepared: Prepared, features: Tensor, fill: Tensor, *, v_min: float = 1e-6, check_values: bool = True
) -> tuple[Tensor, Tensor]:
    """(n, coverage): the composite of ``features`` ``[*B, N, D]`` divided by sqrt(weight_sq), the
    composite's standard deviation for unit-variance iid features, where weight_sq >= ``v_min``
    (> 0 when ``v_min`` is not positive), and ``fill`` ``[*B, C, H, W, D]`` elsewhere; coverage
    ``[*B, C, H, W, 1]`` is 1 where the composite was used, else 0. Without gradients. On the C++
    backend one pass from the kernel's tile sums to the images (``csrc/noise_cpu.cpp``); the same
    bits as ``composite_features`` followed by the torch chain below, which other backends run.
    ``check_values=False`` skips the scan of ``features`` for non-finite values (on the C++
    backend; ``composite_features`` always scans)."""
    p = prepared
    ck.check_tensor("features", features, finite=False)
    ck.check_tensor("fill", fill, finite=False)
    images = p.batch + (p.n_cameras, p.height, p.width)
    D = features.shape[-1]
    if features.shape != p.batch + (p.n, D) or fill.shape != images + (D,):
        raise ValueError(
            f"features, fill: expected {list(p.batch + (p.n,))} + [D] and {list(images)} + [D], got "
            f"{list(features.shape)} and {list(fill.shape)}"
        )
    ck.check_same({"means2d": p.projection.means2d, "features": features})
    with torch.no_grad():
        if resolve_backend(p.settings.backend, p.projection.means2d.device) != "cpp":  # checks features always
            out = composite_features(p, features, outputs=("rgb", "weight_sq"))
            V = out.weight_sq
            covered = V >= v_min if v_min > 0 else V > 0
            n = out.rgb / torch.sqrt(torch.where(covered, V, torch.ones_like(V)))
            return torch.where(covered, n, fill.to(n)), covered.to(n.dtype)
        if check_values:
            ck.check_values({"features": features}, None, None)
        I = p.n_cameras * int(torch.Size(p.batch).numel())
        feats = features[..., None, :, :].expand(p.batch + (p.n_cameras, p.n, D))
        proj, bins = p.projection, p.bins
        splats = _flat(proj.means2d, proj.conics, p.opacities, feats, proj.depths)
        feat, _, _, wsq, _ = _cpp_forward(splats, bins, p.settings.blend, (True, False, True))
        n, coverage = load_extension().noise_finish(
            feat, wsq, fill.to(feat).reshape(I, p.height, p.width, D).contiguous(), bins.tiles_x, bins.tiles_y,
            bins.tile_size, p.height, p.width, float(v_min),
        )  # fmt: skip
    return n.reshape(images + (D,)), coverage.reshape(images + (1,))


def _composite_images(p: Prepared, feats: Tensor, per_camera: bool, D: int, background, want: set) -> RenderOutput:
    batch, C, N, width, height = p.batch, p.n_cameras, p.n, p.width, p.height
    proj, bins = p.projection, p.bins
    result = {k: getattr(proj, k) if k in want else None for k in ("means2d", "radii", "visible")}
    if not want & {"rgb", "alpha", "depth", "weight_sq"}:
        return RenderOutput(**result)
    I = C * int(torch.Size(batch).numel())
    feats = feats if per_camera else feats[..., None, :, :].expand(batch + (C, N, D))
    splats = Splats(proj.means2d, proj.conics, p.opacities, feats, proj.depths)
    s = p.settings
    # the transmittance as an image only for alpha, depth or a background (not for structured noise)
    finish = bool(want & {"alpha", "depth"}) or (background is not None and "rgb" in want)
    out = composite(splats, bins, I, s.blend, size=(height, width), features="rgb" in want, depth="depth" in want,
                    weight_sq="weight_sq" in want, transmittance=finish, budget=s.chunk_budget,
                    backend=s.backend)  # fmt: skip
    images = batch + (C, height, width)

    def shaped(x: Tensor | None) -> Tensor | None:  # [I, H, W, d] -> [*B, C, H, W, d]
        return x if x is None or x.shape[:-1] == images else x.reshape(images + (x.shape[-1],))

    if finish:
        rgb, alpha, depth = finish_images(
            shaped(out.features), shaped(out.transmittance), shaped(out.depth), background
        )
    else:  # the features as they are (structured noise: rgb and weight_sq)
        rgb, alpha, depth = shaped(out.features), None, None
    result |= {"rgb": rgb, "alpha": alpha if "alpha" in want else None, "depth": depth}
    result["weight_sq"] = shaped(out.weight_sq)
    return RenderOutput(**result)


def sh_colors(
    degree: int, colors: Tensor, per_camera: bool, means: Tensor, viewmats: Tensor, backend: str
) -> tuple[Tensor, bool]:
    """Colours [*B, C, N, D] from SH coefficients [*B, (C,) N, K, D] along the camera-to-mean
    directions. Without gradients on CPU the C++ kernel evaluates them (csrc/sh_cpu.cpp, no
    [N, K, D] temporary); otherwise ``eval_sh`` in torch, which autograd differentiates.
    Degree 0 is one colour per Gaussian: no directions, and [*B, (C,) N, D] as given (per
    camera only if ``colors`` was); the second value says which."""
    if degree == 0:  # eval_sh at degree 0, op for op (the same bits), without the view directions
        return (C0 * colors[..., 0, :] + 0.5).clamp_min(0.0), per_camera
    dirs = view_dirs(means, viewmats)
    batch, (C, N), (K, D) = tuple(means.shape[:-2]), dirs.shape[-3:-1], colors.shape[-2:]
    grads = torch.is_grad_enabled() and any(t.requires_grad for t in (colors, means, viewmats))
    if not grads and resolve_backend(backend, means.device) == "cpp":
        nb = int(torch.Size(batch).numel())
        coeffs = colors.reshape(nb * C if per_camera else nb, N, K, D).contiguous()
        d = dirs.reshape(nb * C if per_camera else nb, 1 if per_camera else C, N, 3).contiguous()
        return load_extension().sh_forward(degree, coeffs, d).reshape(batch + (C, N, D)), True
    coeffs = colors if per_camera else colors[..., None, :, :, :].expand(batch + (C, N, K, D))
    return eval_sh(degree, coeffs, dirs), True


def rasterize(
    means: Float[Tensor, "*B N 3"],
    quats: Float[Tensor, "*B N 4"],
    scales: Float[Tensor, "*B N 3"],
    opacities: Float[Tensor, "*B N"],
    colors: Tensor,
    viewmats: Float[Tensor, "*B C 4 4"],
    Ks: Float[Tensor, "*B C 3 3"],
    width: int,
    height: int,
    *,
    sh_degree: int | None = None,
    background: Tensor | None = None,
    outputs: Sequence[str] = ("rgb", "alpha"),
    settings: RasterSettings | None = None,
    check_values: bool = True,
    **overrides,
) -> RenderOutput:
    """Render N 3D Gaussians into C cameras with the 3DGS image formation model.

    Inputs are activated values: linear ``scales`` (>= 0), ``opacities`` in [0, 1],
    quaternions wxyz (any norm; zero means identity). ``colors`` is ``[*B, (C,) N, D]``
    plain features, or with ``sh_degree`` set, ``[*B, (C,) N, K, D]`` SH coefficients
    evaluated along the camera-to-mean direction (``renderers.splat.sh``).
    ``background`` is ``[D]`` or ``[*B, C, D]`` (default: none, i.e. black).

    The constants (near and far plane, eps2d, alpha_min, alpha_max, t_min, tile size, the torch
    backend's chunk budget and the compositor backend) are one ``RasterSettings`` (``settings``)
    or its fields as keywords, with the defaults of docs/renderer.md. Only the outputs named in
    ``outputs`` are computed (see ``OUTPUTS``). Images are [*B, C, H, W, ...]. The "cpp"
    compositor (C++/OpenMP, CPU, with the C++ projection and binning), the "torch" one (any
    device) and "gsplat" (gsplat's CUDA kernels, the default on CUDA: ``gsplat_backend`` lists
    what differs) agree to float rounding (tested). ``check_values=False`` skips the value scans
    (finite values, ranges, rigid cameras) for inputs the caller has checked (a training loop
    checks its parameters after every update); types and shapes are always checked.
    """
    s = resolve_settings(settings, overrides)
    extra = {"colors": colors} | ({"background": background} if background is not None else {})
    batch, N, C = ck.check_geometry(means, quats, scales, opacities, viewmats, Ks, width, height, extra)
    D, per_camera = ck.check_colors(colors, background, batch, N, C, sh_degree)
    if check_values:
        geometry = {"means": means, "quats": quats, "scales": scales, "opacities": opacities}
        ck.check_values(geometry | {"viewmats": viewmats, "Ks": Ks} | extra, scales, opacities)
    outputs = ck.check_outputs(outputs)
    want = set(outputs)
    if resolve_backend(s.backend, means.device) == "gsplat":
        why = unsupported(s, want, means, colors, Ks, sh_degree)
        if why is None:
            return rasterize_gsplat(means, quats, scales, opacities, colors, viewmats, Ks, width, height,
                                    sh_degree=sh_degree, background=background, want=want, settings=s,
                                    batch=batch, n_cameras=C)  # fmt: skip
        if s.backend == "gsplat":
            raise ValueError(f"backend: 'gsplat' cannot {why}; use backend='torch' or 'auto' for this render")
    p = _prepare(means, quats, scales, opacities, viewmats, Ks, width, height, batch, C, N, s)
    feats = colors
    if sh_degree is not None and "rgb" in want:
        feats, per_camera = sh_colors(sh_degree, colors, per_camera, means, viewmats, s.backend)
    elif sh_degree is not None:
        feats = colors[..., 0, :]  # SH is only evaluated for rgb; the other outputs ignore features
    return _composite_images(p, feats, per_camera, D, background, want)
