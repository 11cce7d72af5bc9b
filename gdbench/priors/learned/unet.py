"""A small conditional UNet predicting v (or epsilon), in plain torch: the learned prior's network.

The architecture is DDPM's (Ho et al. 2020) cut down to CPU size: residual blocks with group
norm and SiLU, the conditioning scaling and shifting every block's features, stride-2 convolutions down and
nearest upsampling up, skip connections between the levels and self-attention at the coarsest
one. The conditioning, summed into one embedding vector:
- the DDPM timestep t (0..999) as a sinusoidal embedding through an MLP (as Stable Diffusion);
- the caption and the procedural variant as class embeddings, each with a learned "null" row;
- the camera (azimuth, elevation, vertical fov) as sinusoidal features of the angles through an
  MLP, or a learned null vector where the camera is dropped.
``drop`` masks choose the null rows: classifier-free guidance runs the same network with the
conditions dropped, and "view prompting none" drops the camera alone.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass

import torch
from torch import Tensor, nn
from torch.nn import functional as F


@dataclass(frozen=True)
class UNetConfig:
    size: int = 32
    """Input width and height (px)."""
    channels: int = 3
    patch: int = 2
    """Pixels per side folded into channels at the input (pixel unshuffle) and unfolded at the
    output: the network's first level works at size / patch (a CPU's per-operation cost is paid
    per pixel; 32 px at patch 2 costs about a third of patch 1 at the same widths)."""
    widths: tuple[int, ...] = (64, 96, 128)
    """Feature channels per level (each level halves the resolution)."""
    emb: int = 128
    """Width of the conditioning embedding."""
    captions: int = 6
    variants: int = 3
    camera_frequencies: int = 4
    """Sinusoidal frequencies 1..F of azimuth and elevation (fovy: a normalised scalar and its sine)."""
    groups: int = 8
    """GroupNorm groups."""
    coords: bool = True
    """Give the network where each pixel is: x, y coordinate channels at the input and a learned
    embedding of the coarsest level's positions (without them a convolutional net knows position
    only through its zero padding, and global conditions such as the camera, which must move the
    object's parts around the image, were learned slowly: docs/learned_prior.md)."""
    prediction: str = "v"
    """What the network predicts: 'v' (v = sqrt(abar) eps - sqrt(1 - abar) x0, Stable Diffusion 2's
    choice) or 'epsilon'; the prior converts either to epsilon."""

    parts: tuple[tuple[int, ...], ...] = ()
    """Compositional captions: one row per caption of part indices (kind, colour, hat, scarf; 0 is
    "none" for the last three), the caption's embedding the sum of its parts' (so a caption held out
    of training is still a sum of trained parts). Empty: one class embedding per caption."""
    part_sizes: tuple[int, ...] = ()
    """Vocabulary size of each part (its null row, the dropped caption, is index ``size``)."""

    def __post_init__(self) -> None:
        m = self.patch * 2 ** (len(self.widths) - 1)
        if self.patch < 1 or self.size % m:
            raise ValueError(f"size: expected a multiple of patch * 2^(levels - 1) = {m}, got {self.size}")
        if self.prediction not in ("v", "epsilon"):
            raise ValueError(f"prediction: expected 'v' or 'epsilon', got {self.prediction!r}")
        if self.emb % 2:
            raise ValueError(f"emb: expected an even width (sine and cosine halves), got {self.emb}")
        n = len(self.part_sizes)
        if self.parts and (len(self.parts) != self.captions or any(len(r) != n for r in self.parts)):
            raise ValueError(f"parts: expected {self.captions} rows of {n} indices, got {self.parts}")
        if any(w % self.groups for w in self.widths):
            raise ValueError(f"widths: expected multiples of groups={self.groups}, got {self.widths}")

    def to_dict(self) -> dict:
        return asdict(self)


def timestep_embedding(t: Tensor, dim: int) -> Tensor:
    """Sinusoidal embedding [B, dim] of timesteps t [B] (Transformer/DDPM frequencies)."""
    half = dim // 2
    freqs = torch.exp(-math.log(10000.0) * torch.arange(half, dtype=torch.float32, device=t.device) / half)
    a = t.float()[:, None] * freqs[None]
    return torch.cat([a.cos(), a.sin()], 1)


