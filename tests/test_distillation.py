"""Guidance in one call (gdbench/priors/learned/distillation.py): the target is the runtime's
classifier-free guidance (the oracle: the prior's own two-call path, _Epsilon), a tiny student
learns it from its teacher, and the prior uses a distilled model in one call at its scale only."""

from __future__ import annotations

import json

import pytest
import torch

from gdbench.priors import sd_abar
from gdbench.priors.learned.distillation import distill_config
from gdbench.priors.learned.prior import LearnedPrior, _Epsilon, load_model
from gdbench.priors.learned.training import Batches, PriorTrainConfig, guided_target, loss_of, train_prior
from tests.test_learned_prior import TINY, TINY_DATA


@pytest.fixture(scope="module")
def teacher(tmp_path_factory):
    out = tmp_path_factory.mktemp("teacher")
    cfg = PriorTrainConfig(out=out, steps=40, batch=8, warmup=2, lr=2e-3, unet=TINY, data=TINY_DATA, log_every=5,
                           checkpoint_every=100, progress=False, threads=1)  # fmt: skip
    train_prior(cfg)
    return out / "model.safetensors"


def _batch(seed: int = 5, n: int = 16):
    from gdbench.priors.learned.data import load_dataset, to_model_images

    data = load_dataset(TINY_DATA, progress=False)
    cfg = PriorTrainConfig(batch=n, unet=TINY, data=TINY_DATA, seed=seed)
    return Batches(cfg, data, to_model_images(data.images, TINY.size)).draw()


def test_the_target_is_the_runtimes_classifier_free_guidance(teacher):
    net, _ = load_model(teacher)
    b = _batch()
    keep = ~b["camera_drop"] & (b["caption"] < TINY.captions)  # rows with every condition given
    x_t, t = b["x_t"][keep], b["t"][keep]
    got = guided_target(net, {k: v[keep] for k, v in b.items()}, 3.0)
    a = sd_abar()[t].float()[:, None, None, None]
    eps_of_target = a.sqrt() * got + (1 - a).sqrt() * x_t  # v -> eps, as the prior converts
    runtime = _Epsilon(net, sd_abar(), 3.0, camera=True)(x_t, t, b["caption"][keep], b["variant"][keep],
                                                          b["camera"][keep])  # fmt: skip
    torch.testing.assert_close(eps_of_target, runtime, rtol=1e-4, atol=1e-5)
    # and at scale 1 the target is the teacher's conditional prediction itself
    emb = net.embedding(b["t"], b["caption"], b["variant"], b["camera"], b["camera_drop"])
    torch.testing.assert_close(guided_target(net, b, 1.0), net(b["x_t"], emb), rtol=1e-4, atol=1e-5)


def test_a_student_learns_the_guided_prediction_and_the_prior_uses_it_in_one_call(teacher, tmp_path):
    cfg = distill_config(teacher, 3.0, out=tmp_path / "student", steps=60, batch=8, lr=1e-3, warmup=2, log_every=5,
                         checkpoint_every=100, progress=False, threads=1)  # fmt: skip
    assert cfg.unet == TINY and cfg.teacher_guidance == 3.0 and "teacher" in cfg.identity()
    assert "teacher" not in PriorTrainConfig(unet=TINY, data=TINY_DATA).identity()  # older runs' identity kept
    train_prior(cfg)
    t_net, _ = load_model(teacher)
    s_net, meta = load_model(tmp_path / "student" / "model.safetensors")
    assert json.loads(meta["train"])["teacher_guidance"] == 3.0
    b = _batch(seed=11, n=64)
    with torch.no_grad():
        start, end = float(loss_of(t_net, b, "cpu", t_net, 3.0)), float(loss_of(s_net, b, "cpu", t_net, 3.0))
    assert end < 0.7 * start, (start, end)  # the teacher's own call is the student's start

    prior = LearnedPrior(tmp_path / "student" / "model.safetensors", guidance_scale=3.0, view_mode="window")
    cond = prior.encode("a yellow duck")
    g = torch.Generator().manual_seed(2)
    x_t, t = torch.randn(3, 3, 16, 16, generator=g), torch.tensor([100, 500, 900])
    cam = torch.tensor([[0.0, 10.0, 50.0], [90.0, 0.0, 55.0], [180.0, -10.0, 60.0]])
    one_call = _Epsilon(s_net, sd_abar(), 1.0, camera=True)  # the network once, with the conditions
    cap, var = torch.full((3,), cond.caption_index), torch.full((3,), cond.variant_index)
    torch.testing.assert_close(prior.eps(x_t, t, cond, cam), one_call(x_t, t, cap, var, cam), rtol=1e-5, atol=1e-6)
    with pytest.raises(ValueError, match=r"gives guidance 3 in one call \(distilled\); it takes --learned-guidance 3"):
        LearnedPrior(tmp_path / "student" / "model.safetensors", guidance_scale=5.0)
    with pytest.raises(ValueError, match="is itself distilled"):
        distill_config(tmp_path / "student" / "model.safetensors", 3.0)
    with pytest.raises(ValueError, match="teacher_guidance: expected > 1 with a teacher"):
        PriorTrainConfig(unet=TINY, data=TINY_DATA, teacher="x", teacher_guidance=1.0)


