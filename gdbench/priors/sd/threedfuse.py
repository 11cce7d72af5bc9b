"""3DFuse's stages around the Stable Diffusion prior: semantic code sampling (an image of the
prompt, textual inversion of a new token on it, then LoRA fine-tuning of the UNet on it),
saved into and loaded from the run folder, and the ``ImageToPoints`` role.

The Point-E role: 3DFuse lifts the generated image to a point cloud with Point-E, whose
weights are not available here; ``DepthUnprojection`` implements the ``ImageToPoints``
interface by unprojecting a depth map given with the image (a depth estimate, a bank depth,
or a render). A Point-E adapter would implement the same call.
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Protocol

import torch
from torch import Tensor

TOKEN = "<gd-object>"
LORA_TARGETS = ("to_q", "to_k", "to_v", "to_out.0")


@dataclass(frozen=True)
class SemanticCodeConfig:
    size: int = 64
    """Side of the generated image in pixels (512 with real SD weights)."""
    sample_steps: int = 30
    ti_steps: int = 100
    ti_lr: float = 5e-3
    lora_steps: int = 100
    lora_lr: float = 1e-4
    lora_rank: int = 4
    token: str = TOKEN
    seed: int = 0


# ---------------------------------------------------------------------- the diffusion loss
def diffusion_loss(prior, z0: Tensor, emb: Tensor, t: Tensor, noise: Tensor) -> Tensor:
    """The DDPM training loss at ticks t with the given noise: |eps_hat - eps|^2 (or the v
    target for v-prediction models), z0 [B, 4, h, w] channels-first latents."""
    a = prior.abar.to(z0.device)[t].to(z0.dtype)[:, None, None, None]
    x_t = a.sqrt() * z0 + (1 - a).sqrt() * noise
    out = prior.unet(x_t, t, encoder_hidden_states=emb).sample
    target = noise if prior.prediction_type == "epsilon" else a.sqrt() * noise - (1 - a).sqrt() * z0
    return ((out - target) ** 2).mean()


def _draws(n: int, z0: Tensor, generator: torch.Generator) -> tuple[Tensor, Tensor]:
    t = torch.randint(20, 980, (n,), generator=generator)
    return t, torch.randn((n, *z0.shape[1:]), generator=generator)


def eval_loss(prior, z0: Tensor, text: str, *, draws: int = 16, seed: int = 1234) -> float:
    """The diffusion loss averaged over fixed (t, noise) draws: a before/after measure."""
    g = torch.Generator().manual_seed(seed)
    t, n = _draws(draws, z0, g)
    emb = prior.embed([text]).expand(draws, -1, -1)
    with torch.no_grad():
        return float(diffusion_loss(prior, z0.expand(draws, -1, -1, -1), emb, t.to(z0.device), n.to(z0.device)))


# ---------------------------------------------------------------------- textual inversion
def add_token(prior, token: str, init_word: str) -> int:
    """Add ``token`` to the tokenizer and the text encoder, initialised from ``init_word``."""
    tok, te = prior.tokenizer, prior.text_encoder
    if token not in tok.get_vocab():
        tok.add_tokens([token])
        te.resize_token_embeddings(len(tok), mean_resizing=False)
    tid = tok.convert_tokens_to_ids(token)
    init_ids = tok(init_word, add_special_tokens=False).input_ids or [tok.convert_tokens_to_ids("<|endoftext|>")]
    with torch.no_grad():
        w = te.get_input_embeddings().weight
        w[tid] = w[init_ids].mean(0)
    return tid


def textual_inversion(prior, z0: Tensor, text: str, token: str, steps: int, lr: float, generator) -> list[float]:
    """Optimise the embedding row of ``token`` (already added) so that ``text`` denoises z0."""
    tok, te = prior.tokenizer, prior.text_encoder
    tid = tok.convert_tokens_to_ids(token)
    weight = te.get_input_embeddings().weight
    frozen = weight.detach().clone()
    weight.requires_grad_(True)
    opt = torch.optim.AdamW([weight], lr=lr, weight_decay=0.0)
    ids = tok([text], padding="max_length", max_length=tok.model_max_length, truncation=True, return_tensors="pt")
    ids = ids.input_ids.to(prior.device)
    losses = []
    try:
        for _ in range(steps):
            t, n = _draws(1, z0, generator)
            loss = diffusion_loss(prior, z0, te(ids)[0], t.to(z0.device), n.to(z0.device))
            opt.zero_grad()
            loss.backward()
            opt.step()
            with torch.no_grad():  # only the new token's row moves
                keep = torch.ones(weight.shape[0], dtype=torch.bool, device=weight.device)
                keep[tid] = False
                weight[keep] = frozen[keep]
            losses.append(loss.item())
    finally:
        weight.requires_grad_(False)
    return losses


# ---------------------------------------------------------------------- LoRA
def add_lora(prior, rank: int) -> None:
    from peft import LoraConfig

    cfg = LoraConfig(r=rank, lora_alpha=rank, target_modules=list(LORA_TARGETS), init_lora_weights=True)
    prior.unet.add_adapter(cfg)


def lora_parameters(prior) -> list[Tensor]:
    return [p for n, p in prior.unet.named_parameters() if "lora_" in n]


def train_lora(prior, z0: Tensor, text: str, steps: int, lr: float, generator) -> list[float]:
    params = lora_parameters(prior)
    if not params:
        raise ValueError("prior: no LoRA adapters on the UNet (call add_lora first)")
    for p in params:
        p.requires_grad_(True)
    opt = torch.optim.AdamW(params, lr=lr, weight_decay=0.0)
    emb = prior.embed([text])
    losses = []
    try:
        for _ in range(steps):
            t, n = _draws(1, z0, generator)
            loss = diffusion_loss(prior, z0, emb, t.to(z0.device), n.to(z0.device))
            opt.zero_grad()
            loss.backward()
            opt.step()
            losses.append(loss.item())
    finally:
        for p in params:
            p.requires_grad_(False)
    return losses


# ---------------------------------------------------------------------- the whole stage
def semantic_code(prior, prompt: str, out: str | Path, cfg: SemanticCodeConfig | None = None) -> dict:
    """Generate an image of ``prompt``, invert a token on it, fine-tune LoRA on it; save all to
    ``out`` (image.png, token.safetensors, lora/, semantic.json) and leave the prior using them.
    Returns the record written to semantic.json, with losses before and after."""
    import imageio.v3 as iio
    from safetensors.torch import save_file

    cfg = cfg or SemanticCodeConfig()
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    g = torch.Generator().manual_seed(cfg.seed)
    cond = prior.encode(prompt)
    image = prior.sample(cond, cfg.size, steps=cfg.sample_steps, generator=g)
    from gdbench.core.io import atomic_path

    with atomic_path(out / "image.png") as tmp:
        iio.imwrite(tmp, ((image[0] + 1) * 127.5).clamp(0, 255).round().to(torch.uint8).numpy())
    with torch.no_grad():
        z0 = prior.encode_images(image.to(prior.device)).permute(0, 3, 1, 2)
    text = f"{prompt}, {cfg.token}"
    add_token(prior, cfg.token, prompt.split()[-1])
    ti_before = eval_loss(prior, z0, text)
    ti = textual_inversion(prior, z0, text, cfg.token, cfg.ti_steps, cfg.ti_lr, g)
    ti_after = eval_loss(prior, z0, text)
    add_lora(prior, cfg.lora_rank)
    lora = train_lora(prior, z0, text, cfg.lora_steps, cfg.lora_lr, g)
    lora_after = eval_loss(prior, z0, text)
    tid = prior.tokenizer.convert_tokens_to_ids(cfg.token)
    save_file(
        {cfg.token: prior.text_encoder.get_input_embeddings().weight[tid].detach().cpu()}, out / "token.safetensors"
    )
    _save_lora(prior, out / "lora")
    record = {
        "prompt": prompt,
        "text": text,
        "config": asdict(cfg),
        "ti_loss_before": ti_before,
        "ti_loss_after": ti_after,
        "lora_loss_after": lora_after,
        "ti_losses": ti,
        "lora_losses": lora,
    }
    from gdbench.core.io import write_json

    write_json(record, out / "semantic.json")
    prior.code_text = text
    return record


def _save_lora(prior, path: Path) -> None:
    from peft.utils import get_peft_model_state_dict
    from safetensors.torch import save_file

    path.mkdir(parents=True, exist_ok=True)
    sd = {k: v.detach().cpu().contiguous() for k, v in get_peft_model_state_dict(prior.unet).items()}
    save_file(sd, path / "adapter.safetensors")
    rank = next(v.shape[0] for k, v in sd.items() if "lora_A" in k)
    (path / "adapter.json").write_text(json.dumps({"rank": rank, "targets": list(LORA_TARGETS)}))


def load_semantic_code(prior, folder: str | Path) -> str:
    """Load a saved semantic code (token embedding and LoRA) into ``prior``; returns the text
    the prompt becomes."""
    from peft.utils import set_peft_model_state_dict
    from safetensors.torch import load_file

    folder = Path(folder)
    meta = folder / "semantic.json"
    if not meta.is_file():
        raise FileNotFoundError(f"lora: no semantic.json in {folder} (write it with semantic_code)")
    record = json.loads(meta.read_text())
    token = record["config"]["token"]
    (emb,) = load_file(folder / "token.safetensors").values()
    tid = add_token(prior, token, "object")
    with torch.no_grad():
        prior.text_encoder.get_input_embeddings().weight[tid] = emb.to(prior.device, prior.dtype)
    info = json.loads((folder / "lora" / "adapter.json").read_text())
    add_lora(prior, info["rank"])
    set_peft_model_state_dict(prior.unet, load_file(folder / "lora" / "adapter.safetensors"))
    prior.code_text = record["text"]
    return record["text"]


# ---------------------------------------------------------------------- the Point-E role
class ImageToPoints(Protocol):
    def __call__(self, image: Tensor, depth: Tensor | None, viewmat: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        """Image [H, W, 3] in [0, 1] (and its depth [H, W] where the method needs one) seen by a
        camera (world-to-camera viewmat [4, 4], intrinsics K [3, 3]) -> points [P, 3] and
        colours [P, 3] in world coordinates."""
        ...


class DepthUnprojection:
    """``ImageToPoints`` by unprojecting a given depth map (0 = empty); Point-E stands here."""

    def __init__(self, max_points: int | None = None, seed: int = 0):
        self.max_points = max_points
        self.seed = seed

    def __call__(self, image: Tensor, depth: Tensor | None, viewmat: Tensor, K: Tensor) -> tuple[Tensor, Tensor]:
        if depth is None:
            raise ValueError("depth: DepthUnprojection needs a depth map (Point-E weights are not available here)")
        if depth.shape != image.shape[:2]:
            raise ValueError(f"depth: expected shape {list(image.shape[:2])}, got {list(depth.shape)}")
        H, W = depth.shape
        v, u = torch.meshgrid(torch.arange(H, dtype=K.dtype) + 0.5, torch.arange(W, dtype=K.dtype) + 0.5, indexing="ij")
        ok = depth > 0
        z = depth[ok].to(K.dtype)
        cam = torch.stack([(u[ok] - K[0, 2]) / K[0, 0] * z, (v[ok] - K[1, 2]) / K[1, 1] * z, z], -1)
        c2w = torch.linalg.inv(viewmat.to(K.dtype))
        pts = cam @ c2w[:3, :3].T + c2w[:3, 3]
        cols = image[ok]
        if self.max_points is not None and pts.shape[0] > self.max_points:
            idx = torch.randperm(pts.shape[0], generator=torch.Generator().manual_seed(self.seed))[: self.max_points]
            pts, cols = pts[idx], cols[idx]
        return pts, cols
