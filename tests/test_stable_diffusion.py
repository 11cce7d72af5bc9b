"""The Stable Diffusion prior and 3DFuse's stages, offline, on tiny random-weight models built
from configs (gdbench/priors/sd/tiny.py): the VE conversion against the scheduler, guidance,
ControlNet, LoRA and textual inversion, saving and loading, the trainer on every preset, and
the error for missing weights."""

import copy

import pytest
import torch

pytest.importorskip("diffusers")
pytest.importorskip("peft")

from gdbench.priors import ve_sigmas_from_betas
from gdbench.priors.sd.prior import StableDiffusionPrior

PROMPT = "a yellow duck"


@pytest.fixture(scope="module")
def parts():
    from gdbench.priors.sd.tiny import tiny_components

    return {p: tiny_components(0, prediction_type=p) for p in ("epsilon", "v_prediction")}


def make(parts, prediction="epsilon", **kw):
    c = copy.deepcopy(parts[prediction])
    cn = c.pop("controlnet")
    return StableDiffusionPrior(**c, controlnet=cn, device="cpu", **kw)


def test_the_clip_tokenizer_from_open_clips_vocabulary_gives_clips_ids(parts):
    tok = parts["epsilon"]["tokenizer"]
    # OpenAI CLIP's ids for these words (start 49406, 'a' 320, 'photo' 1125, 'of' 539, 'cat' 2368, end 49407)
    assert tok("a photo of a cat").input_ids == [49406, 320, 1125, 539, 320, 2368, 49407]
    assert len(tok) == 49408


def test_sigmas_are_the_ve_conversion_of_the_schedulers_alphas(parts):
    prior = make(parts)
    abar = parts["epsilon"]["scheduler"].alphas_cumprod.double()
    torch.testing.assert_close(prior.sigmas.double(), torch.sqrt((1 - abar) / abar), rtol=1e-6, atol=0)
    # and SD's scaled-linear betas in closed form (the embedded prior's ticks); the scheduler keeps
    # abar in float32, so 1 - abar ~ 8.5e-4 at t = 0 carries ~7e-5 relative error, ~3.5e-5 in sigma
    torch.testing.assert_close(prior.sigmas.double(), ve_sigmas_from_betas(), rtol=5e-5, atol=0)
    k = torch.tensor([0, 10, 500, 999])
    assert torch.equal(prior.timestep(prior.sigmas[k] * 1.001), k)


@pytest.mark.parametrize("prediction", ["epsilon", "v_prediction"])
def test_denoise_is_the_schedulers_x0_prediction(parts, prediction):
    prior = make(parts, prediction, guidance_scale=1.0, view_prompting=False)
    sched = copy.deepcopy(parts[prediction]["scheduler"])
    cond = prior.encode(PROMPT)
    g = torch.Generator().manual_seed(0)
    for t in (30, 400, 900):
        sigma = float(prior.sigmas[t])
        x = torch.randn(1, 8, 8, 4, generator=g) * (1 + sigma)
        D = prior.denoise(x, torch.tensor([sigma]), cond)
        x_t = x.permute(0, 3, 1, 2) / (1 + sigma**2) ** 0.5
        with torch.no_grad():
            out = prior.unet(x_t, torch.tensor([t]), encoder_hidden_states=cond.embeddings).sample
        x0 = sched.step(out, t, x_t).pred_original_sample
        torch.testing.assert_close(D, x0.permute(0, 2, 3, 1), rtol=1e-4, atol=1e-4)


def test_guidance_combines_conditional_and_unconditional_eps(parts):
    p1 = make(parts, guidance_scale=1.0, view_prompting=False)
    p7 = make(parts, guidance_scale=7.5, view_prompting=False)
    cond = p1.encode(PROMPT)
    x, s = torch.randn(2, 8, 8, 4, generator=torch.Generator().manual_seed(1)), torch.tensor([1.0, 1.0])
    D1, D7 = p1.denoise(x, s, cond), p7.denoise(x, s, cond)
    assert float((D1 - D7).abs().max()) > 1e-3
    # closed form: D_s = x - sigma (eps_u + s (eps_c - eps_u)) with sigma snapped to its tick
    sig = float(p1.sigmas[p1.timestep(s)][0])
    eu = (x - p1.denoise(x, s, type(cond)(cond.prompt, cond.uncond, cond.uncond))) / sig
    ec = (x - D1) / sig
    torch.testing.assert_close(D7, x - sig * (eu + 7.5 * (ec - eu)), rtol=1e-3, atol=1e-3)


