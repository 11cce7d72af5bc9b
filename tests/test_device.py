"""``--device``: where a run, a render and a score compute. On every machine: the choice is checked
before any work (one line naming the option), leaves a run's id alone and is recorded. With a CUDA
GPU (``-m cuda``, skipped with its reason elsewhere): the renderer, the trainer, the three priors,
``render`` and ``score`` on CUDA against the same work on the CPU (docs/renderer.md, "On a GPU")."""

import json

import pytest
import torch

from gdbench.core.devices import resolve_device
from gdbench.priors.empirical import EmpiricalPrior
from gdbench.train.run import run_id, train
from tests._util import CAPTION, TINY_CELL, cli, one_line, tiny, tiny_bank

CUDA = torch.cuda.is_available()
NO_CUDA = "needs a CUDA GPU (torch sees none)"


@pytest.fixture(scope="module")
def prior():
    return EmpiricalPrior(banks={CAPTION: tiny_bank(CAPTION)})


# ------------------------------------------------------------------ every machine
def test_resolve_device_names_the_option_and_what_is_missing():
    assert resolve_device("cpu") == resolve_device(torch.device("cpu")) == torch.device("cpu")
    assert resolve_device("auto") == torch.device("cuda" if CUDA else "cpu")
    with pytest.raises(ValueError, match=r"--device: expected one of \('cpu', 'cuda', 'auto'\).*got 'tpu'"):
        resolve_device("tpu", "--device")
    with pytest.raises(ValueError, match=r"--device: expected one of .*got 'cpu:1'"):
        resolve_device("cpu:1", "--device")
    if not CUDA:
        with pytest.raises(ValueError, match=r"--device: 'cuda' asked for, but torch sees no CUDA device"):
            resolve_device("cuda", "--device")


@pytest.mark.skipif(CUDA, reason="checks the refusal on a machine without CUDA")
@pytest.mark.parametrize(
    "argv",
    [
        ("generate", "a yellow duck", "--steps", "3", "--device", "cuda"),
        ("render", "RUN", "--device", "cuda"),
        ("score", "RUN", "--device", "cuda"),
        ("sweep", "--prompts", "a yellow duck", "--presets", "gd", "--seeds", "0", "--steps", "3", "--device", "cuda"),
    ],
)
def test_cuda_without_a_gpu_is_one_line_before_any_work(argv, tmp_path, monkeypatch, capsys):
    """No bank built, no folder written: the refusal comes first and names --device."""
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("GDBENCH_CACHE", str(tmp_path / "cache"))
    if argv[0] in ("render", "score"):
        from gdbench.core.scene import sphere_init

        (tmp_path / "RUN").mkdir()
        sphere_init(20, 0.3, 0.5, 0.8, generator=torch.Generator().manual_seed(0)).save_ply(tmp_path / "RUN/scene.ply")
    code, _, err = cli(monkeypatch, capsys, *argv)
    assert code == 2
    line = one_line(err)
    assert "device" in line and "torch sees no CUDA device" in line, line
    assert not (tmp_path / "cache" / "banks").exists()
    assert not (tmp_path / "runs").exists()


def test_a_run_json_config_leaves_the_device_to_the_command_line(tmp_path):
    """A run.json made on a GPU reproduces its run on a machine without one (--device chooses);
    a settings file's device is a setting like any other."""
    from gdbench.app.cmd_generate import _config_file
    from gdbench.train.outputs import config_dict

    cfg = config_dict(tiny("gd", tmp_path / "run", device="cuda"))
    (tmp_path / "run.json").write_text(json.dumps({"run_id": "x", "config": cfg}))
    (tmp_path / "settings.json").write_text(json.dumps(cfg))
    assert _config_file(tmp_path / "run.json", None)[0].device == "cpu"
    assert _config_file(tmp_path / "settings.json", None)[0].device == "cuda"


