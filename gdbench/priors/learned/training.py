"""Training the learned prior: v prediction on the procedural assets' renders.

The objective is Stable Diffusion 2's: for a view x0 in [-1, 1], a DDPM timestep t uniform over
the 1000 ticks of SD's scaled-linear schedule and eps ~ N(0, I),

    x_t = sqrt(abar_t) x0 + sqrt(1 - abar_t) eps,   v = sqrt(abar_t) eps - sqrt(1 - abar_t) x0,
    loss = |v_theta(x_t, t, c) - v|^2

(or |eps_theta - eps|^2 with ``unet.prediction = 'epsilon'``). Why v: in x0's terms the epsilon
loss weighs a noise level by its signal-to-noise ratio, so at high noise, where only the
conditions say what the image is, it hardly rewards learning them: measured on an epsilon model
after 4500 steps, giving the right camera, none or the opposite one changed its loss at t >= 700
by 3% and its x0 estimates at sigma 2-10 by under 0.1 dB (the model ignored the camera). The v
loss weighs x0's error by 1 / (1 - abar): about 1 at high noise.

The conditions c (caption, variant, camera) are each replaced by their null embedding at their own
rate, so one network gives the conditional and the unconditional predictions classifier-free
guidance needs, and the caption-only prediction of "view prompting none". Views are drawn with
probability proportional to exp(kappa cos azimuth) (``front_bias``; 0 is uniform). AdamW with a
linear warm-up and a cosine decay; the exponential moving average of the weights is the model.

A run folder holds config.json, the checkpoint (atomic, resumed when the folder is reused with
the same settings), loss.csv (the loss per logged interval), loss.png and model.safetensors (the
averaged weights in float16 with their settings, commit and final loss as metadata).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path

import torch

from gdbench.priors import sd_abar
from gdbench.priors.learned.data import DataConfig, captions, load_dataset, to_model_images, view_weights
from gdbench.priors.learned.unet import UNet, UNetConfig


@dataclass(frozen=True)
class PriorTrainConfig:
    out: Path = Path("runs/prior")
    """Run folder (reused: the run resumes from its checkpoint)."""
    front_bias: float = 0.0
    """kappa: views drawn with probability proportional to exp(kappa cos azimuth) (0: uniform; the
    shipped front-biased model: 2)."""
    steps: int = 8000
    """Optimiser steps."""
    batch: int = 32
    lr: float = 6e-4
    """Peak learning rate (AdamW), reached after ``warmup`` steps, then cosine decay to a tenth."""
    warmup: int = 300
    weight_decay: float = 0.0
    ema: float = 0.999
    """Decay of the weights' moving average (the shipped model)."""
    caption_drop: float = 0.1
    """Rate at which the caption (and with it the variant and the camera) is dropped."""
    variant_drop: float = 0.3
    """Rate at which the variant alone is dropped (the instance setting's caption-only prior)."""
    camera_drop: float = 0.3
    """Rate at which the camera alone is dropped (view prompting 'none')."""
    seed: int = 0
    """Seed of the initial weights and of every draw (views, timesteps, noise, drops)."""
    threads: int = 0
    """torch CPU threads (0: torch's default). Results are reproducible for one thread count."""
    device: str = "auto"
    """'auto' (CUDA when present), 'cpu' or 'cuda'."""
    data_workers: int = 1
    """Processes rendering the data on first use (the same data whatever the count)."""
    checkpoint_every: int = 500
    log_every: int = 50
    progress: bool = True
    unet: UNetConfig = field(default_factory=UNetConfig)
    data: DataConfig = field(default_factory=DataConfig)
    held_out: tuple[str, ...] = ()
    """Captions the model knows (a row of its compositional caption embedding) but never sees in
    training: the generalisation check of held-out combinations (``world_config``)."""
    teacher: str = ""
    """Guidance distillation (``distillation.py``): the weights of a finished model this one starts
    from and learns to match, guided, in one call ('' trains a model of its own)."""
    teacher_guidance: float = 0.0
    """... the classifier-free guidance scale of the teacher's prediction it learns (> 1)."""

    def __post_init__(self) -> None:
        checks = [
            ("steps", self.steps >= 1, "an int >= 1"),
            ("batch", self.batch >= 1, "an int >= 1"),
            ("lr", self.lr > 0, "a positive rate"),
            ("warmup", self.warmup >= 0, "an int >= 0"),
            ("ema", 0 <= self.ema < 1, "a decay in [0, 1)"),
            ("front_bias", math.isfinite(self.front_bias) and self.front_bias >= 0, "kappa >= 0"),
            ("checkpoint_every", self.checkpoint_every >= 1, "an int >= 1"),
            ("data_workers", self.data_workers >= 1, "an int >= 1"),
            ("log_every", self.log_every >= 1, "an int >= 1"),
            ("device", self.device in ("auto", "cpu", "cuda"), "'auto', 'cpu' or 'cuda'"),
        ]
        for name in ("caption_drop", "variant_drop", "camera_drop"):
            checks.append((name, 0 <= getattr(self, name) < 1, "a rate in [0, 1)"))
        checks.append(("teacher_guidance", (self.teacher_guidance > 1) == bool(self.teacher), "> 1 with a teacher"))
        for name, ok, want in checks:
            if not ok:
                raise ValueError(f"{name}: expected {want}, got {getattr(self, name)!r}")
        caps = model_captions(self)
        if self.unet.captions != len(caps):
            raise ValueError(
                f"unet.captions: expected {len(caps)} (the data's captions and held_out), got {self.unet.captions}"
            )
        if self.held_out and not self.unet.parts:
            raise ValueError("held_out: only a compositional model (unet.parts) can know captions it never saw")
        if set(self.held_out) & set(captions(self.data)):
            raise ValueError(f"held_out: {sorted(set(self.held_out) & set(captions(self.data)))} are also in the data")
        if self.data.resolution % self.unet.size:
            raise ValueError(
                f"unet.size: expected a divisor of the data's {self.data.resolution} px, got {self.unet.size}"
            )

    def to_dict(self) -> dict:
        d = asdict(self)
        d["out"] = str(self.out)
        return d

    def identity(self) -> dict:
        """The settings a resumed run must share: all but where it runs and how it reports, and
        ``steps`` (a finished run can be extended; its cosine schedule then follows the new length
        from where it stands, so the result differs from a run made at that length at once)."""
        d = self.to_dict()
        for k in ("out", "steps", "threads", "device", "data_workers", "checkpoint_every", "log_every", "progress"):
            d.pop(k)
        if not self.teacher:  # a model of its own: the identity runs had before distillation existed
            d.pop("teacher")
            d.pop("teacher_guidance")
        return d


