"""Input checks at the public boundary of the splat renderer.

Every failure raises ``ValueError`` or ``TypeError`` naming the argument, what was
expected and what was given. Internal invariants use asserts.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import torch
from torch import Tensor

from .sh import num_sh_bases

FLOAT_DTYPES = (torch.float32, torch.float64)


def check_tensor(name: str, x: object, *, finite: bool = True) -> Tensor:
    """Check that ``x`` is a floating tensor (float32/float64) with finite values."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{name}: expected dtype float32 or float64, got {x.dtype}")
    if finite and x.numel() > 0 and not all_finite(x):
        n_bad = int((~torch.isfinite(x)).sum())
        raise ValueError(f"{name}: expected finite values, found {n_bad} NaN/Inf entries")
    return x


def all_finite(x: Tensor) -> bool:
    """Whether every entry is finite. A finite sum proves it in one reduction (NaN and Inf
    propagate through a sum); only a non-finite sum (or an overflow) looks entry by entry.
    CPU tensors are read through numpy (the same data, no copy): a fifth of torch's per-call
    cost on the small tensors a render checks (~6 against ~30 us)."""
    x = x.detach()
    if x.device.type == "cpu":
        a = x.numpy()
        return bool(np.isfinite(a.sum())) or bool(np.isfinite(a).all())
    return bool(torch.isfinite(x.sum())) or bool(torch.isfinite(x).all())


def check_shape(name: str, x: Tensor, expected: Sequence[int | str], batch: tuple[int, ...] | None = None) -> None:
    """Check ``x.shape == batch + expected``; string entries in ``expected`` are free sizes.

    Raises ValueError with the expected and actual shape.
    """
    lead = batch if batch is not None else tuple(x.shape[: x.dim() - len(expected)])
    want = tuple(lead) + tuple(expected)
    ok = x.dim() == len(want) and all(
        isinstance(w, str) or int(w) == int(s) for w, s in zip(want, x.shape, strict=True)
    )
    if not ok:
        shown = "[" + ", ".join(str(w) for w in want) + "]"
        raise ValueError(f"{name}: expected shape {shown}, got {list(x.shape)}")


def check_same(tensors: dict[str, Tensor]) -> tuple[torch.dtype, torch.device]:
    """All tensors share one dtype and one device; name the first one that differs."""
    items = list(tensors.items())
    first_name, first = items[0]
    for name, t in items[1:]:
        if t.device != first.device:
            raise ValueError(f"{name}: expected device {first.device} (the device of {first_name}), got {t.device}")
        if t.dtype != first.dtype:
            raise TypeError(f"{name}: expected dtype {first.dtype} (the dtype of {first_name}), got {t.dtype}")
    return first.dtype, first.device


def check_size(name: str, value: object, minimum: int = 1) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise TypeError(f"{name}: expected an int, got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{name}: expected an int >= {minimum}, got {value}")
    return value


def check_range(name: str, value: float, lo: float, hi: float, *, lo_open: bool = False) -> float:
    if not isinstance(value, (int, float)) or isinstance(value, bool):
        raise TypeError(f"{name}: expected a float, got {type(value).__name__}")
    value = float(value)
    bad_lo = value <= lo if lo_open else value < lo
    if bad_lo or value > hi:
        left = "(" if lo_open else "["
        raise ValueError(f"{name}: expected a value in {left}{lo}, {hi}], got {value}")
    return value


OUTPUTS = ("rgb", "alpha", "depth", "weight_sq", "means2d", "radii", "visible")
"""Everything the renderer can return (``RenderOutput``'s fields)."""


def check_outputs(outputs) -> tuple[str, ...]:
    if isinstance(outputs, str) or not isinstance(outputs, Sequence):
        raise TypeError(f"outputs: expected a tuple of names from {OUTPUTS}, got {outputs!r}")
    bad = [o for o in outputs if o not in OUTPUTS]
    if bad:
        raise ValueError(f"outputs: unknown names {bad}; expected names from {OUTPUTS}")
    return tuple(outputs)


