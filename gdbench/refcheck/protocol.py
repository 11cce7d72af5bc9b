"""Bring your own renderer: the one call shape gdbench renders with, what must come back, and how a
renderer written elsewhere enters the comparisons (docs/references.md, "Bring your own renderer").

A renderer is a function with ``renderers.splat.rasterize``'s shape::

    fn(means, quats, scales, opacities, colors, viewmats, Ks, width, height, *,
       background=None, outputs=("rgb", "alpha")) -> an object with .rgb and .alpha (.depth optional)

- ``means`` [N, 3], ``quats`` [N, 4] (wxyz, any norm; zero means identity), ``scales`` [N, 3]
  (linear, not log), ``opacities`` [N] in [0, 1]: float32 tensors on the renderer's device;
- ``colors``: [N, 3] RGB in [0, 1] (``colors="rgb"``, the default) or [N, 1, 3] SH degree-0
  coefficients (``colors="sh0"``: rgb = 0.5 + 0.2820948 * c);
- ``viewmats`` [C, 4, 4] world-to-camera (OpenCV axes: x right, y down, z forward), ``Ks`` [C, 3, 3]
  pixel intrinsics with pixel centres at +0.5, ``width``, ``height``: ints;
- ``background`` [3] or None (black); ``outputs`` names what to compute ("depth": the expected
  depth, only where the renderer declares ``depth=True``);
- it returns ``rgb`` [C, H, W, 3] and ``alpha`` [C, H, W, 1] (and ``depth`` [C, H, W, 1]) as float
  tensors, differentiable through torch autograd where the renderer declares ``gradients=True``.

A renderer enters by ``module:function`` on the command line (``gdbench compare --renderer
pkg.mod:fn``), the function either the renderer itself (the defaults above) or a ``RendererSpec``
that says what it supports, or by ``register_renderer(name, fn, ...)`` in Python. No private
table is touched: the built-in backends keep their own registry (``backends.BACKENDS``).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import Literal

C0 = 0.28209479177387814
"""The SH degree-0 basis constant: rgb = 0.5 + C0 * c."""


@dataclass(frozen=True)
class RendererSpec:
    """A renderer and what it supports; what it does not support is skipped, not failed."""

    name: str
    fn: Callable
    colors: Literal["rgb", "sh0"] = "rgb"
    """How colours arrive: RGB [N, 3], or SH degree-0 coefficients [N, 1, 3]."""
    device: Literal["cpu", "cuda"] = "cpu"
    """Where its inputs live (a CUDA renderer's cases are skipped where there is no CUDA)."""
    gradients: bool = True
    """Whether its outputs carry gradients to the inputs through torch autograd."""
    depth: bool = False
    """Whether it renders the expected depth."""
    tolerance: Literal["exact", "approximate"] = "exact"
    """Its tolerance class: an exact float32 rasterizer (the fixtures' tolerance against the float64
    twin), or an approximate one (a ray tracer, a point splatter: compared, not judged)."""
    alpha_max: float = 0.99
    """The alpha clamp it applies: the twin is run with the same one."""
    unavailable: str = ""
    """Why it cannot run on this machine (what to install): every case is a SKIP with this reason."""

    def __post_init__(self) -> None:
        if not callable(self.fn):
            raise ValueError(f"renderer {self.name!r}: expected a callable, got {type(self.fn).__name__}")
        if self.colors not in ("rgb", "sh0") or self.device not in ("cpu", "cuda"):
            raise ValueError(
                f"renderer {self.name!r}: colors must be 'rgb' or 'sh0' and device 'cpu' or 'cuda', "
                f"got {self.colors!r} and {self.device!r}"
            )
        if self.tolerance not in ("exact", "approximate") or not 0 < self.alpha_max <= 1:
            raise ValueError(
                f"renderer {self.name!r}: tolerance must be 'exact' or 'approximate' and alpha_max in (0, 1], "
                f"got {self.tolerance!r} and {self.alpha_max!r}"
            )

    def why_not(self, sh_degree: int, want_depth: bool = False) -> str | None:
        """Why this renderer cannot run a case (a SKIP with the reason), or None."""
        if self.unavailable:
            return f"renderer {self.name!r} is not available here: {self.unavailable}"
        if sh_degree > 0:
            return f"renderer {self.name!r} takes SH degree 0 colours; the case has degree {sh_degree}"
        if want_depth and not self.depth:
            return f"renderer {self.name!r} declares no depth"
        if self.device == "cuda":
            import torch

            if not torch.cuda.is_available():
                return f"renderer {self.name!r} runs on CUDA; this machine has none"
        return None

    def render(self, means, quats, scales, opacities, sh, viewmats, Ks, width, height, *, background=None,
               outputs=("rgb", "alpha")):  # fmt: skip
        """Call the renderer with gdbench's scene (``sh``: [N, K, 3] coefficients, degree 0 here)
        converted to its colours and device; the outputs back on the inputs' device, checked (a
        wrong shape, dtype or a missing output is a ValueError naming the renderer)."""
        import torch

        home = means.device
        colors = sh[:, :1] if self.colors == "sh0" else 0.5 + C0 * sh[:, 0]
        dev = torch.device(self.device)
        move = lambda x: x.to(dev) if isinstance(x, torch.Tensor) else x  # noqa: E731
        args = [move(x) for x in (means, quats, scales, opacities, colors, viewmats, Ks)]
        out = self.fn(*args, width, height, background=move(background), outputs=tuple(outputs))
        C = viewmats.shape[0]
        for name, channels in (("rgb", 3), ("alpha", 1), ("depth", 1)):
            if name not in outputs:
                continue
            x = getattr(out, name, None)
            if not isinstance(x, torch.Tensor):
                raise ValueError(f"renderer {self.name!r}: returned no {name} tensor (got {type(x).__name__})")
            if tuple(x.shape) != (C, height, width, channels) or not x.is_floating_point():
                raise ValueError(
                    f"renderer {self.name!r}: {name} should be a float tensor [{C}, {height}, {width}, {channels}], "
                    f"got {x.dtype} {tuple(x.shape)}"
                )
        return {k: getattr(out, k).to(home) for k in outputs}


REGISTERED: dict[str, RendererSpec] = {}
"""Renderers registered in this process (``register_renderer``), by name."""


def register_renderer(name: str, fn: Callable, **spec) -> RendererSpec:
    """Register a renderer under ``name`` (not a built-in backend's) with what it supports
    (``RendererSpec``'s fields); returns its spec. Registering a name again replaces it."""
    from gdbench.refcheck.backends import BACKENDS

    if not isinstance(name, str) or not name or name in BACKENDS or ":" in name:
        raise ValueError(f"renderer name: expected a new name without ':', not a built-in backend's, got {name!r}")
    REGISTERED[name] = RendererSpec(name, fn, **spec)
    return REGISTERED[name]


def builtin(name: str) -> RendererSpec:
    """A built-in backend (``backends.BACKENDS``, one with ``rasterize``'s shape) as a renderer of
    the protocol: its comparable settings, alpha clamp, tolerance class and availability here."""
    from gdbench.refcheck.backends import get

    b = get(name)
    if not b.renders:
        raise ValueError(f"renderer {name!r}: a built-in backend without rasterize's call shape (compare drives it); "
                         "expected splat, splat_torch, gsplat_torch, gsplat_cuda or mitsuba_ellipsoids")  # fmt: skip
    ok, why = b.available()
    return RendererSpec(name, b.render, gradients=b.differentiable, tolerance=b.tolerance, alpha_max=b.alpha_max,
                        unavailable="" if ok else (why or "not installed"))  # fmt: skip


def load_or_fail(ref: str) -> RendererSpec:
    """``load_renderer(ref)``, or where it cannot load, a renderer that fails every case with that
    one line (so that the other renderers still run and every case reports)."""
    try:
        return load_renderer(ref)
    except ValueError as e:
        message = str(e)

        def cannot(*args, **kwargs):
            raise ValueError(message)

        return RendererSpec(ref, cannot)


def load_renderer(ref: str) -> RendererSpec:
    """A renderer by a built-in or registered name, by ``module:function`` or by
    ``path/to/file.py:function`` (the function a renderer or a
        ``RendererSpec``); a reference that cannot be imported or is not callable is a one-line
        ValueError naming it."""
    if ref in REGISTERED:
        return REGISTERED[ref]
    from gdbench.refcheck.backends import BACKENDS

    if ref in BACKENDS and BACKENDS[ref].renders:
        return builtin(ref)
    from gdbench.core.imports import import_ref

    if ":" not in ref:
        raise ValueError(
            f"renderer {ref!r}: expected module:function (pkg.mod:fn), path/to/file.py:function or a registered name"
        )
    obj = import_ref(ref, "renderer")
    if isinstance(obj, RendererSpec):
        return obj
    if not callable(obj):
        raise ValueError(f"renderer {ref!r}: {ref.rpartition(':')[2]!r} is a {type(obj).__name__}, not a function")
    return RendererSpec(ref, obj)