def model_captions(cfg: PriorTrainConfig) -> tuple[str, ...]:
    """The captions a model of ``cfg`` knows, in catalogue order: the data's and the held-out ones."""
    from gdbench.assets.library import CAPTIONS

    known = set(captions(cfg.data)) | set(cfg.held_out)
    return tuple(c for c in CAPTIONS if c in known)


WORLD_HELD_OUT = ("a blue duck", "a grey rabbit", "a white bear", "a red frog", "a blue car", "a white teapot")
"""The world set's held-out colour x kind combinations (6 of its 32 objects, about 20%): each kind
is seen in training in another colour (the white duck, the white rabbit, the brown bear, the green
frog, the red and yellow cars, the blue teapot) and each colour on other kinds."""


def world_config(**kw) -> PriorTrainConfig:
    """A compositional model of the whole catalogue: the six and the world's objects, the world's
    ``WORLD_HELD_OUT`` held out; ``kw`` as ``PriorTrainConfig`` (``data`` and ``unet`` fields may
    be given as dicts of overrides)."""
    from dataclasses import replace

    from gdbench.assets.library import CAPTIONS
    from gdbench.priors.learned.data import parts_of

    held = tuple(kw.pop("held_out", WORLD_HELD_OUT))
    train = tuple(c for c in CAPTIONS if c not in held)
    data = replace(DataConfig(), **kw.pop("data", {}), captions=train)
    rows, sizes = parts_of(tuple(c for c in CAPTIONS if c in set(train) | set(held)))
    unet = replace(UNetConfig(), **kw.pop("unet", {}), captions=len(rows), parts=rows, part_sizes=sizes)
    return PriorTrainConfig(data=data, unet=unet, held_out=held, **kw)


def lr_at(cfg: PriorTrainConfig, step: int) -> float:
    """Learning rate at 0-based ``step``: linear warm-up, then cosine from ``lr`` to ``lr / 10``."""
    if step < cfg.warmup:
        return cfg.lr * (step + 1) / cfg.warmup
    t = (step - cfg.warmup) / max(cfg.steps - cfg.warmup, 1)
    return cfg.lr * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * min(t, 1.0))))


