"""The layouts of a run's config as run.json stores it, across versions of the code, and the one
converter between them.

Up to commit 95ebebe the config was flat: the prior's kind as 'prior' and every prior's settings
beside the other fields, and so were the views' and VGS's settings (views_per_step, vgs_gamma).
Then the prior became a mapping with its 'kind' and its own settings, and views and vgs mappings
of their configs (the tree). Since the house's second step, three settings have other names:
the structured noise's switch is ``noise.enabled`` (``structured_noise`` before), the noise's
mixing is ``noise.ratio`` (``noise.ratio_mode``) and view prompting belongs to the prior
(``prior.view_prompting``; ``view_prompting`` before).

Run ids, and a checkpoint's check that it resumes the same config, compare the flat layout of
95ebebe (``flat_config``), so runs keep their ids across every change; ``train.config`` reads any
layout through ``RENAMED`` and ``LEGACY_PRIOR_DEFAULTS``.
"""

from __future__ import annotations

from collections.abc import Mapping

LEGACY_PRIOR_DEFAULTS = {
    "view_window_deg": 45.0, "front_bias": 0.0, "variants": 1, "depth_conditioning": False,
    "learned_model": "auto", "learned_guidance": 3.0, "sd_model": "tiny", "sd_mode": "rgb",
    "sd_guidance": 100.0, "sd_controlnet": None, "sd_dtype": "float32", "semantic_code": False,
    "semantic_steps": 100,
}  # fmt: skip
"""The prior's settings as flat fields of the config had them up to commit 95ebebe, with their
defaults then, frozen here: run.json files of that layout hold every one of them, and a run's id
is still the hash of that layout (``flat_config``), so runs keep their ids."""

LEGACY_FLAT_GROUPS = {"views": {"per_step": "views_per_step", "spread_deg": "views_spread_deg"},
                      "vgs": {"enabled": "vgs", "gamma": "vgs_gamma", "unit": "vgs_unit"}}  # fmt: skip
"""Groups whose settings were flat fields up to commit 95ebebe, under those names."""

RENAMED = {
    "structured_noise": "noise.enabled",
    "noise.ratio_mode": "noise.ratio",
    "view_prompting": "prior.view_prompting",
}
"""Settings renamed since run.json files were first written: the old key -> today's."""


def flat_config(d: Mapping[str, object]) -> dict:
    """A config dict (``outputs.config_dict``'s, or run.json's of any layout) in the flat layout
    of commit 95ebebe and before: the prior's kind as 'prior' and its settings beside the other
    fields, those of the other priors at their defaults then (``LEGACY_PRIOR_DEFAULTS``), the noise's
    switch as 'structured_noise' and its mixing as 'ratio_mode'. Run ids and a checkpoint's config
    check compare this layout."""
    out = dict(d)
    for group, names in LEGACY_FLAT_GROUPS.items():
        if isinstance(out.get(group), Mapping):
            for k, v in out.pop(group).items():
                out[names.get(k, f"{group}_{k}")] = v  # a setting added since: its option's name
    if isinstance(out.get("noise"), Mapping):
        noise = dict(out["noise"])
        if "enabled" in noise:
            out["structured_noise"] = noise.pop("enabled")
        if "ratio" in noise:
            noise["ratio_mode"] = noise.pop("ratio")
        out["noise"] = noise
    prior = out.get("prior")
    if not isinstance(prior, Mapping):
        return out  # already flat
    out.pop("prior")
    return out | LEGACY_PRIOR_DEFAULTS | {k: v for k, v in prior.items() if k != "kind"} | {"prior": prior.get("kind")}
