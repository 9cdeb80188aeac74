"""The suite's two workers (tests/conftest.py): each in a network namespace of its own where it can make one."""

from __future__ import annotations

import os
import subprocess

import pytest


def test_a_worker_and_its_processes_see_only_their_own_loopback():
    if os.environ.get("PYTEST_XDIST_WORKER") is None:
        pytest.skip("not in a worker (pytest -n 0)")
    if os.geteuid() != 0:
        pytest.skip("not root: the workers share the host's network and every test runs alone")
    links = subprocess.run(["ip", "-o", "link"], capture_output=True, text=True, check=True).stdout.splitlines()
    assert len(links) == 1 and ": lo:" in links[0] and "UP" in links[0], links
    # another worker's router on 7447 would be here: in a namespace of its own, the port is free
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 7447))