def test_view_prompting_uses_the_cameras_bucket(parts):
    prior = make(parts, guidance_scale=1.0)
    cond = prior.encode(PROMPT)
    assert cond.embeddings.shape[0] == 4
    x, s = torch.randn(1, 8, 8, 4, generator=torch.Generator().manual_seed(2)), torch.tensor([0.5])
    front = prior.denoise(x, s, cond, azimuth=torch.tensor([10.0]), elevation=torch.tensor([0.0]))
    front2 = prior.denoise(x, s, cond, azimuth=torch.tensor([-30.0]), elevation=torch.tensor([5.0]))
    back = prior.denoise(x, s, cond, azimuth=torch.tensor([170.0]), elevation=torch.tensor([0.0]))
    assert torch.equal(front, front2) and float((front - back).abs().max()) > 1e-4


def test_controlnet_conditions_only_through_its_zero_convolutions(parts):
    prior = make(parts, guidance_scale=1.0, view_prompting=False)
    cond = prior.encode(PROMPT)
    x, s = torch.randn(1, 8, 8, 4, generator=torch.Generator().manual_seed(3)), torch.tensor([0.5])
    depth = 1 + torch.rand(1, 64, 64, generator=torch.Generator().manual_seed(4))
    plain = prior.denoise(x, s, cond)
    # an untrained ControlNet's output convolutions are zero: conditioning changes nothing yet
    torch.testing.assert_close(prior.denoise(x, s, cond, depth=depth), plain, rtol=0, atol=1e-6)
    g = torch.Generator().manual_seed(5)
    with torch.no_grad():
        cn = prior.controlnet  # its zero-initialised convolutions, as training would leave them
        for m in [*cn.controlnet_down_blocks, cn.controlnet_mid_block, cn.controlnet_cond_embedding.conv_out]:
            m.weight.copy_(torch.randn(m.weight.shape, generator=g) * 0.5)
    half = depth.clone()
    half[..., :32] = 0  # an object on the right half only
    a = prior.denoise(x, s, cond, depth=depth)
    b = prior.denoise(x, s, cond, depth=half)
    assert float((a - plain).abs().max()) > 1e-3 and float((a - b).abs().max()) > 1e-4


def test_lora_starts_as_identity_changes_the_output_and_lowers_its_loss(parts):
    from gdbench.priors.sd import threedfuse as f

    prior = make(parts, guidance_scale=1.0, view_prompting=False)
    cond = prior.encode(PROMPT)
    x, s = torch.randn(1, 8, 8, 4, generator=torch.Generator().manual_seed(6)), torch.tensor([0.8])
    before = prior.denoise(x, s, cond)
    f.add_lora(prior, rank=4)
    torch.testing.assert_close(prior.denoise(x, s, cond), before, rtol=0, atol=1e-6)  # B = 0 at init
    z0 = torch.randn(1, 4, 8, 8, generator=torch.Generator().manual_seed(7))
    loss0 = f.eval_loss(prior, z0, PROMPT)
    f.train_lora(prior, z0, PROMPT, steps=60, lr=3e-3, generator=torch.Generator().manual_seed(8))
    assert f.eval_loss(prior, z0, PROMPT) < 0.95 * loss0
    assert float((prior.denoise(x, s, cond) - before).abs().max()) > 1e-3
    # only the adapters trained
    assert all(not p.requires_grad for p in prior.unet.parameters())


def test_semantic_code_is_saved_and_loaded_with_the_run(parts, tmp_path):
    from gdbench.priors.sd.threedfuse import SemanticCodeConfig, load_semantic_code, semantic_code

    a = make(parts, guidance_scale=3.0, view_prompting=False)
    cfg = SemanticCodeConfig(size=64, sample_steps=4, ti_steps=20, ti_lr=0.05, lora_steps=20, lora_lr=3e-3)
    rec = semantic_code(a, PROMPT, tmp_path, cfg)
    assert rec["ti_loss_after"] < rec["ti_loss_before"] and rec["lora_loss_after"] < rec["ti_loss_after"]
    assert (tmp_path / "image.png").is_file() and (tmp_path / "lora" / "adapter.safetensors").is_file()
    b = make(parts, guidance_scale=3.0, view_prompting=False)
    assert load_semantic_code(b, tmp_path) == rec["text"] == f"{PROMPT}, <gd-object>"
    ca, cb = a.encode(PROMPT), b.encode(PROMPT)
    torch.testing.assert_close(cb.embeddings, ca.embeddings)
    x, s = torch.randn(1, 8, 8, 4, generator=torch.Generator().manual_seed(9)), torch.tensor([0.5])
    torch.testing.assert_close(b.denoise(x, s, cb), a.denoise(x, s, ca), rtol=1e-5, atol=1e-5)
    with pytest.raises(FileNotFoundError, match=r"lora: no semantic\.json"):
        load_semantic_code(b, tmp_path / "nope")