class Batches:
    """The training draws, all from one generator on the CPU (the same on every device)."""

    def __init__(self, cfg: PriorTrainConfig, data, images: torch.Tensor):
        self.cfg, self.data, self.images = cfg, data, images
        self.weights = view_weights(data.azimuth, cfg.front_bias).float()
        self.abar = sd_abar().float()
        self.g = torch.Generator().manual_seed(cfg.seed + 1)
        model = model_captions(cfg)
        self.to_model = torch.tensor([model.index(c) for c in data.captions], dtype=torch.int64)
        """A data caption index -> the model's (the same where nothing is held out)."""

    def draw(self) -> dict[str, torch.Tensor]:
        cfg, d, g, B = self.cfg, self.data, self.g, self.cfg.batch
        if cfg.front_bias:
            idx = torch.multinomial(self.weights, B, replacement=True, generator=g)
        else:
            idx = torch.randint(0, len(d), (B,), generator=g)
        t = torch.randint(0, len(self.abar), (B,), generator=g)
        eps = torch.randn((B, *self.images.shape[1:]), generator=g)
        u = torch.rand(B, 3, generator=g)
        no_caption = u[:, 0] < cfg.caption_drop
        caption = torch.where(no_caption, cfg.unet.captions, self.to_model[d.caption[idx]])
        variant = torch.where(no_caption | (u[:, 1] < cfg.variant_drop), cfg.unet.variants, d.variant[idx])
        camera_drop = no_caption | (u[:, 2] < cfg.camera_drop)
        camera = torch.stack([d.azimuth[idx], d.elevation[idx], d.fovy[idx]], 1)
        a = self.abar[t][:, None, None, None]
        x0 = self.images[idx]
        x_t = a.sqrt() * x0 + (1 - a).sqrt() * eps
        target = eps if cfg.unet.prediction == "epsilon" else a.sqrt() * eps - (1 - a).sqrt() * x0
        return {"x_t": x_t, "target": target, "t": t, "caption": caption, "variant": variant, "camera": camera,
                "camera_drop": camera_drop}  # fmt: skip


def loss_of(model: UNet, b: dict[str, torch.Tensor], device: torch.device, teacher=None, scale: float = 1.0):
    """The batch's loss: against the drawn target, or with a ``teacher`` against its guided
    prediction at ``scale`` for the same inputs (``distillation.guided_target``)."""
    b = {k: v.to(device) for k, v in b.items()}
    emb = model.embedding(b["t"], b["caption"], b["variant"], b["camera"], b["camera_drop"])
    if teacher is not None:
        b["target"] = guided_target(teacher, b, scale)
    return (model(b["x_t"], emb) - b["target"]).pow(2).mean()


def train_prior(cfg: PriorTrainConfig, *, stop_at: int | None = None) -> dict:
    """Train (or resume) the prior of ``cfg`` in ``cfg.out``; returns a summary. ``stop_at`` ends
    the call after that many steps with a checkpoint, as if the run had been killed there (calling
    again resumes it, to the same weights as an uninterrupted run on the same thread count)."""
    threads = torch.get_num_threads()
    if cfg.threads:
        torch.set_num_threads(cfg.threads)
    try:
        with torch.random.fork_rng(devices=[]):  # the seed below stays inside this call
            return _train(cfg, stop_at)
    finally:
        torch.set_num_threads(threads)


