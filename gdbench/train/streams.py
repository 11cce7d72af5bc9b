"""Paired random streams: one ``torch.Generator`` per kind of draw, each seeded from the run's
seed and the stream's name.

Two presets with one seed then draw the same initial scene, the same views, the same noise
levels and the same iid noise, and differ only in what they ablate (docs/training.md, "Paired
random streams"): a preset that switches VGS off simply never touches the ``jitter`` stream, so
it cannot shift the draws of any other. ``gd`` mixes its structured noise with the iid field that
``sjc-gs`` uses as its whole noise, so even the noise is paired.
"""

from __future__ import annotations

import hashlib

import torch
from torch import Tensor

STREAMS = ("init", "noise_cloud", "views", "sigma", "jitter", "noise_colors", "noise_iid", "densify")
"""init: the initial Gaussians; noise_cloud: the noise Gaussians' geometry; views: training poses;
sigma: noise levels; jitter: VGS; noise_colors: the noise cloud's colours (and iid fill where it
covers nothing); noise_iid: the iid noise (all of it without structured noise, its iid part with);
densify: split offsets."""


def stream_seed(seed: int, name: str) -> int:
    """A 63-bit seed for stream ``name`` of run seed ``seed`` (stable across versions and platforms)."""
    if name not in STREAMS:
        raise ValueError(f"name: unknown stream {name!r}; expected one of {STREAMS}")
    digest = hashlib.sha256(f"gdbench/{int(seed)}/{name}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & (2**63 - 1)


def make_streams(seed: int) -> dict[str, torch.Generator]:
    return {name: torch.Generator().manual_seed(stream_seed(seed, name)) for name in STREAMS}


def stream_states(streams: dict[str, torch.Generator]) -> dict[str, Tensor]:
    return {name: g.get_state() for name, g in streams.items()}


def set_stream_states(streams: dict[str, torch.Generator], states: dict[str, Tensor]) -> None:
    missing = set(STREAMS) - set(states)
    if missing:
        raise ValueError(f"states: missing random streams {sorted(missing)}")
    for name in STREAMS:
        streams[name].set_state(states[name])
