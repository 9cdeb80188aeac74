"""A converter that starts past the sources' history leaves counts without power: every summary says so (issue 33).

Measured before: a converter killed and restarted 14 s later missed the 196 counts chunks that fell out of the
sources' 10 s history, and every summary said nothing: the converter ``received 506 chunks: converted 506; lost 0
of 506``, the recorder ``received 904 chunks: recorded 904; lost 0 of 904``. Here the hole is made deterministic
(not by timing): the source keeps 1 s of history and the converter starts once the source is 3 s in, so at
least its first ~2 s of counts can never reach it. A real run on loopback (a router, every service a client, a
recorder writing MCAP): the recorder's closing line, ``ps`` while the hole is open, ``inspect`` and the
converter's status name the exact missing numbers, checked against the recorded file's counts and power topics,
and offline ``convert`` of the recording gives their power.
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_services_walkthrough import Proc

from mntes_stream.io import keys
from mntes_stream.io.mcap import Session
from mntes_stream.io.mcap.envelope import peek_envelope
from mntes_stream.io.messages import StatusMessage
from mntes_stream.io.transport import QueueSubscriber, ZenohSettings, free_tcp_port, open_session

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _mntes(*args, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mntes_stream", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=120)


def _seqs(path: Path, kind: str) -> dict[str, set[int]]:
    """Per stream ``"<board>/<module>"``, the sequence numbers of the ``kind`` (counts, power) messages recorded."""
    out: dict[str, set[int]] = {}
    for m in Session(path).iter_messages():
        parts = m.topic.split("/")
        if parts[2] == kind:
            out.setdefault(f"{parts[3]}/{parts[4]}", set()).add(peek_envelope(m.payload).seq)
    return out


def _as_text(seqs: set[int]) -> str:
    """Inclusive runs, as the summaries print them ("0-23, 40"), computed here from the numbers alone."""
    runs: list[list[int]] = []
    for n in sorted(seqs):
        if runs and n == runs[-1][1] + 1:
            runs[-1][1] = n
        else:
            runs.append([n, n])
    return ", ".join(f"{a}-{b}" if b > a else f"{a}" for a, b in runs)


def _wait_seq(sub, kind: str, at_least: int, timeout_s: float) -> int:
    """Wait until a ``kind`` message of stream 0/0 with ``seq >= at_least`` arrives; its seq."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        item = sub.get(timeout_s=0.2)
        if item is not None and item[0].endswith(f"/{kind}/0/0"):
            seq = peek_envelope(item[1]).seq
            if seq >= at_least:
                return seq
    raise AssertionError(f"no {kind} chunk with seq >= {at_least} within {timeout_s} s")