def test_ray_sweeps_on_cuda_are_refused_before_any_cell(tmp_path, monkeypatch):
    """Ray hides the GPUs from tasks that ask for none: a Ray sweep on CUDA would fail in every
    cell after the grid was accepted, so it is refused with the grid (a GPU is faked here)."""
    import gdbench.core.devices
    from gdbench.experiments.sweep import SweepConfig, sweep

    real = gdbench.core.devices.resolve_device
    monkeypatch.setattr(
        gdbench.core.devices,
        "resolve_device",
        lambda name, what="device": torch.device("cuda") if name == "cuda" else real(name, what),
    )
    with pytest.raises(ValueError, match=r"device: Ray runs a sweep's cells as tasks without a GPU"):
        sweep(
            SweepConfig(
                ["a yellow duck"],
                ["gd"],
                [0],
                steps=2,
                out=tmp_path / "sw",
                executor="ray",
                overrides={"device": "cuda"},
            )
        )
    assert not (tmp_path / "sw" / "cells").exists()


def test_device_leaves_the_run_id_and_is_recorded(prior, tmp_path):
    """The device is where a run computes, like the thread count: not part of the run's id (a CPU
    run's checkpoint resumes on CUDA and back), but recorded in run.json and a sweep's rows."""
    assert run_id(tiny("gd", device="cpu")) == run_id(tiny("gd", device="auto")) == run_id(tiny("gd", device="cuda"))
    r = train(tiny("gd", tmp_path / "run", steps=2), prior)
    info = json.loads((tmp_path / "run" / "run.json").read_text())
    assert info["device"] == "cpu" and info["config"]["device"] == "cpu"
    assert r.state.scene().means.device.type == "cpu"


# ------------------------------------------------------------------ CUDA
def _both(cfg_kw: dict, prior, tmp_path, steps: int):
    out = {}
    for dev in ("cpu", "cuda"):
        r = train(tiny("gd", tmp_path / dev, steps=steps, device=dev, **cfg_kw), prior, write_outputs=False)
        out[dev] = r.state
    return out


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
@pytest.mark.parametrize("name", ["anisotropic", "crossing", "random_cloud_10k", "procedural", "subpixel"])
def test_torch_renderer_on_cuda_matches_the_cpu(name):
    """Images and gradients of the torch compositor on CUDA against the C++ compositor on the CPU."""
    from gdbench.refcheck.bm_cuda import GSPLAT_ALPHA_MAX, _ours_images, _render_and_grad
    from gdbench.refcheck.scenes import load_fixture

    f = load_fixture(name)
    gpu = _render_and_grad(_ours_images(GSPLAT_ALPHA_MAX), f.scene, f.cameras, "cuda", 0)
    cpu = _render_and_grad(_ours_images(GSPLAT_ALPHA_MAX, "cpp"), f.scene, f.cameras, "cpu", 0)
    for k in cpu:
        scale = float(cpu[k].abs().max()) or 1.0
        err = float((gpu[k].cpu() - cpu[k]).abs().max())
        assert gpu[k].device.type == "cuda"
        assert err <= (2e-5 if k in ("rgb", "alpha") else 1e-3) * max(scale, 1.0), (k, err, scale)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
