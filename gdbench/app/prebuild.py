"""``gdbench cache build``: what a default run of a prompt and its scores read from the cache
(the prior's image bank, the view metrics' reference ring and its front masks, the ground truth's held-out views, the
prompt check's palette), built ahead of the first run; scripts/setup.sh runs it in the background."""

from __future__ import annotations

import json
import os
import tempfile
import time

PID = "prebuild.pid"
"""Written into the cache folder while ``build`` runs (its process id), removed when it ends:
``generate`` says so when it starts beside a build (``running``)."""

PREBUILT = "prebuilt.json"
"""Written into the banks folder when ``build`` has built every asset (scripts/setup.sh looks for
it before starting a background build)."""


def build(prompts: list[str] | None = None) -> list[str]:
    """Build what a default run (``generate --preset gd``) and its scores need for each prompt, in
    order: the prior's image bank, the view metrics' reference ring, the ground truth's held-out
    views and the prompt check's palette. Default: every asset, "a yellow duck" last (the demo
    builds its own in the meantime). Returns the captions built for; when all were, writes
    ``PREBUILT``. While it runs, ``PID`` in the cache folder names its process."""
    from gdbench.assets.library import ASSETS
    from gdbench.core.cache import root

    everything = prompts is None
    if everything:
        prompts = sorted(ASSETS, key=lambda c: (c == "a yellow duck", c))
    pid = root() / PID
    pid.parent.mkdir(parents=True, exist_ok=True)
    pid.write_text(str(os.getpid()))
    try:
        return _build(prompts, everything)
    finally:
        pid.unlink(missing_ok=True)


def running() -> int | None:
    """The process id of a ``gdbench cache build`` running now (its ``PID`` file names a live
    process), else None."""
    from gdbench.core.cache import root

    try:
        pid = int((root() / PID).read_text().strip())
        os.kill(pid, 0)
    except (OSError, ValueError):
        return None
    return pid if pid != os.getpid() else None


def _build(prompts: list[str], everything: bool) -> list[str]:
    from gdbench.assets.bank import ASSET_VERSION, cache_dir
    from gdbench.core.cache import root
    from gdbench.core.io import atomic_write
    from gdbench.metrics.gt import asset_views, heldout_poses
    from gdbench.metrics.views import reference
    from gdbench.priors.factory import make_prior
    from gdbench.priors.prompt_check import palette
    from gdbench.train.config import preset

    done = []
    for i, prompt in enumerate(prompts, 1):
        before = _size(cache_dir())
        t0 = time.perf_counter()
        with tempfile.TemporaryDirectory() as tmp:
            cfg = preset("gd", prompt=prompt, out=tmp, progress=False)
            prior = make_prior(cfg)
            caption = getattr(prior.encode(prompt), "caption", prompt)  # refuses a prompt no asset matches
        reference(caption)
        asset_views(caption, heldout_poses(12), 64)
        palette(caption)
        done.append(caption)
        added = (_size(cache_dir()) - before) / 2**20
        count = f"[{i}/{len(prompts)}] " if len(prompts) > 1 else ""
        took = time.perf_counter() - t0
        print(f"gdbench cache: {count}{caption!r} ready ({took:.1f} s, +{added:.0f} MB)", flush=True)
    if everything:
        blob = json.dumps({"asset_version": ASSET_VERSION, "captions": done}).encode()
        atomic_write(root() / "banks" / PREBUILT, lambda f: f.write(blob))
    return done


def _size(folder) -> int:
    """Bytes of the files in ``folder`` (0 if it does not exist)."""
    return sum(f.stat().st_size for f in folder.glob("*") if f.is_file()) if folder.is_dir() else 0
