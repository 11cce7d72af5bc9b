"""``rasterize``: the entry point of the splat renderer (project -> bin_tiles -> composite)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import NamedTuple

import torch
from jaxtyping import Bool, Float
from torch import Tensor

from . import _checks as ck
from .autograd import composite, resolve_backend
from .bin_tiles import TileBins, bin_tiles, bin_tiles_cpu
from .composite import BlendParams, Splats
from .project import Projection, project, project_cpu, view_dirs
from .sh import eval_sh, num_sh_bases

OUTPUTS = ("rgb", "alpha", "depth", "weight_sq", "means2d", "radii", "visible")


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


def _check_geometry(means, quats, scales, opacities, viewmats, Ks, width, height, extra: dict[str, Tensor]):
    """Types, devices, shapes and values of the geometry; returns (batch, N, C)."""
    tensors = {
        "means": means,
        "quats": quats,
        "scales": scales,
        "opacities": opacities,
        "viewmats": viewmats,
        "Ks": Ks,
        **extra,
    }
    for name, x in tensors.items():  # types first, then devices, then shapes, then values
        ck.check_tensor(name, x, finite=False)
    ck.check_same(tensors)
    if means.dim() < 2 or means.shape[-1] != 3:
        raise ValueError(f"means: expected shape [*B, N, 3], got {list(means.shape)}")
    batch = tuple(means.shape[:-2])
    N = means.shape[-2]
    ck.check_shape("quats", quats, (N, 4), batch)
    ck.check_shape("scales", scales, (N, 3), batch)
    ck.check_shape("opacities", opacities, (N,), batch)
    if viewmats.dim() != len(batch) + 3 or viewmats.shape[-2:] != (4, 4):
        raise ValueError(f"viewmats: expected shape [*B, C, 4, 4] with *B = {list(batch)}, got {list(viewmats.shape)}")
    ck.check_shape("viewmats", viewmats, ("C", 4, 4), batch)
    C = viewmats.shape[-3]
    if C < 1:
        raise ValueError(f"viewmats: expected at least one camera, got shape {list(viewmats.shape)}")
    ck.check_shape("Ks", Ks, (C, 3, 3), batch)
    ck.check_size("width", width)
    ck.check_size("height", height)
    return batch, N, C


def _check_values(tensors: dict[str, Tensor], scales: Tensor | None, opacities: Tensor | None) -> None:
    for name, x in tensors.items():
        ck.check_tensor(name, x, finite=True)
    if scales is not None and scales.numel() and bool((scales < 0).any()):
        raise ValueError("scales: expected non-negative linear scales (pass exp(log_scales))")
    if opacities is not None and opacities.numel() and bool(((opacities < 0) | (opacities > 1)).any()):
        raise ValueError("opacities: expected values in [0, 1] (pass sigmoid(logits))")
    if "viewmats" in tensors and "Ks" in tensors:
        _check_cameras(tensors["viewmats"], tensors["Ks"])


def _check_cameras(viewmats: Tensor, Ks: Tensor, tol: float = 1e-3) -> None:
    """World-to-camera matrices must be rigid ([R t; 0 1], R a rotation to ``tol``) and the
    intrinsics a pinhole with positive focal lengths (pixel units)."""
    if not viewmats.numel():
        return
    f = torch.stack([Ks[..., 0, 0], Ks[..., 1, 1]], -1)
    if bool((f <= 0).any()):
        raise ValueError(f"Ks: expected positive focal lengths fx, fy (pixels), got minimum {float(f.min()):g}")
    R = viewmats[..., :3, :3].double()
    eye = torch.eye(3, dtype=R.dtype, device=R.device)
    ortho = float((R @ R.transpose(-1, -2) - eye).abs().amax())
    det = torch.linalg.det(R)
    if ortho > tol or bool(((det - 1).abs() > tol).any()):
        raise ValueError(
            "viewmats: expected world-to-camera rigid transforms whose 3x3 block is a rotation "
            f"(R R^T = I, det R = 1; got max |R R^T - I| = {ortho:.3g}, det R in "
            f"[{float(det.min()):.3g}, {float(det.max()):.3g}])"
        )
    bottom = viewmats[..., 3, :].double()
    want = torch.tensor([0.0, 0.0, 0.0, 1.0], dtype=bottom.dtype, device=bottom.device)
    if float((bottom - want).abs().amax()) > tol:
        raise ValueError("viewmats: expected the last row [0, 0, 0, 1]")


def _check_colors(colors, background, batch, N, C, sh_degree) -> tuple[int, bool]:
    """Shape of colours / SH coefficients and background; returns (D, per_camera)."""
    sh = sh_degree is not None
    if sh and sh_degree not in (0, 1, 2, 3):
        raise ValueError(f"sh_degree: expected None or 0..3, got {sh_degree}")
    tail = 3 if sh else 2  # [N, K, D] or [N, D]
    if colors.dim() == len(batch) + tail:
        per_camera = False
    elif colors.dim() == len(batch) + tail + 1:
        per_camera = True
    else:
        want = "[*B, (C,) N, K, D]" if sh else "[*B, (C,) N, D]"
        raise ValueError(f"colors: expected shape {want} with *B = {list(batch)}, got {list(colors.shape)}")
    lead = batch + ((C,) if per_camera else ())
    if sh:
        K = num_sh_bases(sh_degree)
        if colors.shape[-2] < K:
            raise ValueError(f"colors: sh_degree={sh_degree} needs K >= {K} SH coefficients, got {colors.shape[-2]}")
        ck.check_shape("colors", colors, (N, "K", "D"), lead)
    else:
        ck.check_shape("colors", colors, (N, "D"), lead)
    D = colors.shape[-1]
    if background is not None and background.shape != (D,):
        ck.check_shape("background", background, (C, D), batch)
    return D, per_camera


def check_settings(near_plane, far_plane, eps2d, alpha_min, alpha_max, t_min, outputs) -> tuple[str, ...]:
    ck.check_range("near_plane", near_plane, 0.0, float("inf"), lo_open=True)
    ck.check_range("far_plane", far_plane, near_plane, float("inf"), lo_open=True)
    ck.check_range("eps2d", eps2d, 0.0, float("inf"))
    ck.check_range("alpha_min", alpha_min, 0.0, 1.0, lo_open=True)
    ck.check_range("alpha_max", alpha_max, alpha_min, 1.0, lo_open=True)
    if alpha_max >= 1.0:
        raise ValueError(f"alpha_max: expected a value below 1 (T would reach 0), got {alpha_max}")
    ck.check_range("t_min", t_min, 0.0, 1.0)
    if isinstance(outputs, str) or not isinstance(outputs, Sequence):
        raise TypeError(f"outputs: expected a tuple of names from {OUTPUTS}, got {outputs!r}")
    bad = [o for o in outputs if o not in OUTPUTS]
    if bad:
        raise ValueError(f"outputs: unknown names {bad}; expected names from {OUTPUTS}")
    return tuple(outputs)


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
    blend: BlendParams
    chunk_budget: int
    backend: str


def _prepare(
    means,
    quats,
    scales,
    opacities,
    viewmats,
    Ks,
    width,
    height,
    batch,
    C,
    N,
    *,
    near_plane,
    far_plane,
    eps2d,
    alpha_min,
    alpha_max,
    t_min,
    tile_size,
    chunk_budget,
    backend,
) -> Prepared:
    # the C++ projection and binning go with the C++ compositor (CPU); they give no gradients for
    # the cameras, so cameras that need them take the torch path
    fused = resolve_backend(backend, means.device) == "cpp" and not (viewmats.requires_grad or Ks.requires_grad)
    proj = (project_cpu if fused else project)(
        means,
        quats,
        scales,
        opacities,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        alpha_min=alpha_min,
    )
    I = C * int(torch.Size(batch).numel())
    bins = (bin_tiles_cpu if fused else bin_tiles)(
        proj.means2d.detach().reshape(I, N, 2),
        proj.radii.reshape(I, N, 2),
        proj.depths.detach().reshape(I, N),
        proj.visible.reshape(I, N),
        width,
        height,
        tile_size,
    )
    opac = opacities[..., None, :].expand(batch + (C, N)).reshape(I * N)
    blend = BlendParams(alpha_min, alpha_max, t_min)
    return Prepared(proj, bins, opac, batch, C, N, width, height, blend, chunk_budget, backend)


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
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    alpha_min: float = 1.0 / 255.0,
    alpha_max: float = 0.99,
    t_min: float = 1e-4,
    tile_size: int = 16,
    chunk_budget: int = 1 << 22,
    backend: str = "auto",
    check_values: bool = True,
) -> Prepared:
    """Project and bin once; then ``composite_features(prepared, features)`` per feature set.

    Same arguments and checks as ``rasterize`` minus the colours. ``check_values=False``
    skips the value scans (finite, ranges) for geometry that was checked before, such as a
    fixed noise cloud rendered every step; types and shapes are always checked.
    """
    batch, N, C = _check_geometry(means, quats, scales, opacities, viewmats, Ks, width, height, {})
    check_settings(near_plane, far_plane, eps2d, alpha_min, alpha_max, t_min, ())
    if check_values:
        _check_values(
            {"means": means, "quats": quats, "scales": scales, "opacities": opacities, "viewmats": viewmats, "Ks": Ks},
            scales,
            opacities,
        )
    ck.check_size("tile_size", tile_size)
    ck.check_size("chunk_budget", chunk_budget)
    resolve_backend(backend, means.device)
    return _prepare(
        means,
        quats,
        scales,
        opacities,
        viewmats,
        Ks,
        width,
        height,
        batch,
        C,
        N,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        alpha_min=alpha_min,
        alpha_max=alpha_max,
        t_min=t_min,
        tile_size=tile_size,
        chunk_budget=chunk_budget,
        backend=backend,
    )


def composite_features(
    prepared: Prepared,
    features: Tensor,
    *,
    background: Tensor | None = None,
    outputs: Sequence[str] = ("rgb", "alpha"),
) -> RenderOutput:
    """Blend per-Gaussian features ``[*B, (C,) N, D]`` over a ``prepare``d projection."""
    p = prepared
    outputs = check_settings(0.01, 1e10, 0.0, p.blend.alpha_min, p.blend.alpha_max, p.blend.t_min, outputs)
    ck.check_tensor("features", features, finite=False)
    if background is not None:
        ck.check_tensor("background", background, finite=False)
    D, per_camera = _check_colors(features, background, p.batch, p.n, p.n_cameras, None)
    extra = {"features": features} | ({"background": background} if background is not None else {})
    ck.check_same({"means2d": p.projection.means2d, **extra})
    _check_values(extra, None, None)
    return _composite_images(p, features, per_camera, D, background, set(outputs))


def _composite_images(p: Prepared, feats: Tensor, per_camera: bool, D: int, background, want: set) -> RenderOutput:
    batch, C, N, width, height = p.batch, p.n_cameras, p.n, p.width, p.height
    proj, bins = p.projection, p.bins
    result = {
        "means2d": proj.means2d if "means2d" in want else None,
        "radii": proj.radii if "radii" in want else None,
        "visible": proj.visible if "visible" in want else None,
    }
    if not want & {"rgb", "alpha", "depth", "weight_sq"}:
        return RenderOutput(**result)
    I = C * int(torch.Size(batch).numel())
    feats = feats if per_camera else feats[..., None, :, :].expand(batch + (C, N, D))
    flat = Splats(
        proj.means2d.reshape(I * N, 2),
        proj.conics.reshape(I * N, 3),
        p.opacities,
        feats.reshape(I * N, D),
        proj.depths.reshape(I * N),
    )
    out = composite(
        flat,
        bins,
        I,
        p.blend,
        features="rgb" in want,
        depth="depth" in want,
        weight_sq="weight_sq" in want,
        budget=p.chunk_budget,
        backend=p.backend,
    )

    def untile(x: Tensor) -> Tensor:
        ts = bins.tile_size
        x = x.reshape(I, bins.tiles_y, bins.tiles_x, ts, ts, -1).permute(0, 1, 3, 2, 4, 5)
        x = x.reshape(I, bins.tiles_y * ts, bins.tiles_x * ts, -1)[:, :height, :width]
        return x.reshape(batch + (C, height, width, x.shape[-1]))

    T = untile(out.transmittance)
    alpha = 1.0 - T
    if "rgb" in want:
        rgb = untile(out.features)
        if background is not None:
            bg = background if background.dim() == 1 else background[..., None, None, :]
            rgb = rgb + T * bg
        result["rgb"] = rgb
    if "alpha" in want:
        result["alpha"] = alpha
    if "depth" in want:
        acc = untile(out.depth)
        covered = alpha > 0
        safe = torch.where(covered, alpha, torch.ones_like(alpha))
        result["depth"] = torch.where(covered, acc / safe, torch.zeros_like(acc))
    if "weight_sq" in want:
        result["weight_sq"] = untile(out.weight_sq)
    return RenderOutput(**result)


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
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    alpha_min: float = 1.0 / 255.0,
    alpha_max: float = 0.99,
    t_min: float = 1e-4,
    outputs: Sequence[str] = ("rgb", "alpha"),
    tile_size: int = 16,
    chunk_budget: int = 1 << 22,
    backend: str = "auto",
    check_values: bool = True,
) -> RenderOutput:
    """Render N 3D Gaussians into C cameras with the 3DGS image formation model.

    Inputs are activated values: linear ``scales`` (>= 0), ``opacities`` in [0, 1],
    quaternions wxyz (any norm; zero means identity). ``colors`` is ``[*B, (C,) N, D]``
    plain features, or with ``sh_degree`` set, ``[*B, (C,) N, K, D]`` SH coefficients
    evaluated along the camera-to-mean direction (``renderers.splat.sh``).
    ``background`` is ``[D]`` or ``[*B, C, D]`` (default: none, i.e. black).

    The model and its constants are in ``composite.py`` and ``project.py`` and in
    docs/renderer.md; the camera conventions in docs/conventions.md. Only the outputs
    named in ``outputs`` are computed (see ``OUTPUTS``). Images are [*B, C, H, W, ...].
    ``chunk_budget`` bounds the elements of one compositing chunk of the torch backend
    (memory, not results). ``backend`` picks the compositor: "cpp" (C++/OpenMP, CPU),
    "torch" (any device) or "auto" (cpp on CPU when it builds, else torch); the two agree
    to float rounding (tested). ``check_values=False`` skips the value scans (finite values,
    ranges, rigid cameras) for inputs the caller has checked (a training loop checks its
    parameters after every update); types and shapes are always checked.
    """
    extra = {"colors": colors} | ({"background": background} if background is not None else {})
    batch, N, C = _check_geometry(means, quats, scales, opacities, viewmats, Ks, width, height, extra)
    D, per_camera = _check_colors(colors, background, batch, N, C, sh_degree)
    if check_values:
        _check_values(
            {
                "means": means,
                "quats": quats,
                "scales": scales,
                "opacities": opacities,
                "viewmats": viewmats,
                "Ks": Ks,
                **extra,
            },
            scales,
            opacities,
        )
    outputs = check_settings(near_plane, far_plane, eps2d, alpha_min, alpha_max, t_min, outputs)
    ck.check_size("tile_size", tile_size)
    ck.check_size("chunk_budget", chunk_budget)
    resolve_backend(backend, means.device)
    want = set(outputs)
    p = _prepare(
        means,
        quats,
        scales,
        opacities,
        viewmats,
        Ks,
        width,
        height,
        batch,
        C,
        N,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        alpha_min=alpha_min,
        alpha_max=alpha_max,
        t_min=t_min,
        tile_size=tile_size,
        chunk_budget=chunk_budget,
        backend=backend,
    )
    feats = colors
    if sh_degree is not None and "rgb" in want:
        coeffs = colors if per_camera else colors[..., None, :, :, :].expand(batch + (C, N) + colors.shape[-2:])
        feats, per_camera = eval_sh(sh_degree, coeffs, view_dirs(means, viewmats)), True
    elif sh_degree is not None:
        feats = colors[..., 0, :]  # SH is only evaluated for rgb; the other outputs ignore features
    return _composite_images(p, feats, per_camera, D, background, want)