def camera_features(azimuth: Tensor, elevation: Tensor, fovy: Tensor, frequencies: int) -> Tensor:
    """[B, 4F + 2] sinusoidal camera features: cos/sin(k az), cos/sin(k el) for k = 1..F (angles in
    degrees; azimuth wraps around), and fovy mapped from its training range 40-70 to [-1, 1] with its
    sine."""
    k = torch.arange(1, frequencies + 1, dtype=torch.float32, device=azimuth.device)
    a = torch.deg2rad(azimuth.float())[:, None] * k
    e = torch.deg2rad(elevation.float())[:, None] * k
    f = ((fovy.float() - 55.0) / 15.0)[:, None]
    return torch.cat([a.cos(), a.sin(), e.cos(), e.sin(), f, torch.sin(f)], 1)


class ResBlock(nn.Module):
    def __init__(self, cin: int, cout: int, emb: int, groups: int):
        super().__init__()
        self.norm1 = nn.GroupNorm(groups, cin)
        self.conv1 = nn.Conv2d(cin, cout, 3, padding=1)
        self.emb = nn.Linear(emb, 2 * cout)
        self.norm2 = nn.GroupNorm(groups, cout)
        self.conv2 = nn.Conv2d(cout, cout, 3, padding=1)
        self.skip = nn.Conv2d(cin, cout, 1) if cin != cout else nn.Identity()
        nn.init.zeros_(self.conv2.weight)  # each block starts as the identity
        nn.init.zeros_(self.conv2.bias)

    def forward(self, x: Tensor, emb: Tensor) -> Tensor:
        h = self.conv1(F.silu(self.norm1(x)))
        scale, shift = self.emb(emb)[:, :, None, None].chunk(2, 1)
        h = self.norm2(h) * (1 + scale) + shift
        return self.skip(x) + self.conv2(F.silu(h))


class Attention(nn.Module):
    """Single-head self-attention over the pixels of a (coarse) feature map."""

    def __init__(self, ch: int, groups: int):
        super().__init__()
        self.norm = nn.GroupNorm(groups, ch)
        self.qkv = nn.Conv2d(ch, 3 * ch, 1)
        self.out = nn.Conv2d(ch, ch, 1)
        nn.init.zeros_(self.out.weight)
        nn.init.zeros_(self.out.bias)

    def forward(self, x: Tensor) -> Tensor:
        B, C, H, W = x.shape
        q, k, v = self.qkv(self.norm(x)).reshape(B, 3, C, H * W).transpose(-1, -2).unbind(1)
        h = F.scaled_dot_product_attention(q, k, v)
        return x + self.out(h.transpose(-1, -2).reshape(B, C, H, W))


