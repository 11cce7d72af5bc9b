"""Where tensors live: ``resolve_device`` turns a ``--device`` choice into a ``torch.device``.

'cpu' is the reference everywhere (the C++ compositor, results that reproduce bit for bit);
'cuda' renders on the GPU with gsplat's CUDA kernels (``renderers.splat.gsplat_backend``; the
torch path for what they cannot give, such as structured noise's weights, or where they do not
build); 'auto' is CUDA when torch sees one. Random draws stay on the CPU's generators on every
device (``gdbench.core.rand``), so a run on CUDA draws the same views, noise levels and noise as the
same run on the CPU; its results differ by float rounding and by gsplat's alpha clamp, and
follow the CPU's in distribution (docs/renderer.md, "On a GPU").
"""

from __future__ import annotations

import torch

CHOICES = ("cpu", "cuda", "auto")


def resolve_device(name: str | torch.device, what: str = "device") -> torch.device:
    """``torch.device`` of ``name`` ('cpu', 'cuda', 'cuda:N' or 'auto'); CUDA asked for where torch
    sees none raises a ValueError naming ``what``."""
    if isinstance(name, torch.device):
        name = str(name)
    if not isinstance(name, str):
        raise ValueError(f"{what}: expected one of {CHOICES}, got {name!r}")
    if name == "auto":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        dev = torch.device(name)
    except RuntimeError:
        raise ValueError(f"{what}: expected one of {CHOICES} (or 'cuda:N'), got {name!r}") from None
    if dev.type not in ("cpu", "cuda") or (dev.type == "cpu" and dev.index not in (None, 0)):
        raise ValueError(f"{what}: expected one of {CHOICES} (or 'cuda:N'), got {name!r}")
    if dev.type == "cuda":
        if not torch.cuda.is_available():
            raise ValueError(
                f"{what}: {name!r} asked for, but torch sees no CUDA device (torch {torch.__version__}; "
                "a CUDA build of torch and an NVIDIA driver are needed)"
            )
        if dev.index is not None and dev.index >= torch.cuda.device_count():
            raise ValueError(f"{what}: {name!r} asked for, but torch sees {torch.cuda.device_count()} CUDA device(s)")
    return dev
