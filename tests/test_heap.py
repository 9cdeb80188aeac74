"""service.heap: the heap's top padded once per process, never where the user set it or glibc is absent."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest

CHECK = ("import sys, mntes_stream.service.heap as h; first = h.pad_heap(); "
         "print(first, h.pad_heap(), h._padded)")


def _run(env_extra: dict) -> str:
    env = {k: v for k, v in os.environ.items() if k != "MALLOC_TOP_PAD_"} | env_extra
    return subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, env=env, check=True,
                          timeout=60).stdout.split()


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="glibc's mallopt: Linux only")
def test_the_heap_is_padded_once_and_a_users_setting_wins():
    assert _run({}) == ["True", "True", "True"]                            # padded, then idempotent
    assert _run({"MALLOC_TOP_PAD_": "1048576"}) == ["False", "False", "False"]  # the environment's pad stands