def _train(cfg: PriorTrainConfig, stop_at: int | None) -> dict:
    from gdbench.core.devices import resolve_device
    from gdbench.core.io import atomic_write
    from gdbench.core.signals import RunInterrupted, defer_stop_signals

    device = resolve_device(cfg.device)
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    ckpt_path = out / "checkpoint.pt"
    data = load_dataset(cfg.data, progress=cfg.progress, workers=cfg.data_workers)
    images = to_model_images(data.images, cfg.unet.size)
    torch.manual_seed(cfg.seed)  # the initial weights (nn.Module initialises from the global generator)
    model = UNet(cfg.unet).to(device)
    ema = UNet(cfg.unet).to(device)
    teacher = None
    if cfg.teacher:  # guidance distillation: start from the teacher's weights (distillation.py)
        teacher = load_teacher(cfg, device)
        model.load_state_dict(teacher.state_dict())
    ema.load_state_dict(model.state_dict())
    ema.requires_grad_(False)
    opt = torch.optim.AdamW(model.parameters(), lr=cfg.lr, weight_decay=cfg.weight_decay)
    batches = Batches(cfg, data, images)
    log: list[dict] = []
    step, elapsed = 0, 0.0
    acc, n = 0.0, 0  # the loss summed over the interval being logged
    if ckpt_path.is_file():
        ck = load_checkpoint(ckpt_path)
        if ck["identity"] != cfg.identity():
            changed = sorted(k for k in cfg.identity() if ck["identity"].get(k) != cfg.identity()[k])
            raise ValueError(
                f"out: {out} holds a run with other settings ({', '.join(changed)}); pick another --out or "
                "delete its checkpoint.pt"
            )
        model.load_state_dict(ck["model"])
        ema.load_state_dict(ck["ema"])
        opt.load_state_dict(ck["optimizer"])
        batches.g.set_state(ck["generator"])
        log, step, elapsed = ck["log"], ck["step"], ck.get("seconds", 0.0)
        acc, n = ck.get("partial", (0.0, 0))
        print(f"resuming {out} at step {step}")
    (out / "config.json").write_text(json.dumps(cfg.to_dict(), indent=2))

    t0 = time.perf_counter()

    def save() -> None:
        state = {
            "identity": cfg.identity(), "model": model.state_dict(), "ema": ema.state_dict(),
            "optimizer": opt.state_dict(), "generator": batches.g.get_state(), "log": log, "step": step,
            "seconds": elapsed + time.perf_counter() - t0, "partial": (acc, n),
        }  # fmt: skip
        atomic_write(ckpt_path, lambda f: torch.save(state, f))
        write_log(out / "loss.csv", log)

    from gdbench.core.progress import progress

    bar = progress(cfg.steps, f"train-prior kappa={cfg.front_bias:g}", "step", initial=step, disable=not cfg.progress)
    t0 = time.perf_counter()
    last = cfg.steps if stop_at is None else min(stop_at, cfg.steps)
    interrupted: list = []
    with defer_stop_signals(interrupted):  # a stop signal ends the step it lands in: whole steps saved
        try:
            while step < last and not interrupted:
                for group in opt.param_groups:
                    group["lr"] = lr_at(cfg, step)
                loss = loss_of(model, batches.draw(), device, teacher, cfg.teacher_guidance)
                opt.zero_grad(set_to_none=True)
                loss.backward()
                torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
                opt.step()
                decay = min(cfg.ema, (1 + step) / (10 + step))
                with torch.no_grad():
                    for pe, pm in zip(ema.parameters(), model.parameters()):
                        pe.lerp_(pm, 1 - decay)
                step += 1
                acc, n = acc + loss.item(), n + 1
                if step % cfg.log_every == 0 or step == cfg.steps:
                    secs = elapsed + time.perf_counter() - t0
                    log.append({"step": step, "loss": acc / n, "lr": lr_at(cfg, step - 1), "seconds": secs})
                    acc, n = 0.0, 0
                    if bar is not None:
                        bar.set_postfix(loss=f"{log[-1]['loss']:.4f}")
                if bar is not None:
                    bar.update(1)
                if step % cfg.checkpoint_every == 0:
                    save()
        finally:
            if bar is not None:
                bar.close()
    if interrupted:
        save()
        raise RunInterrupted.at(interrupted[0], step, cfg.steps, ckpt_path)
    save()
    if step < cfg.steps:
        return {"out": str(out), "steps": step, "final_loss": _final_loss(log), "weights": None}
    final = _final_loss(log)
    _write_model(ema, out / "model.safetensors", cfg.unet, cfg.identity(), cfg, step, final)
    plot_loss(log, out / "loss.png", title=f"kappa={cfg.front_bias:g}")
    summary = {"out": str(out), "steps": step, "final_loss": final, "weights": str(out / "model.safetensors")}
    print(f"trained {step} steps, loss {final:.4f} (mean of the last tenth) -> {out / 'model.safetensors'}")
    return summary


def _write_model(ema: UNet, path: Path, unet: UNetConfig, identity: dict, cfg, step: int, loss: float):
    from gdbench.core.provenance import code_commit
    from gdbench.priors.learned.data import data_key

    meta = {
        "unet": json.dumps(asdict(unet)), "train": json.dumps(identity), "steps": str(step),
        "commit": code_commit(), "final_loss": f"{loss:.6f}", "data_key": data_key(cfg.data),
        "captions": json.dumps(model_captions(cfg)), "held_out": json.dumps(list(cfg.held_out)),
    }  # fmt: skip
    save_weights(ema, path, meta)


def export_weights(run: Path, path: Path | None = None) -> Path:
    """The averaged weights of a run's latest checkpoint as a model.safetensors (an unfinished
    run's model, to look at while it trains); default path: <run>/model-step<N>.safetensors."""
    run = Path(run)
    ck = load_checkpoint(run / "checkpoint.pt")
    ident = ck["identity"]
    u = ident["unet"]
    unet = UNetConfig(**{**u, "widths": tuple(u["widths"]), "parts": tuple(tuple(r) for r in u.get("parts", ())),
                         "part_sizes": tuple(u.get("part_sizes", ()))})  # fmt: skip
    data = DataConfig.from_dict(ident["data"])
    cfg = PriorTrainConfig(unet=unet, data=data, held_out=tuple(ident.get("held_out", ())))
    net = UNet(unet)
    net.load_state_dict(ck["ema"])
    path = Path(path) if path is not None else run / f"model-step{ck['step']}.safetensors"
    _write_model(net, path, unet, ident, cfg, ck["step"], _final_loss(ck["log"]))
    return path


