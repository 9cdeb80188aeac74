"""``mntes-stream up``: simulator, converter and recorder as processes; power flows, the MCAP grows, Ctrl-C stops all cleanly."""

from __future__ import annotations

import re
import signal
import subprocess
import sys
import time

from mntes_stream.io.mcap_io import Session
from mntes_stream.io.messages import PowerChunk, decode


def test_up_runs_until_ctrl_c_and_leaves_a_finished_recording(tmp_path):
    cmd = [sys.executable, "-m", "mntes_stream", "up", "--duration", "0", "--modules", "1", "--channels", "8",
           "--out", str(tmp_path / "up")]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    lines = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            assert line, f"up ended early: {lines} {proc.stderr.read()}"
            lines.append(line)
            m = re.search(r"power chunks\s+(\d+).*MCAP 1 file\(s\) ([\d.]+) MB", line)
            if m and int(m.group(1)) >= 20:
                break
        else:
            raise AssertionError(f"no power after 120 s: {lines}")
        proc.send_signal(signal.SIGINT)  # what Ctrl-C sends to the foreground process
        out, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, err
    assert "Traceback" not in err
    done = [line for line in out.splitlines() if line.startswith("done:")]
    assert done and "lost 0" in done[0], out
    session = Session(tmp_path / "up" / "recordings")
    assert session.complete  # the recorder finished its file (summary and footer written)
    counts = session.message_counts()
    n_power = sum(n for t, n in counts.items() if "/power/" in t)
    n_counts = sum(n for t, n in counts.items() if "/counts/" in t)
    assert n_power >= 20 and n_power == n_counts  # everything sent was converted and recorded
    assert any("/provenance" in t for t in counts) and any("/hk/" in t for t in counts)
    first = next(iter(session.iter_messages(["mntes/lab/power/**"])))
    assert isinstance(decode(first.payload), PowerChunk)