class UNet(nn.Module):
    def __init__(self, config: UNetConfig | None = None):
        super().__init__()
        c = self.config = config or UNetConfig()
        E, G, W = c.emb, c.groups, c.widths
        self.t_mlp = nn.Sequential(nn.Linear(E, E), nn.SiLU(), nn.Linear(E, E))
        if c.parts:  # a caption is the sum of its parts' embeddings; the null caption, of their null rows
            self.part_embs = nn.ModuleList(nn.Embedding(n + 1, E) for n in c.part_sizes)
            table = torch.tensor([*c.parts, c.part_sizes], dtype=torch.int64)
            self.register_buffer("part_table", table, persistent=False)
        else:
            self.caption_emb = nn.Embedding(c.captions + 1, E)  # the last row is "no caption"
        self.variant_emb = nn.Embedding(c.variants + 1, E)
        self.cam_mlp = nn.Sequential(nn.Linear(4 * c.camera_frequencies + 2, E), nn.SiLU(), nn.Linear(E, E))
        self.cam_null = nn.Parameter(torch.zeros(E))
        self.conv_in = nn.Conv2d(c.channels * c.patch**2 + (2 if c.coords else 0), W[0], 3, padding=1)
        coarse = c.size // (c.patch * 2 ** (len(W) - 1))
        self.pos = nn.Parameter(torch.zeros(1, W[-1], coarse, coarse)) if c.coords else None
        self.down = nn.ModuleList()
        self.downsample = nn.ModuleList()
        prev = W[0]
        for i, w in enumerate(W):
            self.down.append(ResBlock(prev, w, E, G))
            prev = w
            if i < len(W) - 1:
                self.downsample.append(nn.Conv2d(w, w, 3, stride=2, padding=1))
        self.mid1 = ResBlock(prev, prev, E, G)
        self.mid_attn = Attention(prev, G)
        self.mid2 = ResBlock(prev, prev, E, G)
        self.up = nn.ModuleList()
        self.upsample = nn.ModuleList()
        for i, w in reversed(list(enumerate(W))):
            self.up.append(ResBlock(prev + w, w, E, G))
            prev = w
            if i > 0:
                self.upsample.append(nn.Conv2d(w, W[i - 1], 3, padding=1))
                prev = W[i - 1]
        self.norm_out = nn.GroupNorm(G, prev)
        self.conv_out = nn.Conv2d(prev, c.channels * c.patch**2, 3, padding=1)
        nn.init.zeros_(self.conv_out.weight)
        nn.init.zeros_(self.conv_out.bias)

    def caption_embedding(self, caption: Tensor) -> Tensor:
        """[B, emb] of caption indices [B] (``captions``: the null caption)."""
        if not self.config.parts:
            return self.caption_emb(caption)
        rows = self.part_table[caption]
        return sum(emb(rows[:, j]) for j, emb in enumerate(self.part_embs))

    def embedding(
        self,
        t: Tensor,
        caption: Tensor,
        variant: Tensor,
        camera: Tensor | None,
        camera_drop: Tensor | None = None,
    ) -> Tensor:
        """[B, emb]: caption/variant indices equal to ``captions``/``variants`` are the null rows;
        ``camera`` [B, 3] (azimuth, elevation, fovy in degrees) or None (all dropped);
        ``camera_drop`` [B] bool drops single rows."""
        c = self.config
        e = self.t_mlp(timestep_embedding(t, c.emb)) + self.caption_embedding(caption) + self.variant_emb(variant)
        if camera is None:
            return e + self.cam_null
        cam = self.cam_mlp(camera_features(camera[:, 0], camera[:, 1], camera[:, 2], c.camera_frequencies))
        if camera_drop is not None:
            cam = torch.where(camera_drop[:, None], self.cam_null.expand_as(cam), cam)
        return e + cam

    def forward(self, x: Tensor, emb: Tensor) -> Tensor:
        """The prediction (``config.prediction``) [B, C, H, W] for DDPM inputs x [B, C, H, W] under
        embeddings ``emb`` [B, E]."""
        p = self.config.patch
        h = F.pixel_unshuffle(x, p) if p > 1 else x
        if self.config.coords:
            n = h.shape[-1]
            r = (torch.arange(n, device=x.device, dtype=x.dtype) + 0.5) / n * 2 - 1
            yy, xx = torch.meshgrid(r, r, indexing="ij")
            h = torch.cat([h, torch.stack([xx, yy]).expand(h.shape[0], -1, -1, -1)], 1)
        h = self.conv_in(h)
        skips = []
        for i, block in enumerate(self.down):
            h = block(h, emb)
            skips.append(h)
            if i < len(self.downsample):
                h = self.downsample[i](h)
        if self.pos is not None:
            h = h + self.pos
        h = self.mid2(self.mid_attn(self.mid1(h, emb)), emb)
        for i, block in enumerate(self.up):
            h = block(torch.cat([h, skips.pop()], 1), emb)
            if i < len(self.upsample):
                h = self.upsample[i](F.interpolate(h, scale_factor=2.0, mode="nearest"))
        out = self.conv_out(F.silu(self.norm_out(h)))
        return F.pixel_shuffle(out, p) if p > 1 else out
