import os
import sys

import pytest
import torch

from tests._util import require_cpp

torch.set_num_threads(int(os.environ.get("GDBENCH_TEST_THREADS", "2")))


def pytest_addoption(parser):
    parser.addoption(
        "--device",
        default="cpu",
        choices=("cpu", "cuda"),
        help="where the renderer tests render (tests/test_rasterize.py and the backend fixture): "
        "'cuda' runs them on CUDA copies of their inputs, compared with the same CPU oracles",
    )


def pytest_configure(config):
    import tests._util

    device = config.getoption("--device")
    if device == "cuda" and not torch.cuda.is_available():
        raise pytest.UsageError("--device cuda: torch sees no CUDA device")
    tests._util.TEST_DEVICE = torch.device(device)


@pytest.fixture(autouse=True, scope="module")
def _free_zoom_levels():
    """The empirical prior's zoomed levels outlive its priors (a sweep's next cell finds them):
    each test file starts without those of the files before it, and their memory is freed."""
    yield
    empirical = sys.modules.get("gdbench.priors.empirical")
    if empirical is not None:
        empirical.clear_level_cache()


@pytest.fixture
def cpp_extension():
    return require_cpp()


@pytest.fixture(params=["cpp", "torch"])
def compositor(request) -> str:
    """Both compositor backends of renderers.splat; 'cpp' drops out if it cannot build, and under
    ``--device cuda`` (CPU tensors only)."""
    import tests._util

    if request.param == "cpp":
        if tests._util.TEST_DEVICE.type != "cpu":
            pytest.skip("the C++ compositor runs on CPU tensors (--device cuda)")
        require_cpp()
    return request.param


@pytest.fixture(params=["splat", "splat_torch", "gsplat_torch", "gsplat_cuda", "mitsuba_ellipsoids"])
def backend(request):
    """Every registered backend with a rasterize-signature render function (gdbench/refcheck/backends.py);
    skipped with the registry's reason where it cannot run here."""
    from gdbench.refcheck.backends import get

    b = get(request.param)
    ok, why = b.available()
    if not ok:
        pytest.skip(f"{b.name} unavailable: {why}")
    return b
