"""Session-wide test set-up.

so3g (sotodlib's compiled core) and toast bundle shared libraries that must be
loaded before spt3g's: a process that imports ``spt3g.core`` first and then
``so3g`` or ``toast`` segfaults (spt3g 1.0.2, so3g 0.2.9, toast 3.0.6). The G3
and framework tests share one pytest process, so the frameworks go first.
"""

from __future__ import annotations

import contextlib
import importlib

import pytest

for _name in ("so3g", "toast"):
    with contextlib.suppress(ImportError):
        importlib.import_module(_name)


# The fast subset (`pytest -m "not slow"`, README "Development") leaves out the
# end-to-end files marked `slow` in themselves and these, each measured over a
# few seconds on the 2-core CI machine (`pytest --durations=60`): a node id, or a
# file for all its tests. CI runs them all.
SLOW_TESTS = frozenset({
})


@pytest.hookimpl(tryfirst=True)  # before -m deselects
def pytest_collection_modifyitems(config, items):
    for item in items:
        nodeid = item.nodeid.split("[", 1)[0]
        if nodeid in SLOW_TESTS or nodeid.split("::", 1)[0] in SLOW_TESTS:
            item.add_marker(pytest.mark.slow)
