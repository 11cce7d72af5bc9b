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


def _long_functions(root, limit: int) -> list[tuple[str, str, int]]:
    """(file, function, lines) of every function over ``limit`` lines under ``root``, nested ones
    included, counted from its ``def`` to its last line."""
    import ast

    out = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                n = node.end_lineno - node.lineno + 1
                if n > limit:
                    out.append((str(path.relative_to(root.parent)), node.name, n))
    return out


def test_no_function_is_over_100_lines(tmp_path):
    """The house's rule: a long function is split where its steps have names. The counter is
    checked on a file written here (a function of 101 lines is found, one of 100 is not)."""
    from pathlib import Path

    demo = tmp_path / "pkg"
    demo.mkdir()
    body = "\n".join(f"    x{i} = {i}" for i in range(99))
    (demo / "m.py").write_text(f"def ok():\n{body}\n\n\ndef long():\n{body}\n    return x0\n")
    assert _long_functions(demo, 100) == [("pkg/m.py", "long", 101)]
    root = Path(__file__).resolve().parent.parent
    assert [f for d in ("gdbench", "renderers") for f in _long_functions(root / d, 100)] == []


def _root():
    from pathlib import Path

    return Path(__file__).resolve().parent.parent


def test_the_readme_fits_on_a_screen_or_two_and_its_links_resolve():
    """At most 250 lines (the whole v3 verdict lives in docs/decisive_v3.md), and every relative
    link of the README and of docs/*.md names a file or folder that exists."""
    import re

    root = _root()
    readme = (root / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) <= 250
    assert (
        "docs/decisive_v3.md#the-verdict" in readme and "## The verdict" in (root / "docs/decisive_v3.md").read_text()
    )
    missing = []
    for md in [root / "README.md", *sorted((root / "docs").glob("*.md"))]:
        for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", md.read_text(encoding="utf-8")):
            if "://" not in target and not (md.parent / target).exists():
                missing.append(f"{md.relative_to(root)}: {target}")
    assert missing == []


def test_the_modules_docs_architecture_names_exist():
    """Every module path docs/architecture.md names (`train/options.py`, `gdbench/core/io.py`,
    `core.constraints.flag`) is in the package, outside its table of what moved where."""
    import re

    root = _root()
    text = (root / "docs" / "architecture.md").read_text(encoding="utf-8")
    assert "## What moved where" not in text  # the history is in docs/log/
    named = set(re.findall(r"(?<![\w/.{])((?:gdbench/|renderers/)?[a-z_0-9]+(?:/[a-z_0-9]+)+\.py)", text))
    assert len(named) > 20  # not vacuous
    bad = [n for n in named if not any((root / base / n).exists() for base in ("", "gdbench"))]
    assert bad == []
    dotted = set(re.findall(r"`((?:core|train|priors|metrics|experiments|app|refcheck|bench|mechanisms|assets)"
                            r"\.[a-z_0-9.]+)`", text))  # fmt: skip
    from pathlib import Path

    for d in dotted:
        parts = d.split(".")
        assert any((root / "gdbench" / Path(*parts[:k])).with_suffix(".py").exists()
                   or (root / "gdbench" / Path(*parts[:k])).is_dir() for k in range(1, len(parts) + 1)), d  # fmt: skip
