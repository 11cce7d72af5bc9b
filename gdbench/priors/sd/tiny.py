"""Tiny, randomly initialised Stable Diffusion components built from configs, offline.

The tests (and anyone without weights) run the whole Stable Diffusion path with these: a
UNet, a VAE with SD's factor-8 latents, a CLIP text model, a depth ControlNet, the DDPM
scheduler with SD's scaled-linear betas, and the real CLIP tokenizer built from the BPE
vocabulary that ``open_clip_torch`` ships (no download). The weights are random, so
images mean nothing; shapes, conversions and gradients are those of the real models.

Writes nothing unless asked: ``save_tiny_model(path)`` lays the components out like a
diffusers model folder (``unet/``, ``vae/``, ``text_encoder/``, ``tokenizer/``,
``scheduler/``), which ``StableDiffusionPrior.from_pretrained`` loads as it would SD.
"""

from __future__ import annotations

import gzip
import json
from functools import lru_cache
from pathlib import Path

import torch

from gdbench.assets.bank import cache_dir

HIDDEN = 32
"""Width of the tiny text model (the UNet's cross-attention dimension)."""


def _bytes_to_unicode() -> dict[int, str]:
    """GPT-2/CLIP's reversible byte -> printable character map."""
    bs = list(range(ord("!"), ord("~") + 1)) + list(range(ord("¡"), ord("¬") + 1)) + list(range(ord("®"), ord("ÿ") + 1))
    cs = bs[:]
    n = 0
    for b in range(256):
        if b not in bs:
            bs.append(b)
            cs.append(256 + n)
            n += 1
    return dict(zip(bs, map(chr, cs)))


@lru_cache(maxsize=1)
def clip_tokenizer_files() -> tuple[Path, Path]:
    """(vocab.json, merges.txt) of CLIP's tokenizer, written once from open_clip's BPE file.

    The vocabulary is built as open_clip's SimpleTokenizer builds it: the 256 byte symbols,
    the same with an end-of-word mark, the 48,894 merges, then the two special tokens, which
    reproduces OpenAI CLIP's 49,408-entry vocabulary (start 49406, end 49407)."""
    import importlib.util

    out = cache_dir().parent / "clip_tokenizer"
    vocab_path, merges_path = out / "vocab.json", out / "merges.txt"
    if vocab_path.is_file() and merges_path.is_file():  # written once: open_clip is needed only then
        return vocab_path, merges_path
    # find the file without importing open_clip (which would need torchvision)
    spec = importlib.util.find_spec("open_clip")
    bpe = Path(spec.origin).parent / "bpe_simple_vocab_16e6.txt.gz" if spec and spec.origin else None
    if bpe is None or not bpe.is_file():
        raise ImportError("the CLIP tokenizer needs open_clip's BPE file: pip install --no-deps open_clip_torch")
    lines = gzip.open(bpe).read().decode("utf-8").split("\n")[1 : 49152 - 256 - 2 + 1]
    merges = [tuple(m.split()) for m in lines]
    vocab = list(_bytes_to_unicode().values())
    vocab = vocab + [v + "</w>" for v in vocab] + ["".join(m) for m in merges] + ["<|startoftext|>", "<|endoftext|>"]
    out.mkdir(parents=True, exist_ok=True)
    tmp_v, tmp_m = vocab_path.with_suffix(".tmp"), merges_path.with_suffix(".tmp")
    tmp_v.write_text(json.dumps({t: i for i, t in enumerate(vocab)}))
    tmp_m.write_text("#version: 0.2\n" + "\n".join(" ".join(m) for m in merges) + "\n")
    tmp_v.replace(vocab_path)
    tmp_m.replace(merges_path)
    return vocab_path, merges_path


def clip_tokenizer():
    from transformers import CLIPTokenizer

    vocab, merges = clip_tokenizer_files()
    return CLIPTokenizer(str(vocab), str(merges), pad_token="<|endoftext|>", model_max_length=77)


def tiny_components(seed: int = 0, *, prediction_type: str = "epsilon") -> dict:
    """unet, vae, text_encoder, tokenizer, scheduler and a depth controlnet, seeded."""
    from diffusers import AutoencoderKL, ControlNetModel, DDPMScheduler, UNet2DConditionModel
    from transformers import CLIPTextConfig, CLIPTextModel

    torch.manual_seed(seed)  # diffusers/transformers initialise from the global generator
    unet = UNet2DConditionModel(
        sample_size=8,
        in_channels=4,
        out_channels=4,
        block_out_channels=(32, 64),
        layers_per_block=1,
        down_block_types=("CrossAttnDownBlock2D", "DownBlock2D"),
        up_block_types=("UpBlock2D", "CrossAttnUpBlock2D"),
        cross_attention_dim=HIDDEN,
        attention_head_dim=4,
        norm_num_groups=8,
    )
    vae = AutoencoderKL(
        in_channels=3,
        out_channels=3,
        down_block_types=("DownEncoderBlock2D",) * 4,
        up_block_types=("UpDecoderBlock2D",) * 4,
        block_out_channels=(8, 8, 16, 16),
        latent_channels=4,
        layers_per_block=1,
        norm_num_groups=4,
        sample_size=64,
    )
    text = CLIPTextModel(
        CLIPTextConfig(
            vocab_size=49408,
            hidden_size=HIDDEN,
            intermediate_size=64,
            num_hidden_layers=2,
            num_attention_heads=4,
            max_position_embeddings=77,
            bos_token_id=49406,
            eos_token_id=49407,
            pad_token_id=49407,
        )
    )
    controlnet = ControlNetModel.from_unet(unet, conditioning_embedding_out_channels=(8, 8, 16, 16))
    scheduler = DDPMScheduler(
        num_train_timesteps=1000,
        beta_start=0.00085,
        beta_end=0.012,
        beta_schedule="scaled_linear",
        clip_sample=False,
        prediction_type=prediction_type,
    )
    for m in (unet, vae, text, controlnet):
        m.eval().requires_grad_(False)
    return {
        "unet": unet,
        "vae": vae,
        "text_encoder": text,
        "tokenizer": clip_tokenizer(),
        "scheduler": scheduler,
        "controlnet": controlnet,
    }


def save_tiny_model(path: str | Path, seed: int = 0, *, prediction_type: str = "epsilon") -> Path:
    """Write the tiny components as a diffusers model folder (and ``controlnet/``)."""
    path = Path(path)
    parts = tiny_components(seed, prediction_type=prediction_type)
    for name, part in parts.items():
        part.save_pretrained(path / name)
    (path / "model_index.json").write_text(json.dumps({"_class_name": "StableDiffusionPipeline", "gdbench_tiny": True}))
    return path