def test_vae_encoding_is_differentiable(parts):
    prior = make(parts, dtype=torch.float64)
    g = torch.Generator().manual_seed(10)
    rgb = (torch.rand(1, 16, 16, 3, generator=g, dtype=torch.float64) * 2 - 1).requires_grad_(True)
    v = torch.randn(rgb.shape, generator=g, dtype=torch.float64)
    w = torch.randn(1, 2, 2, 4, generator=g, dtype=torch.float64)
    (grad,) = torch.autograd.grad((prior.encode_images(rgb) * w).sum(), rgb)
    h = 1e-5
    with torch.no_grad():
        fd = ((prior.encode_images(rgb + h * v) - prior.encode_images(rgb - h * v)) * w).sum() / (2 * h)
    assert float((grad * v).sum()) == pytest.approx(float(fd), rel=1e-5)
    with pytest.raises(ValueError, match="multiples of 8"):
        prior.encode_images(torch.zeros(1, 12, 12, 3))


def test_from_pretrained_loads_a_local_folder_and_names_missing_weights(parts, tmp_path):
    from gdbench.priors.sd.tiny import save_tiny_model

    folder = save_tiny_model(tmp_path / "tiny-sd")
    loaded = StableDiffusionPrior.from_pretrained(folder, controlnet=folder / "controlnet", guidance_scale=1.0)
    ref = make(parts, guidance_scale=1.0)
    x, s = torch.randn(1, 8, 8, 4, generator=torch.Generator().manual_seed(11)), torch.tensor([0.5])
    torch.testing.assert_close(loaded.denoise(x, s, loaded.encode(PROMPT)), ref.denoise(x, s, ref.encode(PROMPT)))
    with pytest.raises(FileNotFoundError, match=r"(?s)model: .*not found at .*huggingface-cli download"):
        StableDiffusionPrior.from_pretrained(tmp_path / "no-weights")
    with pytest.raises(FileNotFoundError, match="huggingface-cli download"):
        StableDiffusionPrior.from_pretrained("someone/not-in-the-cache")


def test_depth_unprojection_inverts_the_projection():
    from gdbench.core.camera import SphericalPoses
    from gdbench.priors.sd.threedfuse import DepthUnprojection

    cams = SphericalPoses.orbit(1, radius=1.2, elevation=20.0, fovy=50.0).cameras(16, 12)
    g = torch.Generator().manual_seed(12)
    depth = 0.8 + 0.5 * torch.rand(12, 16, generator=g, dtype=torch.float64)
    depth[0, :4] = 0  # empty pixels give no points
    image = torch.rand(12, 16, 3, generator=g)
    pts, cols = DepthUnprojection()(image, depth, cams.viewmats[0].double(), cams.Ks[0].double())
    assert pts.shape == (12 * 16 - 4, 3) and torch.equal(cols, image[depth > 0])
    px, z = cams.to(torch.float64).project(pts)
    v, u = torch.nonzero(depth > 0, as_tuple=True)
    torch.testing.assert_close(px[0], torch.stack([u + 0.5, v + 0.5], -1).double(), rtol=0, atol=1e-9)
    torch.testing.assert_close(z[0], depth[depth > 0], rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="depth: DepthUnprojection needs a depth map"):
        DepthUnprojection()(image, None, cams.viewmats[0], cams.Ks[0])


# ------------------------------------------------------------------ the trainer on the tiny prior
def _two_sd_steps(out, **extra) -> dict:
    """TrainConfig fields for a 2-step run at 32 px on the tiny SD prior."""

    kw = dict(prompt=PROMPT, prior="sd", sd_guidance=7.5, steps=2, resolution=32, init_points=200)
    kw.update(progress=False, turntable_frames=2, out=out, **{"noise.n_gaussians": 200, "noise.scale": 0.05})
    return kw | extra


