"""``gdbench cache build``: what a default run of a prompt and its scores read from the cache
(the prior's image bank, the view metrics' reference ring, the ground truth's held-out views, the
prompt check's palette), built ahead of the first run; scripts/setup.sh runs it in the background."""

from __future__ import annotations

import json
import tempfile
import time

PREBUILT = "prebuilt.json"
"""Written into the banks folder when ``build`` has built every asset (scripts/setup.sh looks for
it before starting a background build)."""


def build(prompts: list[str] | None = None) -> list[str]:
    """Build what a default run (``generate --preset gd``) and its scores need for each prompt, in
    order: the prior's image bank, the view metrics' reference ring, the ground truth's held-out
    views and the prompt check's palette. Default: every asset, "a yellow duck" last (the demo
    builds its own in the meantime). Returns the captions built for; when all were, writes
    ``PREBUILT``."""
    from gdbench.assets.bank import ASSET_VERSION
    from gdbench.assets.library import ASSETS
    from gdbench.core.cache import root
    from gdbench.core.io import atomic_write
    from gdbench.metrics.gt import asset_views, heldout_poses
    from gdbench.metrics.views import reference
    from gdbench.priors.factory import make_prior
    from gdbench.priors.prompt_check import palette
    from gdbench.train.config import preset

    everything = prompts is None
    if everything:
        prompts = sorted(ASSETS, key=lambda c: (c == "a yellow duck", c))
    done = []
    for prompt in prompts:
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            cfg = preset("gd", prompt=prompt, out=tmp, progress=False)
            prior = make_prior(cfg)
            caption = getattr(prior.encode(prompt), "caption", prompt)  # refuses a prompt no asset matches
        reference(caption)
        asset_views(caption, heldout_poses(12), 64)
        palette(caption)
        done.append(caption)
        print(f"gdbench cache: {caption!r} ready ({time.perf_counter() - t0:.1f} s)", flush=True)
    if everything:
        blob = json.dumps({"asset_version": ASSET_VERSION, "captions": done}).encode()
        atomic_write(root() / "banks" / PREBUILT, lambda f: f.write(blob))
    return done
