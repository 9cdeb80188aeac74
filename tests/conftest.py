"""Session-wide test set-up.

so3g (sotodlib's compiled core) and toast bundle shared libraries that must be
loaded before spt3g's: a process that imports ``spt3g.core`` first and then
``so3g`` or ``toast`` segfaults (spt3g 1.0.2, so3g 0.2.9, toast 3.0.6). The G3
and framework tests share one pytest process, so the frameworks go first.
"""

from __future__ import annotations

import contextlib
import importlib
from pathlib import Path

import pytest

for _name in ("so3g", "toast"):
    with contextlib.suppress(ImportError):
        importlib.import_module(_name)


# The fast subset (`pytest -m "not slow"`, README "Development") leaves out the
# end-to-end files marked `slow` in themselves and the tests listed in
# tests/slow_tests.txt, measured over 1 s. CI runs them all.
SLOW_TESTS = frozenset(
    line.split("#", 1)[0].strip()
    for line in (Path(__file__).with_name("slow_tests.txt")).read_text().splitlines()
    if line.split("#", 1)[0].strip()
)


# Tests that need the crossbar router, which .ci/run installs in the background while the tests run: last, so
# its install has the whole suite's time to finish before they wait for it.
NEEDS_CROSSBAR = ("tests/test_ocs_bridge.py", "tests/test_dfmux_bridge.py::test_lab_recipe_as_written")


@pytest.hookimpl(tryfirst=True)  # before -m deselects
def pytest_collection_modifyitems(config, items):
    for item in items:
        nodeid = item.nodeid.split("[", 1)[0]
        if nodeid in SLOW_TESTS or nodeid.split("::", 1)[0] in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
    items.sort(key=lambda item: item.nodeid.startswith(NEEDS_CROSSBAR))  # stable: the rest keep their order
