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


FREEZE = """
import gc, sys
from mntes_stream.service.base import Service
from mntes_stream.service.heap import own_process

class Once(Service):
    name = "once"
    Config = dict
    def zenoh_settings(self):
        return None
    def setup(self, ctx):
        self.built = [[i] for i in range(1000)]  # what a setup builds (containers the collector tracks)
    def step(self, ctx):
        self.frozen = gc.get_freeze_count()
        return False
    def finish(self, ctx):
        return {"frozen": self.frozen}

if sys.argv[1] == "own":
    own_process()
before = gc.get_freeze_count()
print(before, Once({}).run()["frozen"])
"""


def test_setup_is_frozen_only_in_a_process_of_its_own():
    def frozen(mode: str) -> list[int]:
        out = subprocess.run([sys.executable, "-c", FREEZE, mode], capture_output=True, text=True, check=True,
                             timeout=60).stdout.split()
        return [int(n) for n in out]

    before, during = frozen("own")
    assert before == 0 and during > 1000  # the setup's lists, and everything imported, out of the collector's walks
    assert frozen("embedded") == [0, 0]   # a process embedding services (a test, a notebook) keeps its collector
