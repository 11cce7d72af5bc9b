"""``generate --log-dir``: the run's scalars as TensorBoard events, for those who watch runs there.

Every ``log_every`` steps: the score residual, sigma, the Gaussians' count, mean opacity and the
step's seconds (with its parts: views, render, noise, prior, update). Every ``checkpoint_every``
steps and at the end, where the prompt matched a built-in asset: the PSNR of the current scene
against the asset at the 12 held-out views (aligned, no azimuth search: ``metrics.gt``), the curve
``gdbench score`` ends on. Events go to ``log_dir/<run folder name>-<preset>-<run id>``, so runs
compare side by side; tensorboard itself is loaded only when asked for.
"""

from __future__ import annotations

from pathlib import Path

import torch

SCALARS = ("residual", "sigma", "n", "alpha", "seconds", "t_views", "t_render", "t_noise", "t_prior", "t_update")
"""Step metrics written (``trainer.train_step``'s keys); ``n`` is written as ``gaussians``."""


def require_tensorboard() -> None:
    """Raise an ImportError saying what to install when tensorboard is missing."""
    import importlib.util

    if importlib.util.find_spec("tensorboard") is None:
        raise ImportError("--log-dir needs tensorboard: pip install -e '.[log]' (or `make setup`)")


class ScalarLog:
    def __init__(self, cfg, ctx, run_id: str):
        require_tensorboard()
        from torch.utils.tensorboard import SummaryWriter

        self.cfg, self.ctx = cfg, ctx
        # one folder per run folder and config: runs of one config in two folders stay apart
        self.dir = Path(cfg.log_dir) / f"{Path(cfg.out).name}-{cfg.preset}-{run_id}"
        self.writer = SummaryWriter(log_dir=str(self.dir))
        self.caption = getattr(ctx.cond, "caption", None)
        self._ref = None

    def step(self, state, m: dict, last: int) -> None:
        step = state.step
        if step % self.cfg.log_every == 0 or step == last:
            for k in SCALARS:
                if k in m:
                    self.writer.add_scalar(f"train/{'gaussians' if k == 'n' else k}", float(m[k]), step)
        if self.caption is not None and (step % self.cfg.checkpoint_every == 0 or step == last):
            self.writer.add_scalar("gt/psnr_vs_asset", self.psnr(state), step)

    def psnr(self, state) -> float:
        """PSNR (dB) of the current scene against the asset at the held-out views, aligned (the
        asset's views rendered once per run)."""
        from gdbench.metrics.gt import asset_views, heldout_poses, score_against_asset

        bg = self.cfg.background
        if self._ref is None:
            self._ref = asset_views(self.caption, heldout_poses(), 64, bg, 0)
        at0 = torch.zeros(1, dtype=torch.float64)  # no azimuth search
        return score_against_asset(state.scene(), self.caption, offsets=at0, background=bg, reference=self._ref).psnr

    def close(self) -> None:
        self.writer.flush()
        self.writer.close()