def check_geometry(means, quats, scales, opacities, viewmats, Ks, width, height, extra: dict[str, Tensor]):
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
        check_tensor(name, x, finite=False)
    check_same(tensors)
    if means.dim() < 2 or means.shape[-1] != 3:
        raise ValueError(f"means: expected shape [*B, N, 3], got {list(means.shape)}")
    batch = tuple(means.shape[:-2])
    N = means.shape[-2]
    check_shape("quats", quats, (N, 4), batch)
    check_shape("scales", scales, (N, 3), batch)
    check_shape("opacities", opacities, (N,), batch)
    if viewmats.dim() != len(batch) + 3 or viewmats.shape[-2:] != (4, 4):
        raise ValueError(f"viewmats: expected shape [*B, C, 4, 4] with *B = {list(batch)}, got {list(viewmats.shape)}")
    check_shape("viewmats", viewmats, ("C", 4, 4), batch)
    C = viewmats.shape[-3]
    if C < 1:
        raise ValueError(f"viewmats: expected at least one camera, got shape {list(viewmats.shape)}")
    check_shape("Ks", Ks, (C, 3, 3), batch)
    check_size("width", width)
    check_size("height", height)
    return batch, N, C


def check_values(tensors: dict[str, Tensor], scales: Tensor | None, opacities: Tensor | None) -> None:
    """Finite values everywhere, non-negative linear scales, opacities in [0, 1], rigid cameras
    with positive focal lengths (when ``viewmats`` and ``Ks`` are among ``tensors``)."""
    for name, x in tensors.items():
        check_tensor(name, x, finite=True)
    if scales is not None and scales.numel() and float(scales.detach().min()) < 0:
        raise ValueError("scales: expected non-negative linear scales (pass exp(log_scales))")
    if opacities is not None and opacities.numel():
        lo, hi = (float(v) for v in torch.aminmax(opacities.detach()))
        if lo < 0 or hi > 1:
            raise ValueError("opacities: expected values in [0, 1] (pass sigmoid(logits))")
    if "viewmats" in tensors and "Ks" in tensors:
        check_cameras(tensors["viewmats"], tensors["Ks"])


def check_cameras(viewmats: Tensor, Ks: Tensor, tol: float = 1e-3) -> None:
    """World-to-camera matrices must be rigid ([R t; 0 1], R a rotation to ``tol``) and the
    intrinsics a pinhole with positive focal lengths (pixel units)."""
    if not viewmats.numel():
        return
    # in float64 numpy on the host: a few small arrays, where torch's per-operation cost made this
    # check a fraction of a millisecond of every render (no graph, no scalar-from-grad warnings)
    viewmats = viewmats.detach().cpu().double().numpy()
    Ks = Ks.detach().cpu().double().numpy()
    f = np.stack([Ks[..., 0, 0], Ks[..., 1, 1]], -1)
    if bool((f <= 0).any()):
        raise ValueError(f"Ks: expected positive focal lengths fx, fy (pixels), got minimum {float(f.min()):g}")
    # a pinhole: [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]; skew or another third row would be
    # rendered as if it were one
    off = np.stack([Ks[..., 0, 1], Ks[..., 1, 0], Ks[..., 2, 0], Ks[..., 2, 1], Ks[..., 2, 2] - 1], -1)
    if not np.isfinite(Ks).all() or float(np.abs(off).max()) > 1e-6:
        raise ValueError(
            "Ks: expected pinhole intrinsics [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] (no skew, third row "
            f"[0, 0, 1]); got max deviation {float(np.nan_to_num(np.abs(off), nan=np.inf).max()):.3g}"
        )
    R = viewmats[..., :3, :3]
    ortho = float(np.abs(R @ np.swapaxes(R, -1, -2) - np.eye(3)).max())
    a, b = [1, 2, 0], [2, 0, 1]  # the triple product R0 . (R1 x R2) (np.cross costs 30 us)
    det = (R[..., 0, :] * (R[..., 1, a] * R[..., 2, b] - R[..., 1, b] * R[..., 2, a])).sum(-1)
    if ortho > tol or float(np.abs(det - 1).max()) > tol:
        raise ValueError(
            "viewmats: expected world-to-camera rigid transforms whose 3x3 block is a rotation "
            f"(R R^T = I, det R = 1; got max |R R^T - I| = {ortho:.3g}, det R in "
            f"[{float(det.min()):.3g}, {float(det.max()):.3g}])"
        )
    if float(np.abs(viewmats[..., 3, :] - np.array([0.0, 0.0, 0.0, 1.0])).max()) > tol:
        raise ValueError("viewmats: expected the last row [0, 0, 0, 1]")


def check_colors(colors, background, batch, N, C, sh_degree) -> tuple[int, bool]:
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
        check_shape("colors", colors, (N, "K", "D"), lead)
    else:
        check_shape("colors", colors, (N, "D"), lead)
    D = colors.shape[-1]
    if D < 1:
        raise ValueError(f"colors: expected at least one channel (D >= 1), got shape {list(colors.shape)}")
    if background is not None and background.shape != (D,):
        check_shape("background", background, (C, D), batch)
    return D, per_camera