def load_checkpoint(path: Path) -> dict:
    """A training checkpoint, loaded safely (``io.load_torch_safely``: tensors and plain data only,
    so a checkpoint from elsewhere cannot run code on resume); anything else is a one-line error."""
    from gdbench.core.io import load_torch_safely

    ck = load_torch_safely(path, "delete it to start the run afresh")
    if not isinstance(ck, dict) or not {"identity", "model", "ema", "step"} <= set(ck):
        raise ValueError(f"checkpoint: {path} is not a train-prior checkpoint; pick another --out or delete it")
    return ck


def _final_loss(log: list[dict]) -> float:
    """Mean logged loss over the last tenth of the run (the curve's noise averaged out)."""
    if not log:
        return math.nan
    k = max(1, len(log) // 10)
    return sum(r["loss"] for r in log[-k:]) / k


def write_log(path: Path, log: list[dict]) -> None:
    from gdbench.core.io import atomic_write

    names = [f.name for f in fields(_LogRow)]
    text = ",".join(names) + "\n" + "".join(",".join(f"{r[k]:.6g}" for k in names) + "\n" for r in log)
    atomic_write(path, lambda f: f.write(text.encode()))


@dataclass
class _LogRow:
    step: int
    loss: float
    lr: float
    seconds: float


def save_weights(model: UNet, path: Path, metadata: dict[str, str]) -> None:
    """The model's weights in float16 (halves the shipped size; the prior computes in float32)."""
    from safetensors.torch import save

    from gdbench.core.io import atomic_write

    state = {k: v.detach().to("cpu", torch.float16).contiguous() for k, v in model.state_dict().items()}
    blob = save(state, metadata=metadata)
    atomic_write(path, lambda f: f.write(blob))


def plot_loss(log: list[dict], path: Path, title: str = "") -> None:
    """The loss curve (per logged interval, and its running mean over a tenth of the run)."""
    if not log:
        return
    from gdbench.core.plotting import pyplot, save

    plt = pyplot()
    steps = [r["step"] for r in log]
    loss = torch.tensor([r["loss"] for r in log])
    k = max(1, len(log) // 10)
    smooth = torch.nn.functional.avg_pool1d(loss[None, None], k, 1, padding=0)[0, 0]
    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot(steps, loss, lw=0.6, alpha=0.5, label="loss per interval")
    ax.plot(steps[k - 1 :], smooth, lw=1.5, label=f"running mean ({k} intervals)")
    ax.set(xlabel="step", ylabel="loss (v MSE)", yscale="log", title=f"learned prior {title}".strip())
    ax.legend()
    save(fig, path, dpi=120)


def load_teacher(cfg: PriorTrainConfig, device) -> UNet:
    """The teacher of ``cfg`` (eval mode, no gradients), checked to have the student's architecture
    and data."""
    from gdbench.priors.learned.prior import load_model

    net, meta = load_model(cfg.teacher, device)
    ident = json.loads(meta.get("train", "{}"))
    if asdict(net.config) != asdict(cfg.unet) or ident.get("data") != json.loads(json.dumps(asdict(cfg.data))):
        raise ValueError(f"teacher: {cfg.teacher} has another architecture or data than this run; build the run "
                         "with distill_config (train-prior --teacher)")  # fmt: skip
    return net


@torch.no_grad()
def guided_target(teacher: UNet, b: dict[str, torch.Tensor], scale: float) -> torch.Tensor:
    """The teacher's classifier-free guided prediction at ``scale`` for the batch's inputs (its
    conditions as drawn, with their drops) in the network's own output terms, both evaluations as
    one batch: the unconditional one drops caption, variant and camera."""
    c, t, cap, var = teacher.config, b["t"], b["caption"], b["variant"]
    B = t.shape[0]
    drop = torch.cat([torch.ones(B, dtype=torch.bool, device=t.device), b["camera_drop"].bool()])
    emb = teacher.embedding(
        torch.cat([t, t]),
        torch.cat([torch.full_like(cap, c.captions), cap]),
        torch.cat([torch.full_like(var, c.variants), var]),
        torch.cat([b["camera"], b["camera"]]),
        drop,
    )
    vu, vc = teacher(torch.cat([b["x_t"], b["x_t"]]), emb).chunk(2)
    return vu + scale * (vc - vu)
