"""Nothing lost silently, live: a stalled source and a busy machine shed nothing, and the summaries say what happened.

Issue 22 measured on the earlier code: a 4 s SIGSTOP of the source during ``up`` shed 892 chunks (22 s of power)
and a busy 2-core machine shed 1,114 of 2,300, each run ending with ``lost 0``. Here the same, as separate
processes on loopback: ``up`` with its source stopped for 4 s while every core is busy with a CPU hog.
"""

from __future__ import annotations

import json
import signal
import subprocess
import sys
import time

import psutil
import pytest

from mntes_stream.bench.chaos import cpu_hog
from mntes_stream.core.ledger import Ledger
from mntes_stream.pipeline.offline import convert_recording

pytestmark = pytest.mark.slow


def test_a_stalled_source_on_a_busy_machine_sheds_nothing_and_the_summary_says_lost_0(tmp_path):
    p = subprocess.Popen([sys.executable, "-m", "mntes_stream", "up", "--duration", "24", "--out", str(tmp_path), "-q",
                          "--json", "--modules", "4", "--channels", "32"],
                         stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    hogs = []
    try:
        deadline = time.monotonic() + 120
        while not list((tmp_path / "recordings").glob("*.mcap")) and time.monotonic() < deadline:
            time.sleep(0.2)
        time.sleep(3.0)  # power flowing
        hogs = cpu_hog(14.0)
        time.sleep(3.0)
        # The services are started in order recorder, converter, source: the source is the newest child.
        kids = [c for c in psutil.Process(p.pid).children() if "resource_tracker" not in " ".join(c.cmdline())]
        source = max(kids, key=lambda c: c.create_time())
        source.send_signal(signal.SIGSTOP)
        time.sleep(4.0)
        source.send_signal(signal.SIGCONT)
        out, err = p.communicate(timeout=180)
    finally:
        for h in hogs:
            h.kill()
        if p.poll() is None:
            p.kill()
    assert p.returncode == 0, err[-2000:]
    conv = json.loads(out)["services"]["converter"]
    assert conv["chunks_shed"] == 0 and conv["chunks_set_aside"] == 0 and conv["chunks_lost"] == 0
    led = Ledger.from_dict(conv["ledger"])
    tot = led.totals()
    assert led.balanced() and tot.received == tot.done > 100 and set(led.streams) == {"0/0", "0/1", "0/2", "0/3"}
    # The summary's last line is the converter's ledger, and it is the truth.
    last = err.strip().splitlines()[-1]
    assert last.strip() == f"converter: received {tot.received} chunks: converted {tot.done}; lost 0 of {tot.received}"
    # The recording holds every counts chunk, and offline convert gives power for each of them.
    off = convert_recording(tmp_path / "recordings", tmp_path / "offline.mcap", progress=False)
    otot = Ledger.from_dict(off.ledger).totals()
    assert otot.received == otot.done >= tot.received and otot.lost == 0
