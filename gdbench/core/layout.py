"""The layout of a run's config as run.json stores it, across versions of the code.

Up to commit 95ebebe the config was flat: the prior's kind as 'prior' and every prior's settings
beside the other fields, and so were the views' and VGS's settings (views_per_step, vgs_gamma).
Since then the prior is a mapping with its 'kind' and its own settings
(``train.config.TrainConfig.prior``), and views and vgs are mappings of their configs. Run ids,
and a checkpoint's check that it resumes the same config, compare the flat layout
(``flat_config``), so runs keep their ids across the change; ``train.config.config_from_dict``
reads both layouts.
"""

from __future__ import annotations

from collections.abc import Mapping

from gdbench.core.constraints import flag

LEGACY_PRIOR_DEFAULTS = {
    "view_window_deg": 45.0, "front_bias": 0.0, "variants": 1, "depth_conditioning": False,
    "learned_model": "auto", "learned_guidance": 3.0, "sd_model": "tiny", "sd_mode": "rgb",
    "sd_guidance": 100.0, "sd_controlnet": None, "sd_dtype": "float32", "semantic_code": False,
    "semantic_steps": 100,
}  # fmt: skip
"""The prior's settings as flat fields of the config had them up to commit 95ebebe, with their
defaults then, frozen here: run.json files of that layout hold every one of them, and a run's id
is still the hash of that layout (``flat_config``), so runs keep their ids."""


LEGACY_FLAT_GROUPS = ("views", "vgs")
"""Groups whose settings were flat fields up to commit 95ebebe, named as their options are
(``constraints.flag``): views_per_step, views_spread_deg, vgs, vgs_gamma, vgs_unit."""


def flat_config(d: Mapping[str, object]) -> dict:
    """A config dict (``outputs.config_dict``'s, or run.json's of either layout) in the flat layout
    of commit 95ebebe and before: the prior's kind as 'prior' and its settings beside the other
    fields, those of the other priors at their defaults then (``LEGACY_PRIOR_DEFAULTS``). Run ids
    and a checkpoint's config check compare this layout."""
    out = dict(d)
    for group in LEGACY_FLAT_GROUPS:
        if isinstance(out.get(group), Mapping):
            for k, v in out.pop(group).items():
                out[flag(f"{group}.{k}")[2:].replace("-", "_")] = v  # vgs.enabled -> vgs, vgs.gamma -> vgs_gamma
    prior = out.get("prior")
    if not isinstance(prior, Mapping):
        return out  # already flat
    out.pop("prior")
    return out | LEGACY_PRIOR_DEFAULTS | {k: v for k, v in prior.items() if k != "kind"} | {"prior": prior.get("kind")}