def test_training_on_cuda_follows_the_cpu_run(prior, tmp_path):
    """The same draws on both devices (the streams stay on the CPU): the first step's gradients
    agree to float rounding (its Adam step is sign(g) lr, so a gradient near 0 may flip: the
    parameters are not compared), the residuals of a few steps stay close, and every tensor of the
    CUDA run's state lives on the GPU."""
    one = _both({}, prior, tmp_path / "one", 1)
    for k, v in one["cpu"].params.items():
        assert one["cuda"].params[k].device.type == "cuda"
        if v.numel() == 0:  # sh_rest at SH degree 0
            continue
        g_cpu, g_gpu = v.grad, one["cuda"].params[k].grad
        assert g_cpu is not None and float(g_cpu.abs().max()) > 0, k
        torch.testing.assert_close(g_gpu.cpu(), g_cpu, rtol=1e-3, atol=1e-4 * float(g_cpu.abs().max()))
    few = _both({}, prior, tmp_path / "few", 4)
    r_cpu = [h["residual"] for h in few["cpu"].history]
    r_gpu = [h["residual"] for h in few["cuda"].history]
    assert r_gpu == pytest.approx(r_cpu, rel=0.02)
    assert few["cuda"].noise_colors.device.type == "cuda"


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
def test_generate_render_and_score_on_cuda(tmp_path, monkeypatch, capsys):
    """The commands end to end on CUDA: a run records its device; render's frames and score's
    numbers on CUDA agree with the CPU's."""
    monkeypatch.chdir(tmp_path)
    code, _, err = cli(monkeypatch, capsys, "generate", "a yellow duck", "--steps", "30", "--device", "cuda",
                         "--out", "gpu", "--no-progress", "--no-score")  # fmt: skip
    assert code == 0, err
    assert json.loads((tmp_path / "gpu/run.json").read_text())["device"] == "cuda"
    scores = {}
    for dev in ("cpu", "cuda"):
        (tmp_path / "gpu/scores.json").unlink(missing_ok=True)  # else the second call reuses the first's
        code, _, err = cli(monkeypatch, capsys, "score", "gpu", "--no-colmap", "--device", dev)
        assert code == 0, err
        scores[dev] = json.loads((tmp_path / "gpu/scores.json").read_text())
        assert scores[dev]["gt"]["made"]["device"] == dev
    assert scores["cuda"]["gt"]["psnr"] == pytest.approx(scores["cpu"]["gt"]["psnr"], abs=0.01)
    frames = {}
    for dev in ("cpu", "cuda"):
        code, _, err = cli(monkeypatch, capsys, "render", "gpu", "--out", dev, "--frames", "4", "--device", dev)
        assert code == 0, err
        import imageio.v3 as iio

        frames[dev] = iio.imread(tmp_path / dev / "scene_turntable_sheet.png").astype(int)
    assert abs(frames["cuda"] - frames["cpu"]).max() <= 2


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
@pytest.mark.parametrize("dtype,mode", [("float32", "rgb"), ("float16", "rgb"), ("float32", "latent")])
def test_stable_diffusion_prior_on_cuda(dtype, mode, tmp_path):
    """The Stable Diffusion code path with the tiny offline models on CUDA, in both precisions and
    both modes: the prior, its VAE encoder in the graph (rgb) or the latent render, on one device."""
    pytest.importorskip("diffusers")
    from gdbench.mechanisms.noise import NoiseConfig
    from gdbench.train.config import preset

    cfg = preset("gd", prompt="a yellow duck", prior="sd", sd_model="tiny", sd_dtype=dtype, sd_mode=mode, steps=2,
                 resolution=32, init_points=200, progress=False, out=tmp_path / f"{dtype}-{mode}", device="cuda",
                 noise=NoiseConfig(n_gaussians=200, scale=0.05))  # fmt: skip
    from gdbench.train.trainer import make_context

    assert make_context(cfg).prior.device.type == "cuda"
    r = train(cfg, write_outputs=False)
    assert r.state.step == 2 and r.state.params["means"].device.type == "cuda"
    assert all(bool(torch.isfinite(v).all()) for v in r.state.params.values())


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
def test_learned_prior_on_cuda(tmp_path):
    """The shipped learned prior's network on the GPU beside the render."""
    from gdbench.train.config import preset

    cfg = preset("gd", prompt="a yellow duck", prior="learned", steps=2, resolution=64, init_points=512,
                 progress=False, out=tmp_path / "learned", device="cuda")  # fmt: skip
    from gdbench.train.trainer import make_context

    assert make_context(cfg).prior.device.type == "cuda"
    r = train(cfg, write_outputs=False)
    assert r.state.step == 2 and r.state.params["means"].device.type == "cuda"
    assert r.state.history[-1]["residual"] > 0


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
@pytest.mark.parametrize("first,then", [("cpu", "cuda"), ("cuda", "cpu")])
def test_a_checkpoint_resumes_on_the_other_device(first, then, prior, tmp_path):
    """Stopped at step 4 on one device and resumed on the other: the run finishes where it was
    asked, every tensor of the state on the second device, its residuals after the resume close
    to those of an uninterrupted run on the first device (the same draws: the streams are the
    CPU's; float rounding and the two backends keep them from being equal)."""
    full = train(tiny("gd", tmp_path / "full", steps=8, device=first), prior, write_outputs=False)
    train(tiny("gd", tmp_path / "x", steps=8, device=first), prior, stop_at=4, write_outputs=False)
    resumed = train(tiny("gd", tmp_path / "x", steps=8, device=then), prior, write_outputs=False)
    assert resumed.resumed_from == 4 and resumed.state.step == 8
    assert all(v.device.type == then for v in resumed.state.params.values())
    assert [h["residual"] for h in resumed.state.history] == pytest.approx(
        [h["residual"] for h in full.state.history], rel=0.05
    )


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
def test_depth_conditioning_on_cuda(tmp_path):
    """Depth conditioning's renders (expected depth from gsplat's kernels) on CUDA: the tiny SD
    prior with its depth ControlNet trains, with the depth points on the GPU."""
    pytest.importorskip("diffusers")
    from gdbench.mechanisms.noise import NoiseConfig
    from gdbench.train.config import preset
    from gdbench.train.trainer import make_context

    cfg = preset("gd", prompt="a yellow duck", prior="sd", sd_model="tiny", depth_conditioning=True, steps=2,
                 resolution=32, init_points=200, progress=False, out=tmp_path / "d", device="cuda",
                 noise=NoiseConfig(n_gaussians=200, scale=0.05))  # fmt: skip
    ctx = make_context(cfg)
    assert ctx.depth_points is not None
    r = train(cfg, write_outputs=False)
    assert r.state.step == 2 and r.state.params["means"].device.type == "cuda"
    assert all(bool(torch.isfinite(v).all()) for v in r.state.params.values())


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
def test_a_two_cell_sweep_on_cuda(tmp_path):
    """A sweep of two cells on CUDA: both cells train and score there, their rows say so, and
    their GT PSNR is close to the same cells on the CPU (a few steps: within 1 dB)."""
    from gdbench.experiments.sweep import SweepConfig, sweep

    tiny_cfg = TINY_CELL
    rows = {}
    for dev in ("cpu", "cuda"):
        grid = SweepConfig(["a yellow duck"], ["gd", "sjc-gs"], [0], steps=4, out=tmp_path / dev, colmap=False,
                           overrides=tiny_cfg | {"device": dev}, progress=False)  # fmt: skip
        rows[dev] = sweep(grid)
        assert len(rows[dev]) == 2
    for a, b in zip(rows["cpu"], rows["cuda"]):
        assert b["device"] == "cuda" and a["device"] == "cpu"
        assert float(b["gt_psnr"]) == pytest.approx(float(a["gt_psnr"]), abs=1.0)


