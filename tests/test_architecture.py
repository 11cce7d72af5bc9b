"""The package's tiers (docs/architecture.md): a module imports only from lower tiers or from its
own package, checked on the source (lazy imports included), so a layer cannot quietly reach up.
renderers/ is the lowest tier and never imports gdbench."""

import pytest

from tests._util import import_edges

TIERS = {
    "renderers": 0,
    "gdbench.core": 1,
    "gdbench.assets": 2,
    "gdbench.mechanisms": 2,
    "gdbench.metrics": 3,
    "gdbench.priors": 4,
    "gdbench.train": 5,
    "gdbench.bench": 6,
    "gdbench.experiments": 6,
    "gdbench.refcheck": 7,
    "gdbench.app": 8,
    "gdbench": 9,  # the package's own __init__: a few names for the ten-line example
}
"""Each package of the house and its tier (docs/architecture.md draws them)."""


def package_of(module: str) -> str:
    """The longest TIERS key that ``module`` is or lives under."""
    keys = [k for k in TIERS if module == k or module.startswith(k + ".")]
    if not keys:
        raise KeyError(f"{module}: in no tier of tests/test_architecture.py's TIERS (add its package there)")
    return max(keys, key=len)


def upward(edges: dict[str, set[str]]) -> list[tuple[str, str]]:
    """(importer, imported) pairs that cross to a tier at or above the importer's, from another package."""
    bad = []
    for a, targets in edges.items():
        pa = package_of(a)
        for b in targets:
            pb = package_of(b)
            if pb != pa and TIERS[pb] >= TIERS[pa]:
                bad.append((a, b))
    return sorted(bad)


def test_no_import_crosses_a_tier_upward():
    edges = import_edges("gdbench", "renderers")
    assert len(edges) > 100 and "gdbench.core.ply" in edges["gdbench.core.scene"]  # the walk sees imports
    assert {package_of(m) for m in edges} == set(TIERS)  # every tier has modules, every module a tier
    assert upward(edges) == []


def test_the_check_catches_an_upward_import():
    """The rule itself: a lower tier reaching up, a sibling of the same tier, and renderers
    importing gdbench are each caught; imports within a package and downward are not."""
    edges = {
        "gdbench.core.scene": {"gdbench.core.ply", "renderers.splat.sh"},
        "gdbench.train.run": {"gdbench.core.io", "gdbench.priors.factory"},
        "gdbench.metrics.gt": {"gdbench.train.run"},
        "gdbench.bench.bm_cell": {"gdbench.experiments.sweep"},
        "renderers.mitsuba.volume": {"gdbench.core.camera"},
    }
    assert upward(edges) == [
        ("gdbench.bench.bm_cell", "gdbench.experiments.sweep"),
        ("gdbench.metrics.gt", "gdbench.train.run"),
        ("renderers.mitsuba.volume", "gdbench.core.camera"),
    ]
    with pytest.raises(KeyError, match="in no tier"):
        package_of("gdbench_extra.x")
