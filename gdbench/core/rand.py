"""Standard normal draws for the training step's hot paths (jitter, structured and iid noise).

``randn(shape, generator=g)`` is ``torch.randn`` with the same contract (an explicit generator,
the same numbers for the same generator state), faster on CPU: it takes one 63-bit key from
``g`` and fills the tensor with the C++ extension's counter-based Philox4x32-10 and Box-Muller
(``renderers/splat/csrc/normal_cpu.cpp``), which is cheaper per value than torch's CPU generator
(mt19937) and fills large tensors on every thread (docs/performance.md).

The numbers differ from torch.randn's for the same seed. A CUDA generator, a CPU without the
extension (``GDBENCH_SPLAT_BACKEND=torch`` or no compiler) and dtypes other than float32 and
float64 take ``torch.randn`` itself, so a run's numbers depend on which of the two paths it took;
either is reproducible on its own.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

_KEY_HIGH = 2**63 - 1


def randn(
    shape: Sequence[int] | torch.Size,
    *,
    generator: torch.Generator,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> Tensor:
    """Standard normals of ``shape`` drawn from ``generator`` (float32 unless ``dtype``; on the
    generator's device unless ``device``)."""
    if not isinstance(generator, torch.Generator):
        raise TypeError(f"generator: expected a torch.Generator, got {type(generator).__name__}")
    shape = tuple(int(s) for s in shape)
    if any(s < 0 for s in shape):
        raise ValueError(f"shape: expected sizes >= 0, got {list(shape)}")
    dtype = dtype or torch.get_default_dtype()
    gdev = generator.device
    dev = torch.device(device) if device is not None else gdev
    ext = _extension() if gdev.type == "cpu" and dtype in (torch.float32, torch.float64) else None
    if ext is None:
        return torch.randn(shape, generator=generator, dtype=dtype, device=gdev).to(dev)
    key = int(torch.randint(_KEY_HIGH, (1,), generator=generator))
    return ext.philox_normal(math.prod(shape), key).reshape(shape).to(device=dev, dtype=dtype)


def _extension():
    from renderers.splat._ext import load_extension

    return load_extension()
