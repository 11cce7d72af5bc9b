"""Input checks at the public boundary of the splat renderer.

Every failure raises ``ValueError`` or ``TypeError`` naming the argument, what was
expected and what was given (see STYLE.md rule 13). Internal invariants use asserts.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

FLOAT_DTYPES = (torch.float32, torch.float64)


def check_tensor(name: str, x: object, *, finite: bool = True) -> Tensor:
    """Check that ``x`` is a floating tensor (float32/float64) with finite values."""
    if not isinstance(x, Tensor):
        raise TypeError(f"{name}: expected a torch.Tensor, got {type(x).__name__}")
    if x.dtype not in FLOAT_DTYPES:
        raise TypeError(f"{name}: expected dtype float32 or float64, got {x.dtype}")
    if finite and x.numel() > 0 and not bool(torch.isfinite(x).all()):
        n_bad = int((~torch.isfinite(x)).sum())
        raise ValueError(f"{name}: expected finite values, found {n_bad} NaN/Inf entries")
    return x


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