@pytest.mark.parametrize("name", ["gd", "gd-no-sn", "gd-no-vgs", "sjc-gs", "sds-gs"])
def test_every_preset_trains_two_steps_on_the_tiny_prior(name, tmp_path):
    from gdbench.train.config import preset
    from gdbench.train.run import train

    r = train(preset(name, **_two_sd_steps(tmp_path)))
    assert r.state.step == 2 and r.paths["ply"].is_file()
    before = {k: v for k, v in r.state.history[0].items() if k != "seconds"}
    assert all(torch.isfinite(torch.tensor(h["residual"])) for h in r.state.history) and before["residual"] > 0


@pytest.mark.parametrize("mode", ["rgb", "latent"])
def test_both_rendering_modes_with_depth_control_and_semantic_code(mode, tmp_path):
    from gdbench.train.config import preset
    from gdbench.train.run import train
    from gdbench.train.trainer import make_context

    kw = _two_sd_steps(tmp_path, sd_mode=mode, depth_conditioning=True, semantic_code=True, semantic_steps=2)
    r = train(preset("gd", **kw))
    assert (tmp_path / "semantic" / "semantic.json").is_file()
    assert r.state.params["sh"].shape[-1] == (4 if mode == "latent" else 3)
    ctx = make_context(preset("gd", **kw))  # the second context reloads the saved code
    assert ctx.cond.prompt.endswith("<gd-object>") and ctx.depth_points is not None
    with pytest.raises(ValueError, match="resolution: the sd prior needs a multiple of 8"):
        preset("gd", **(kw | {"resolution": 36}))


def test_cli_generate_runs_the_sd_prior_and_does_not_score_it_against_an_asset(tmp_path):
    import json

    from gdbench.app.cli import main
    from gdbench.app.cmd_generate import GENERATE_EXCLUDES, generate_command
    from gdbench.train.options import train_options

    train = train_options(GENERATE_EXCLUDES, "sd")(prior="sd", sd_guidance=7.5, steps=2, resolution=32)
    s = main(generate_command("sd")(prompt=PROMPT, out=tmp_path, progress=False, train=train))
    assert s["steps"] == 2 and "gt" not in s
    run = json.loads((tmp_path / "run.json").read_text())
    prior = run["config"]["prior"]
    assert prior["kind"] == "sd" and prior["sd_mode"] == "rgb" and prior["sd_guidance"] == 7.5
    assert run["caption"] is None


@pytest.mark.parametrize("mode", ["rgb", "latent"])
def test_the_densification_statistic_is_per_rendered_pixel_for_every_prior(mode, tmp_path):
    """The definition, written out here: the loss is L = -w sum(score * x) / (elements of the
    render), averaged over the rendered pixels whatever the prior's input x is (in sd-rgb mode the
    sum runs over VAE latents; the trainer used to divide by their count, 48x fewer). Oracle:
    autograd of that L through a fresh render (and the VAE encoder); the trainer hands the score's
    gradient over by hand. The screen-space gradients, which densification thresholds, agree."""
    from gdbench.train.config import preset
    from gdbench.train.trainer import apply_update, init_state, make_context, render_for_prior, sample_views

    # a 2-step run densifies by default no more (densify.min_every): every step, so it gathers the statistic
    cfg = preset("sjc-gs", **_two_sd_steps(tmp_path, sd_mode=mode), densify_every=1)
    ctx = make_context(cfg)
    state = init_state(ctx)
    views = sample_views(ctx, state)
    saved = {k: v.detach().clone() for k, v in state.params.items()}
    out, x = render_for_prior(ctx, state, views)
    score = torch.randn(x.shape, generator=torch.Generator().manual_seed(0))
    apply_update(state, ctx, views, out, x, score)
    got = out.means2d.grad.clone()
    state.params = {k: v.clone().requires_grad_(True) for k, v in saved.items()}
    out2, x2 = render_for_prior(ctx, state, views)
    assert x2.requires_grad  # both SD modes: x carries the graph (the VAE encoder, or the latent render)
    loss = -(cfg.weight * views.weight) * (score * x2).sum() / out2.rgb.numel()
    (want,) = torch.autograd.grad(loss, out2.means2d)
    assert float(want.abs().max()) > 0
    torch.testing.assert_close(got, want, rtol=1e-4, atol=1e-9)
