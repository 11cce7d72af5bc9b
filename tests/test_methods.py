"""Your own method in a run (gdbench/mechanisms/methods.py): a guidance and a noise source enter by
reference; SJC written anew outside the package reproduces --guidance sjc bit for bit (the oracle:
the built-in path), a noise source is called with the step's shape and the run's stream, and bad
methods are one-line errors naming the option."""

from pathlib import Path

import pytest
import torch

from gdbench.mechanisms import methods
from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.run import run_id, train
from tests._util import CAPTION, tiny, tiny_bank

EXAMPLE = Path(__file__).resolve().parents[1] / "docs" / "examples" / "my_method.py"


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})


def _run(tmp, prior, **kw):
    cfg = tiny("gd", tmp, steps=6, **kw)
    r = train(cfg, prior)
    return {k: v.detach().clone() for k, v in r.state.params.items()}, cfg


@pytest.mark.parametrize("samples", [1, 2])
def test_sjc_written_outside_the_package_gives_the_builtin_parameters_bit_for_bit(prior, tmp_path, samples):
    base, r0 = _run(tmp_path / "sjc", prior, samples_per_step=samples)
    mine, r1 = _run(tmp_path / "mine", prior, samples_per_step=samples, guidance=f"{EXAMPLE}:sjc_again")
    assert base.keys() == mine.keys()
    for k in base:
        assert torch.equal(base[k], mine[k]), k
    assert run_id(r0) != run_id(r1)  # another method, another run
    # and a guidance that differs (twice SJC's gradient) changes the parameters
    methods.register_method("guidance", "twice", lambda D, x, s, step, steps: 2 * (D - x) / s)
    try:
        other, _ = _run(tmp_path / "twice", prior, samples_per_step=samples, guidance="twice")
    finally:
        methods.REGISTERED["guidance"].pop("twice", None)
    assert not torch.equal(other["means"], base["means"])


def test_a_noise_source_gets_the_steps_shape_and_stream_and_replaces_the_cloud(prior, tmp_path):
    seen = []

    def source(req):
        seen.append((req.shape, req.step, req.steps, tuple(req.azimuth.shape)))
        return torch.randn(req.shape, generator=req.generator)

    methods.register_method("noise", "logged", source)
    try:
        a, _ = _run(tmp_path / "a", prior, **{"noise.source": "logged"})
        b, _ = _run(tmp_path / "b", prior, **{"noise.source": "logged"})
        c, _ = _run(tmp_path / "c", prior, **{"noise.source": f"{EXAMPLE}:smooth_noise"})
    finally:
        methods.REGISTERED["noise"].pop("logged", None)
    assert [s[1] for s in seen] == list(range(6)) * 2 and all(s[2] == 6 for s in seen)
    assert seen[0][0] == (1, 16, 16, 3) and seen[0][3] == (1,)
    for k in a:  # drawn from the run's stream: the same seed, the same run
        assert torch.equal(a[k], b[k])
    cloud, _ = _run(tmp_path / "cloud", prior)
    assert not torch.equal(cloud["means"], a["means"]) and not torch.equal(c["means"], a["means"])


def test_the_example_noise_is_unit_variance_and_correlated_over_its_width():
    from gdbench.core.imports import import_ref

    fn = import_ref(f"{EXAMPLE}:smooth_noise", "noise")
    req = methods.NoiseRequest((4, 64, 64, 3), 0, 1, *(torch.zeros(4),) * 3, None, torch.Generator().manual_seed(0),
                               torch.device("cpu"))  # fmt: skip
    n = fn(req)
    assert n.shape == (4, 64, 64, 3) and torch.allclose(n.flatten(1).std(dim=1), torch.ones(4), atol=1e-5)
    inner = n[:, 8:-8, 8:-8]
    lag1 = float((inner[:, :, 1:] * inner[:, :, :-1]).mean())  # a 5-wide box: neighbours correlate 4/5
    assert 0.7 < lag1 < 0.9


def test_bad_methods_are_one_line_errors_naming_the_option(prior, tmp_path):
    with pytest.raises(ValueError, match=r"guidance \(--guidance\): expected one of \['sjc', 'sds'\]"):
        tiny("gd", tmp_path, guidance="sjd")
    with pytest.raises(ValueError, match="cannot import 'no_such_pkg'"):
        tiny("gd", tmp_path, guidance="no_such_pkg:fn")
    with pytest.raises(ValueError, match=r"noise.source \(--noise-source\) .*has no 'nothing'"):
        tiny("gd", tmp_path, **{"noise.source": f"{EXAMPLE}:nothing"})
    with pytest.raises(ValueError, match="not a built-in guidance's"):
        methods.register_method("guidance", "sjc", lambda *a: None)
    methods.register_method("noise", "flat", lambda req: torch.zeros(2, 2))
    try:
        with pytest.raises(ValueError, match=r"noise.source 'flat': expected a float tensor \(1, 16, 16, 3\)"):
            train(tiny("gd", tmp_path / "flat", **{"noise.source": "flat"}), prior)
    finally:
        methods.REGISTERED["noise"].pop("flat", None)


def test_a_guidance_that_returns_nan_is_named(prior, tmp_path):
    methods.register_method("guidance", "nan", lambda D, x, s, step, steps: D * float("nan"))
    try:
        with pytest.raises(ValueError, match="guidance 'nan': returned NaN or Inf at step 0"):
            train(tiny("gd", tmp_path / "nan", guidance="nan"), prior)
    finally:
        methods.REGISTERED["guidance"].pop("nan", None)
