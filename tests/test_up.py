"""``mntes-stream up``: simulator, converter and recorder as processes; power flows, the MCAP grows, Ctrl-C stops all cleanly."""

from __future__ import annotations

import queue
import re
import signal
import subprocess
import sys
import threading
import time

from mntes_stream.io.mcap import Session
from mntes_stream.io.messages import PowerChunk, decode


def _pump(stream, lines: queue.Queue) -> None:
    for line in stream:
        lines.put(line)
    lines.put(None)  # end of output


def test_up_runs_until_ctrl_c_and_leaves_a_finished_recording(tmp_path):
    cmd = [sys.executable, "-m", "mntes_stream", "up", "--duration", "0", "--modules", "1", "--channels", "8",
           "--out", str(tmp_path / "up")]
    # stderr to a file (a pipe nobody drains blocks the child at 64 KiB); stdout read by a
    # thread so every wait below has a deadline, even if the child falls silent.
    err_path = tmp_path / "up.stderr"
    with open(err_path, "w") as err_file:
        proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err_file, text=True)
    lines: queue.Queue = queue.Queue()
    reader = threading.Thread(target=_pump, args=(proc.stdout, lines), daemon=True)
    reader.start()
    seen: list[str] = []
    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                line = lines.get(timeout=max(deadline - time.monotonic(), 0.01))
            except queue.Empty:
                raise AssertionError(f"no power after 120 s: {seen} {err_path.read_text()}") from None
            assert line is not None, f"up ended early: {seen} {err_path.read_text()}"
            seen.append(line)
            m = re.search(r"power chunks\s+(\d+).*MCAP 1 file\(s\) ([\d.]+) MB", line)
            if m and int(m.group(1)) >= 20:
                break
        proc.send_signal(signal.SIGINT)  # what Ctrl-C sends to the foreground process
        proc.wait(timeout=60)
        reader.join(10)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    rest = []
    while not lines.empty():
        rest.append(lines.get())
    out = "".join(seen + [x for x in rest if x is not None])
    err = err_path.read_text()
    assert proc.returncode == 130, err  # Ctrl-C: stopped cleanly, summary printed, the shell sees the interrupt
    assert "Traceback" not in err
    done = [line for line in out.splitlines() if line.startswith("done")]
    # The last line is the converter's ledger: every chunk received was converted, and it says so.
    assert done and out.strip().splitlines()[-1].strip().startswith("converter: received"), out
    assert " lost 0 of " in out.strip().splitlines()[-1], out
    session = Session(tmp_path / "up" / "recordings")
    assert session.complete  # the recorder finished its file (summary and footer written)
    counts = session.message_counts()
    n_power = sum(n for t, n in counts.items() if "/power/" in t)
    n_counts = sum(n for t, n in counts.items() if "/counts/" in t)
    assert n_power >= 20 and n_power == n_counts  # everything sent was converted and recorded
    assert any("/provenance" in t for t in counts) and any("/hk/" in t for t in counts)
    first = next(iter(session.iter_messages(["mntes/lab/power/**"])))
    assert isinstance(decode(first.payload), PowerChunk)


def test_the_first_up_with_empty_caches_says_what_it_builds_and_compiles(tmp_path):
    """A first start (no cached tables, no compiled kernels) is not a silence: up names each slow step and its
    time, then says when power flows; the recorder does not call the converter's own start-up missing power."""
    import os

    env = {**os.environ, "MNTES_STREAM_CACHE": str(tmp_path / "cache")}
    env.pop("NUMBA_CACHE_DIR", None)
    cmd = [sys.executable, "-m", "mntes_stream", "up", "--duration", "3", "--modules", "1", "--channels", "8",
           "--out", str(tmp_path / "up")]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=400)
    assert done.returncode == 0, done.stderr[-2000:]
    lines = done.stdout.splitlines()
    compiling = next(i for i, line in enumerate(lines) if "converter: compiling the conversion kernels" in line)
    assert lines[compiling].endswith("...")
    took = re.search(r"compiling the conversion kernels .*: done in ([\d.]+) s", done.stdout)
    assert took and float(took.group(1)) >= 1.0
    ready = next(i for i, line in enumerate(lines) if re.search(r"ready after [\d.]+ s; the source publishes", line))
    first = next(i for i, line in enumerate(lines) if re.search(r"^  first power [\d.]+ s after the start$", line))
    assert compiling < ready < first and ready < next(i for i, line in enumerate(lines) if "power chunks" in line)
    assert "counts without power" not in done.stderr, done.stderr[-2000:]
    assert any((tmp_path / "cache" / "numba").rglob("*.nbi")), "the kernels are cached in the user's cache"
    assert "Traceback" not in done.stderr