@pytest.mark.cuda
@pytest.mark.skipif(not CUDA, reason=NO_CUDA)
def test_structured_noise_for_cuda_cameras_is_the_cpu_render_on_the_gpu():
    """The noise has no gradients and gsplat cannot give its weights: for cameras on CUDA it is
    rendered by the C++ compositor and copied over, the same bits as for the same cameras on the
    CPU (and the same draws of the iid fill)."""
    from gdbench.core.camera import SphericalPoses
    from gdbench.mechanisms.noise import NoiseConfig, NoiseRenderer, make_noise_cloud

    cloud = make_noise_cloud(NoiseConfig(n_gaussians=300, scale=0.05), 3, generator=torch.Generator().manual_seed(0))
    colors = torch.randn(300, 3, generator=torch.Generator().manual_seed(1))
    cams = SphericalPoses.orbit(2, radius=1.5, elevation=15.0).cameras(32, 32)
    cpu = NoiseRenderer(cloud, cache_size=0).render(colors, cams, generator=torch.Generator().manual_seed(2))
    gpu = NoiseRenderer(cloud, cache_size=0).render(  # as the trainer's: no projection reused
        colors.cuda(), cams.to("cuda"), generator=torch.Generator().manual_seed(2)
    )
    assert gpu.noise.device.type == "cuda" and gpu.coverage.device.type == "cuda"
    assert float(cpu.coverage.mean()) > 0.3
    assert torch.equal(gpu.noise.cpu(), cpu.noise) and torch.equal(gpu.coverage.cpu(), cpu.coverage)
