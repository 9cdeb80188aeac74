"""Session-wide test set-up.

so3g (sotodlib's compiled core) and toast bundle shared libraries that must be
loaded before spt3g's: a process that imports ``spt3g.core`` first and then
``so3g`` or ``toast`` segfaults (spt3g 1.0.2, so3g 0.2.9, toast 3.0.6). The G3
and framework tests share one pytest process, so the frameworks go first.
"""

from __future__ import annotations

import contextlib
import importlib
import os
from pathlib import Path

import pytest

for _name in ("so3g", "toast"):
    with contextlib.suppress(ImportError):
        importlib.import_module(_name)


def _list(name: str) -> frozenset:
    """Node ids or files of a tests/*.txt list (one a line, ``#`` comments)."""
    return frozenset(line.split("#", 1)[0].strip() for line in Path(__file__).with_name(name).read_text().splitlines()
                     if line.split("#", 1)[0].strip())


def _listed(item, names: frozenset) -> bool:
    nodeid = item.nodeid.split("[", 1)[0]
    return nodeid in names or nodeid.split("::", 1)[0] in names


# The fast subset (`pytest -m "not slow"`, README "Development") leaves out the
# end-to-end files marked `slow` in themselves and the tests listed in
# tests/slow_tests.txt, measured over 1 s. CI runs them all.
SLOW_TESTS = _list("slow_tests.txt")


# Two workers (pyproject's addopts: `-n 2 --dist loadfile`). Each worker makes itself a network namespace of its
# own, loopback up (as root, which CI is), so services on fixed ports (a router on 7447, services/*.toml) in the
# two workers never meet; the tests in tests/exclusive_tests.txt run alone on the machine (a file lock: the others
# take it shared). Where a worker cannot have its own namespace, every test of it takes the lock exclusively: the
# suite runs one test at a time, as without workers.
EXCLUSIVE = _list("exclusive_tests.txt")
_WORKER = os.environ.get("PYTEST_XDIST_WORKER")
_ALONE_BECAUSE: str | None = None


def _own_network_namespace() -> str | None:
    """This worker's thread (the one that runs the tests and starts their processes) into a new network namespace
    with loopback up; None, or why not."""
    import ctypes
    import subprocess

    if os.geteuid() != 0:
        return "not root"
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.unshare(0x40000000) != 0:  # CLONE_NEWNET
        return f"unshare: {os.strerror(ctypes.get_errno())}"
    up = subprocess.run(["ip", "link", "set", "lo", "up"], capture_output=True, text=True)
    return None if up.returncode == 0 else f"ip link set lo up: {up.stderr.strip()}"


def pytest_configure(config):
    global _ALONE_BECAUSE
    if _WORKER is not None:
        _ALONE_BECAUSE = _own_network_namespace()


@contextlib.contextmanager
def _machine_share(exclusive: bool):
    """A readers-writer lock over the workers: a turnstile first, so an exclusive test waiting keeps new shared
    ones out."""
    import fcntl
    import tempfile

    run = os.environ.get("PYTEST_XDIST_TESTRUNUID", "run")
    base = Path(tempfile.gettempdir()) / f"mntes-stream-tests-{run}"
    with open(f"{base}.turn", "a") as turn, open(f"{base}.lock", "a") as lock:
        fcntl.flock(turn, fcntl.LOCK_EX)
        try:
            fcntl.flock(lock, fcntl.LOCK_EX if exclusive else fcntl.LOCK_SH)
        finally:
            fcntl.flock(turn, fcntl.LOCK_UN)
        try:
            yield
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item, nextitem):
    if _WORKER is None:
        yield
        return
    with _machine_share(_ALONE_BECAUSE is not None or _listed(item, EXCLUSIVE)):
        yield


# Tests that need the crossbar router, which .ci/run installs in the background while the tests run: last, so
# its install has the whole suite's time to finish before they wait for it.
NEEDS_CROSSBAR = ("tests/test_ocs_bridge.py", "tests/test_dfmux_bridge.py::test_lab_recipe_as_written")


@pytest.hookimpl(tryfirst=True)  # before -m deselects
def pytest_collection_modifyitems(config, items):
    for item in items:
        if _listed(item, SLOW_TESTS):
            item.add_marker(pytest.mark.slow)
    items.sort(key=lambda item: item.nodeid.startswith(NEEDS_CROSSBAR))  # stable: the rest keep their order
