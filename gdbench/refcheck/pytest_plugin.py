"""pytest plugin (entry point ``pytest11``, loaded wherever gdbench is installed): a renderer's own
test suite runs gdbench's conformance cases as tests.

    pytest --gdbench-renderer pkg.mod:rasterize            # every fixture scene and stiff case
    pytest --gdbench-renderer pkg.mod:rasterize --gdbench-case "huge scale 1e4" --gdbench-case isotropic

Each (renderer, case) is one test, ``gdbench[<renderer>::<case>]``: it passes on PASS, fails with
the case's reason on FAIL and is skipped, with the reason, on SKIP (docs/references.md, "Bring your
own renderer"). Without ``--gdbench-renderer`` the plugin adds nothing. Importing it is cheap: the
renderer and torch load only when cases are collected.
"""

from __future__ import annotations

import pytest


def pytest_addoption(parser) -> None:
    group = parser.getgroup("gdbench", "gdbench conformance (images and gradients against the float64 twin)")
    group.addoption("--gdbench-renderer", action="append", default=[], metavar="REF",
                    help="a renderer to check: module:function, path/to/file.py:function or a built-in name "
                         "(repeat for several)")  # fmt: skip
    group.addoption("--gdbench-case", action="append", default=[], metavar="NAME",
                    help="only this case (repeat; default: every fixture scene and stiff case)")  # fmt: skip


class ConformanceItem(pytest.Item):
    """One renderer on one conformance case."""

    def __init__(self, *, spec, case: str, cache: dict, **kwargs) -> None:
        super().__init__(**kwargs)
        self.spec, self.case, self.cache = spec, case, cache

    def runtest(self) -> None:
        from gdbench.refcheck import conformance as cf

        twins = self.cache.setdefault(self.case, {})
        row = cf.check(self.spec, cf.case_names()[self.case](), twins)
        self.user_properties.append(("conformance", row))
        if row["verdict"] == "SKIP":
            pytest.skip(row["reason"])
        if row["verdict"] == "FAIL":
            raise ConformanceFailure(row)

    def repr_failure(self, excinfo, style=None):
        if isinstance(excinfo.value, ConformanceFailure):
            r = excinfo.value.row
            return f"{r['renderer']} on {r['case']!r} ({r['class']} class): FAIL: {r['reason']}"
        return super().repr_failure(excinfo, style)

    def reportinfo(self):
        return self.path, None, f"gdbench conformance: {self.spec.name} on {self.case!r}"


class ConformanceFailure(Exception):
    def __init__(self, row: dict) -> None:
        super().__init__(row["reason"])
        self.row = row


@pytest.hookimpl(tryfirst=True)  # before -k / -m select among the items
def pytest_collection_modifyitems(session, config, items) -> None:
    refs = config.getoption("gdbench_renderer")
    if not refs:
        return
    from gdbench.refcheck.conformance import case_names
    from gdbench.refcheck.protocol import load_or_fail

    known = list(case_names())
    wanted = config.getoption("gdbench_case") or known
    unknown = [c for c in wanted if c not in known]
    if unknown:
        raise pytest.UsageError(f"--gdbench-case: unknown {unknown}; known: {known}")
    cache: dict = {}
    for ref in refs:
        spec = load_or_fail(ref)  # one that cannot load fails each of its cases with the reason
        for case in wanted:
            items.append(ConformanceItem.from_parent(session, name=f"gdbench[{spec.name}::{case}]", spec=spec,
                                                     case=case, cache=cache))  # fmt: skip
