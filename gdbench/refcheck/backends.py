"""One registry of renderer backends, used by ``gdbench compare``, every benchmark and the tests
(the ``backend`` fixture in tests/conftest.py).

Each backend has one name, a render function with ``renderers.splat.rasterize``'s signature
(imported lazily), a way to tell whether it can run here (and what to install if not), and the
settings that make it comparable with the splat renderer and its float64 twin: the alpha clamp
it uses (gsplat clamps at 0.999), and for Monte Carlo renderers the samples per pixel, once for
accuracy comparisons and once for speed.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass(frozen=True)
class Backend:
    name: str
    what: str
    alpha_max: float = 0.99
    """The alpha clamp the backend applies: the twin is run with the same one when comparing."""
    comparable: dict = field(default_factory=dict)
    """Keywords of ``render`` for accuracy comparisons (compare, stability)."""
    fast: dict = field(default_factory=dict)
    """Keywords of ``render`` for speed benchmarks (fewer samples where that is a choice)."""
    tolerance: str = "exact"
    """Its conformance class (``tolerance.CLASSES``): an exact float32 rasterizer of gdbench's image
    model, or an approximate one (another image model: the ray-traced ellipsoids)."""
    differentiable: bool = True
    images: bool = True
    """False for backends that only check cameras (pyrender draws the centres as points)."""

    @property
    def renders(self) -> bool:
        """Whether it has a ``rasterize``-signature render function (the volume references and
        the point renderer are driven by ``gdbench compare`` with their own arguments)."""
        return self.name in _RENDER

    def render(self, *args, speed: bool = False, **kwargs):
        """Render with ``rasterize``'s signature (and this backend's comparable or fast options)."""
        return _RENDER[self.name]()(*args, **((self.fast if speed else self.comparable) | kwargs))

    def available(self) -> tuple[bool, str]:
        """(True, '') when the backend can run on this machine, else (False, what to install)."""
        try:
            return _AVAILABLE.get(self.name, lambda: (True, ""))()
        except ImportError as e:
            return False, str(e).splitlines()[0]


def _splat(backend: str) -> Callable:
    from renderers.splat import rasterize

    return lambda *a, **k: rasterize(*a, **k, backend=backend)


def on_device(fn: Callable, device) -> Callable:
    """``fn`` (``rasterize``'s signature) on ``device`` copies of its CPU tensors, its outputs back on
    the first tensor argument's device; the copies are in the graph, so gradients reach the callers'
    tensors (the ``gsplat_cuda`` backend; ``pytest --device cuda``'s renderer tests)."""

    def wrapped(*args, **kwargs):
        import torch

        from renderers.splat import RenderOutput

        home = next(x.device for x in (*args, *kwargs.values()) if isinstance(x, torch.Tensor))
        move = lambda x: x.to(device) if isinstance(x, torch.Tensor) and x.device.type == "cpu" else x  # noqa: E731
        out = fn(*map(move, args), **{k: move(v) for k, v in kwargs.items()})
        return RenderOutput(*(x.to(home) if x is not None else None for x in out))

    return wrapped


def _gsplat_cuda_available() -> tuple[bool, str]:
    from renderers.splat.gsplat_backend import gsplat_status

    return gsplat_status()


def _gsplat() -> Callable:
    from renderers.gsplat_torch import rasterize

    return rasterize


def _mitsuba() -> Callable:
    from renderers.mitsuba.ellipsoids import rasterize

    return rasterize


def _mitsuba_available() -> tuple[bool, str]:
    from renderers.mitsuba._lib import available

    return available()


def _gsplat_available() -> tuple[bool, str]:
    import gsplat.cuda._torch_impl  # noqa: F401

    return True, ""


def _pyrender_available() -> tuple[bool, str]:
    from renderers.pyrender_points._lib import available

    return available()


def _splat_cpp_available() -> tuple[bool, str]:
    from renderers.splat._ext import extension_status, load_extension

    return (load_extension() is not None), extension_status()


_RENDER: dict[str, Callable[[], Callable]] = {
    "splat": lambda: _splat("cpp"),
    "splat_torch": lambda: _splat("torch"),
    "gsplat_torch": _gsplat,
    "gsplat_cuda": lambda: on_device(_splat("gsplat"), "cuda"),
    "mitsuba_ellipsoids": _mitsuba,
}
_AVAILABLE: dict[str, Callable[[], tuple[bool, str]]] = {
    "splat": _splat_cpp_available,
    "gsplat_torch": _gsplat_available,
    "gsplat_cuda": _gsplat_cuda_available,
    "mitsuba_ellipsoids": _mitsuba_available,
    "mitsuba_volume_grid": _mitsuba_available,
    "mitsuba_volume_analytic": _mitsuba_available,
    "pyrender_points": _pyrender_available,
}

BACKENDS: dict[str, Backend] = {
    b.name: b
    for b in (
        Backend("splat", "the splat renderer with its C++ CPU path (projection, binning, compositing)"),
        Backend("splat_torch", "the splat renderer's pure-torch path (any device)"),
        Backend("gsplat_torch", "gsplat 1.5.3's torch stages, completed on CPU", alpha_max=0.999),
        Backend(
            "gsplat_cuda",
            "the splat renderer on gsplat 1.5.3's CUDA kernels (the default on CUDA), inputs moved to the GPU",
            alpha_max=0.999,
            comparable={"alpha_max": 0.999},
            fast={"alpha_max": 0.999},
        ),
        Backend(
            "mitsuba_ellipsoids",
            "Mitsuba 3 ray-traced ellipsoids (volprim_rf_basic)",
            comparable={"spp": 16},
            fast={"spp": 4},
            tolerance="approximate",
        ),
        Backend("mitsuba_volume_grid", "exact emission-absorption volume, grid field (Mitsuba)"),
        Backend("mitsuba_volume_analytic", "exact emission-absorption volume, analytic field (Mitsuba)"),
        Backend(
            "pyrender_points", "Gaussian centres as OpenGL points (cameras only)", differentiable=False, images=False
        ),
    )
}
"""Every renderer gdbench runs, by its one name."""


def get(name: str) -> Backend:
    if name not in BACKENDS:
        raise ValueError(f"backend: unknown {name!r}; expected one of {sorted(BACKENDS)}")
    return BACKENDS[name]
