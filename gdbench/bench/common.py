"""Shared pieces of the benchmarks: timing with warm-up and synchronisation, peak memory,
scene generators; CSV/JSON writing is ``gdbench.core.io``'s (re-exported here)."""

from __future__ import annotations

import math
import os
import platform
import resource
import statistics
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import torch

from gdbench.core.io import read_csv, write_csv, write_json  # noqa: F401  (the benchmarks' writers)


def sync(device: torch.device | str) -> None:
    if torch.device(device).type == "cuda":
        torch.cuda.synchronize()


def rss_mb() -> float:
    """Current resident set size of this process in MB (Linux /proc; 0 elsewhere)."""
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 2**20
    except OSError:
        return 0.0


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far in MB (ru_maxrss is in KB on Linux)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


def timeit(
    fn: Callable[[], object],
    *,
    device: torch.device | str = "cpu",
    warmup: int = 2,
    min_repeats: int = 3,
    max_repeats: int = 10,
    budget_s: float = 2.0,
) -> dict[str, float]:
    """Median and min wall time of ``fn`` after ``warmup`` calls, synchronising CUDA.

    Repeats until ``budget_s`` is spent (between ``min_repeats`` and ``max_repeats`` runs).
    """
    for _ in range(warmup):
        fn()
        sync(device)
    times: list[float] = []
    start = time.perf_counter()
    while len(times) < max_repeats and (len(times) < min_repeats or time.perf_counter() - start < budget_s):
        t0 = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - t0)
    return {"median_s": statistics.median(times), "min_s": min(times), "repeats": len(times)}


@contextmanager
def kernel_clock() -> Iterator[dict[str, list]]:
    """Wall seconds and calls of each function of the renderer's C++ extension while the block
    runs: yields ``{name: [seconds, calls]}``, filled as calls return. Every caller looks the
    extension's functions up at call time (``load_extension().f``), so each is swapped for a
    timed wrapper that passes arguments and results through, and put back on exit. The time
    inside them is the floor of any change to the Python and torch work around them.

    One clock at a time (a second one raises), for one thread: calls from other threads are
    counted too."""
    import functools

    from renderers.splat._ext import extension_status, load_extension

    module = load_extension()
    if module is None:
        raise RuntimeError(f"kernel_clock: the C++ extension is not available ({extension_status()})")
    if _CLOCK_OPEN:
        raise RuntimeError("kernel_clock: a clock is already running; clocks do not nest")
    totals: dict[str, list] = {}
    originals = {n: f for n in dir(module) if not n.startswith("_") and callable(f := getattr(module, n))}

    def timed(name: str, f: Callable) -> Callable:
        entry = totals.setdefault(name, [0.0, 0])

        @functools.wraps(f)
        def call(*args, **kwargs):
            t0 = time.perf_counter()
            try:
                return f(*args, **kwargs)
            finally:
                entry[0] += time.perf_counter() - t0
                entry[1] += 1

        return call

    _CLOCK_OPEN.append(True)
    try:
        for name, f in originals.items():
            setattr(module, name, timed(name, f))
        yield totals
    finally:
        for name, f in originals.items():
            setattr(module, name, f)
        _CLOCK_OPEN.clear()


_CLOCK_OPEN: list[bool] = []
"""Non-empty while a ``kernel_clock`` runs."""


def random_cloud(n: int, *, seed: int = 0, radius: float = 0.5, dtype=torch.float32) -> dict[str, torch.Tensor]:
    """n anisotropic Gaussians uniform in a ball, sized like a converged scene: scales are
    log-normal around half the mean point spacing, so the covered area stays about constant as
    n grows. Opacities in [0.3, 1], random rotations and colours."""
    g = torch.Generator().manual_seed(seed)
    d = torch.nn.functional.normalize(torch.randn(n, 3, generator=g), dim=-1)
    means = d * radius * torch.rand(n, 1, generator=g) ** (1 / 3)
    s0 = 0.5 * radius * (4 / 3 * math.pi / max(n, 1)) ** (1 / 3)
    return {
        "means": means.to(dtype),
        "quats": torch.randn(n, 4, generator=g).to(dtype),
        "scales": (s0 * torch.exp(0.5 * torch.randn(n, 3, generator=g))).to(dtype),
        "opacities": (0.3 + 0.7 * torch.rand(n, generator=g)).to(dtype),
        "colors": torch.rand(n, 3, generator=g).to(dtype),
    }


def environment() -> dict[str, object]:
    from gdbench.core.provenance import code_commit

    return {
        "commit": code_commit(),
        "torch": torch.__version__,
        "threads": torch.get_num_threads(),
        "cpu_count": os.cpu_count(),
        "machine": platform.machine(),
        "python": platform.python_version(),
        "cuda": torch.cuda.is_available(),
    }