def test_counts_without_power_are_named_by_every_summary_and_convert_fills_them(tmp_path):
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("recordings", "*-params.toml"))
    port = free_tcp_port()
    client = tmp_path / "services" / "zenoh-client.json5"
    client.write_text(client.read_text().replace("7447", str(port)))
    c = "-c services/zenoh-client.json5"
    procs: list[Proc] = []
    try:
        procs.append(router := Proc(f"mntes-stream router -l tcp/127.0.0.1:{port}", tmp_path))
        procs.append(rec := Proc(f"mntes-stream serve --config services/recorder.toml {c} "
                                 "--set recorder.directory=rec", tmp_path))
        rec.wait_for(r"recording mntes/lab/\*\* into", 90)
        with open_session(ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))) as z:
            counts = QueueSubscriber(z, [keys.counts_key("lab", 0, 0)])
            # The source keeps 1 s of history (10 chunks a stream): what it published before that is out of reach.
            procs.append(src := Proc(f"mntes-stream serve --config services/source.toml {c} --set zenoh.history_s=1",
                                     tmp_path))
            _wait_seq(counts, "counts", 30, 90)  # 3 s in: at least 20 chunks a stream fell out of its history
            counts.close()
            power = QueueSubscriber(z, ["mntes/lab/power/**"])
            procs.append(conv := Proc(f"mntes-stream serve --config services/converter.toml {c}", tmp_path))
            conv.wait_for(r"converter converter: \d+ detectors", 120)
            first = _wait_seq(power, "power", 0, 60)
            _wait_seq(power, "power", first + 15, 60)  # power flows live past the history
            power.close()
            # ps, while the hole is open: the recorder's heartbeat names it.
            ps = _mntes("ps", "--setup", "lab", "--json", "--interval", "0", "--timeout", "3", *c.split(), cwd=tmp_path)
            assert ps.returncode == 0, ps.stderr
            (rec_beat,) = [b for b in json.loads(ps.stdout)["services"] if b["service"] == "recorder"]
            ps_text = _mntes("ps", "--setup", "lab", "--interval", "0", "--timeout", "3", *c.split(), cwd=tmp_path)
        assert src.interrupt() in (0, 130)
        time.sleep(1.5)  # the converter converts what is on its way
        assert conv.interrupt() in (0, 130)
        time.sleep(0.5)  # its last power and status reach the recorder
        assert rec.interrupt() in (0, 130)
        router.interrupt()
    finally:
        for p in procs:
            p.interrupt(10)
    time.sleep(0.3)  # the reader threads take the last lines
    for p in (rec, conv, src):
        while not p.lines.empty():
            p.seen.append(p.lines.get())
        assert not any("Traceback" in line for line in p.seen), "".join(p.seen)

    # The truth, from the recorded file: the counts chunks whose power was never recorded.
    counts_seqs, power_seqs = _seqs(tmp_path / "rec", "counts"), _seqs(tmp_path / "rec", "power")
    holes = {s: counts_seqs[s] - power_seqs.get(s, set()) for s in counts_seqs}
    assert sorted(holes) == ["0/0", "0/1"]
    for s, hole in holes.items():  # the start before the history, nothing after
        assert len(hole) >= 20 and hole == set(range(len(hole))), (s, _as_text(hole))
    total = sum(len(h) for h in holes.values())

    # The recorder's closing line (serve's last line) names them, stream by stream, and says convert fills them.
    last = [line for line in rec.seen if line.startswith("recorder: ")][-1]
    for s, hole in holes.items():
        assert f"{s} seq {_as_text(hole)}" in last, (s, last)
    assert f"; WARNING {total} counts chunk(s) recorded without power (" in last, last
    assert last.rstrip().endswith("offline `mntes-stream convert` of this recording gives their power"), last
    # ... and ps named them while the hole was open.
    assert rec_beat["unpowered"] == {s: len(h) for s, h in holes.items()}, rec_beat
    assert rec_beat["unpowered_seqs"] == {s: f"seq {_as_text(h)}" for s, h in holes.items()}, rec_beat
    assert f"unpowered=0/0:{len(holes['0/0'])}(seq {_as_text(holes['0/0'])})" in ps_text.stdout, ps_text.stdout

    # The converter says from which number it began, in its log and its status (as recorded).
    for s, hole in holes.items():
        assert re.search(rf"mntes/lab/counts/{s}: the first chunk this converter takes is seq {len(hole)} \(no "
                         "checkpoint\\)", "".join(conv.seen)), "".join(conv.seen)
    statuses = [StatusMessage.from_bytes(m.payload) for m in Session(tmp_path / "rec").iter_messages()
                if m.topic == "mntes/lab/status/converter"]
    assert statuses[-1].began_at == {s: len(h) for s, h in holes.items()}, statuses[-1].began_at

    # inspect says the same, from the file's ledger metadata.
    res = _mntes("inspect", "rec", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (f"counts without power: {total} chunk(s) never converted in this recording; offline `mntes-stream "
            "convert` of it gives their power:") in res.stdout, res.stdout
    for s, hole in holes.items():
        assert re.search(rf"^    {s}: {len(hole)} chunk\(s\), seq {_as_text(hole)}$", res.stdout, re.M), res.stdout
    js = json.loads(_mntes("inspect", "rec", "--json", cwd=tmp_path).stdout)
    assert js["ledger"]["unpowered"] == {s: {"count": len(h), "ranges": [[0, len(h)]]} for s, h in holes.items()}

    # Offline convert of the recording gives their power, and its result lacks nothing.
    res = _mntes("convert", "rec", "out.mcap", "-q", cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    converted = _seqs(tmp_path / "out.mcap", "power")
    for s, hole in holes.items():
        assert hole <= converted[s] and counts_seqs[s] <= converted[s], s
    res = _mntes("inspect", "out.mcap", cwd=tmp_path)
    assert "counts without power: none (every recorded counts chunk has its power)" in res.stdout, res.stdout