def test_train_prior_teacher_option(teacher, tmp_path):
    """`gdbench train-prior --teacher PATH --teacher-guidance S`: the teacher's architecture and data,
    a tenth of a new model's learning rate unless --lr is given, resumable like any run."""
    from gdbench.app.cmd_tools import TrainPrior, run_train_prior

    out = tmp_path / "cli"
    run_train_prior(TrainPrior(out=out, teacher=teacher, teacher_guidance=2.5, steps=6, progress=False, threads=1,
                               stop_at=3))  # fmt: skip
    assert not (out / "model.safetensors").exists()
    run_train_prior(TrainPrior(out=out, teacher=teacher, teacher_guidance=2.5, steps=6, progress=False, threads=1))
    saved = json.loads((out / "config.json").read_text())
    assert saved["lr"] == 1e-4 and saved["teacher_guidance"] == 2.5 and saved["unet"]["size"] == TINY.size
    _, meta = load_model(out / "model.safetensors")
    assert json.loads(meta["train"])["teacher_guidance"] == 2.5
    with pytest.raises(ValueError, match="other settings"):  # another scale is another run
        run_train_prior(TrainPrior(out=out, teacher=teacher, teacher_guidance=4.0, steps=6, progress=False))


def test_teacher_guidance_without_a_teacher_is_refused(tmp_path):
    from gdbench.app.cmd_tools import TrainPrior, run_train_prior

    with pytest.raises(ValueError, match="teacher_guidance \\(--teacher-guidance\\): acts only with --teacher"):
        run_train_prior(TrainPrior(out=tmp_path / "x", teacher_guidance=2.0, steps=2, progress=False))
    assert not (tmp_path / "x").exists()


def test_the_students_check_measures_its_distance_to_the_guided_teacher(teacher):
    """`evaluation.guided_error` on its own oracles: the guided teacher checked against itself is
    0 away at every sigma, the unguided teacher put in the student's place is exactly as far
    from the guided teacher as guidance moves it (the row's own scale), which is not 0, and that
    scale is the MSE between the two teachers' estimates computed directly, whatever the student;
    the teacher at scale 2 lies between."""
    from gdbench.priors.learned.evaluation import guided_error

    guided = LearnedPrior(teacher, guidance_scale=3.0, view_mode="window")
    unguided = LearnedPrior(teacher, guidance_scale=1.0, view_mode="window")
    caption = guided.captions[0]
    same = guided_error(guided, guided, unguided, [caption], sigmas=(0.5, 5.0))
    assert [r["mse_student_teacher"] for r in same] == [0.0, 0.0]
    assert all(r["psnr_student"] == r["psnr_teacher"] for r in same)
    off = guided_error(unguided, guided, unguided, [caption], sigmas=(0.5, 5.0))
    for r in off:
        assert r["mse_student_teacher"] == pytest.approx(r["mse_guided_unguided"], rel=1e-6)
        assert r["mse_guided_unguided"] > 1e-6
    # a third model in the student's place moves only the student's column; guidance's own effect is
    # the MSE between the two teachers' estimates of the same noisy renders, computed here directly
    from gdbench.priors.learned.evaluation import render_views

    other = guided_error(LearnedPrior(teacher, guidance_scale=2.0, view_mode="window"), guided, unguided, [caption],
                         sigmas=(0.5, 5.0))  # fmt: skip
    g = torch.Generator().manual_seed(0)
    az = torch.tensor([0.0, 60.0, 120.0, 180.0, -120.0, -60.0])
    cam = {"azimuth": az, "elevation": torch.full((6,), 15.0), "fovy": torch.full((6,), 55.0)}
    x0 = render_views(caption, az, 15.0, 55.0, size=guided.size)
    cond = guided.encode(caption)
    for r, s in zip(other, (0.5, 5.0)):
        y = x0 + s * torch.randn(x0.shape, generator=g)
        sig = torch.full((6,), s)
        direct = float(((guided.denoise(y, sig, cond, **cam) - unguided.denoise(y, sig, cond, **cam)) ** 2).mean())
        assert r["mse_guided_unguided"] == pytest.approx(direct, rel=1e-6)
        assert 0 < r["mse_student_teacher"] < r["mse_guided_unguided"]  # scale 2 lies between 1 and 3
