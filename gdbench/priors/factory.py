"""The prior a training config asks for: ``TrainConfig.prior`` is one of the priors' configs, a
tagged union whose ``kind`` the command line's --prior names; each config builds its prior with
``make`` and says what the trainer renders for it (``input_space``)."""

from __future__ import annotations

from typing import Union

from gdbench.priors.empirical import EmpiricalPriorConfig
from gdbench.priors.learned.prior import LearnedPriorConfig
from gdbench.priors.sd.prior import SDPriorConfig

PriorConfig = Union[EmpiricalPriorConfig, LearnedPriorConfig, SDPriorConfig]  # noqa: UP007
"""The prior of a training run: one of the priors' configs."""

PRIOR_CONFIGS: dict[str, type] = {c.kind: c for c in (EmpiricalPriorConfig, LearnedPriorConfig, SDPriorConfig)}
"""--prior's choices -> their configs."""


def make_prior(cfg):
    """The prior of a ``TrainConfig``: built by its prior's config from what it reads of the run
    (``RunView``)."""
    return cfg.prior.make(cfg.run_view())
