"""A converter that starts past the sources' history leaves counts without power: every summary says so (issue 33).

Measured before: a converter killed and restarted 14 s later missed the 196 counts chunks that fell out of the
sources' 10 s history, and every summary said nothing: the converter ``received 506 chunks: converted 506; lost 0
of 506``, the recorder ``received 904 chunks: recorded 904; lost 0 of 904``. Here the hole is made deterministic
(not by timing): the source keeps 1 s of history and the converter starts once the source is 3 s in (or is
killed, and started again once 3 s of counts went by), so at least ~2 s of counts can never reach it. A real run on loopback (a router, every service a client, a
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


class _Layout:
    """A router, a recorder writing MCAP into ``rec/`` and a test-side client session, all on loopback; the source
    (1 s of history: 10 chunks a stream) and converters started by the test, every one a client of the router."""

    def __init__(self, tmp_path: Path):
        self.tmp_path = tmp_path
        shutil.copytree(ROOT / "services", tmp_path / "services",
                        ignore=shutil.ignore_patterns("recordings", "*-params.toml"))
        self.port = port = free_tcp_port()
        client = tmp_path / "services" / "zenoh-client.json5"
        client.write_text(client.read_text().replace("7447", str(port)))
        self.c = "-c services/zenoh-client.json5"
        self.procs: list[Proc] = []
        self.convs: list[Proc] = []
        self.router = self.start(f"mntes-stream router -l tcp/127.0.0.1:{port}")
        self.rec = self.start(f"mntes-stream serve --config services/recorder.toml {self.c} --set recorder.directory=rec")
        self.rec.wait_for(r"recording mntes/lab/\*\* into", 90)
        self.z = open_session(ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
        self.sub = QueueSubscriber(self.z, [keys.counts_key("lab", 0, 0), keys.power_key("lab", 0, 0)])

    def start(self, command: str) -> Proc:
        self.procs.append(p := Proc(command, self.tmp_path))
        return p

    def source(self) -> Proc:
        self.src = self.start(f"mntes-stream serve --config services/source.toml {self.c} --set zenoh.history_s=1")
        return self.src

    def converter(self) -> Proc:
        conv = self.start(f"mntes-stream serve --config services/converter.toml {self.c}")
        conv.wait_for(r"converter converter: \d+ detectors", 120)
        self.convs.append(conv)
        return conv

    def ps(self, *extra: str) -> subprocess.CompletedProcess:
        res = _mntes("ps", "--setup", "lab", "--interval", "0", "--timeout", "3", *extra, *self.c.split(),
                     cwd=self.tmp_path)
        assert res.returncode == 0, res.stderr
        return res

    def stop(self) -> None:
        """Source, converter, recorder, router in that order (each converts or records what is on its way)."""
        self.sub.close()
        self.z.close()
        assert self.src.interrupt() in (0, 130)
        time.sleep(1.5)
        assert self.convs[-1].interrupt() in (0, 130)
        time.sleep(0.5)
        assert self.rec.interrupt() in (0, 130)
        self.router.interrupt()

    def close(self) -> None:
        for p in self.procs:
            p.interrupt(10)
        time.sleep(0.3)  # the reader threads take the last lines
        for p in self.procs:
            while not p.lines.empty():
                p.seen.append(p.lines.get())

    def holes(self) -> dict[str, set[int]]:
        """The truth, from the recorded file: per stream, the counts chunks whose power was never recorded."""
        for p in (self.rec, self.src, *self.convs):
            assert not any("Traceback" in line for line in p.seen), "".join(p.seen)
        self.counts = _seqs(self.tmp_path / "rec", "counts")
        power = _seqs(self.tmp_path / "rec", "power")
        return {s: self.counts[s] - power.get(s, set()) for s in self.counts}


def test_counts_without_power_are_named_by_every_summary_and_convert_fills_them(tmp_path):
    run = _Layout(tmp_path)
    try:
        run.source()
        _wait_seq(run.sub, "counts", 30, 90)  # 3 s in: at least 20 chunks a stream fell out of its history
        conv = run.converter()
        first = _wait_seq(run.sub, "power", 0, 60)
        _wait_seq(run.sub, "power", first + 15, 60)  # power flows live past the history
        # ps, while the hole is open: the recorder's heartbeat names it.
        (rec_beat,) = [b for b in json.loads(run.ps("--json").stdout)["services"] if b["service"] == "recorder"]
        ps_text = run.ps()
        run.stop()
    finally:
        run.close()
    holes = run.holes()
    assert sorted(holes) == ["0/0", "0/1"]
    for s, hole in holes.items():  # the start before the history, nothing after
        assert len(hole) >= 20 and hole == set(range(len(hole))), (s, _as_text(hole))
    _check_summaries(run, holes)
    # ps named them while the hole was open.
    assert rec_beat["unpowered"] == {s: len(h) for s, h in holes.items()}, rec_beat
    assert rec_beat["unpowered_seqs"] == {s: f"seq {_as_text(h)}" for s, h in holes.items()}, rec_beat
    assert f"unpowered=0/0:{len(holes['0/0'])}(seq {_as_text(holes['0/0'])})" in ps_text.stdout, ps_text.stdout
    # The converter says where it began in its log too (the first chunk it took; history normally comes first,
    # and its status, checked above, says the lowest it took).
    for s, hole in holes.items():
        m = re.search(rf"mntes/lab/counts/{s}: the first chunk this converter takes is seq (\d+) \(no checkpoint\)",
                      "".join(conv.seen))
        assert m and int(m.group(1)) >= len(hole), "".join(conv.seen)


def test_a_converter_restarted_past_the_history_leaves_a_hole_every_summary_names(tmp_path):
    """The case measured in issue 33: a converter killed, and started again once its streams' next chunks have
    left the sources' history (here 3 s later for 1 s of history), without a checkpoint."""
    run = _Layout(tmp_path)
    try:
        run.converter()
        run.source()
        killed = _wait_seq(run.sub, "power", 10, 90)
        run.convs[0].p.kill()
        _wait_seq(run.sub, "counts", killed + 30, 60)  # 3 s on: 20 chunks or more out of the history
        run.converter()
        first = _wait_seq(run.sub, "power", killed + 30, 60)
        _wait_seq(run.sub, "power", first + 15, 60)
        run.stop()
    finally:
        run.close()
    holes = run.holes()
    assert sorted(holes) == ["0/0", "0/1"]
    for s, hole in holes.items():  # one run of numbers, after the start and before the end
        lo, hi = min(hole), max(hole) + 1
        assert hi - lo >= 20 and hole == set(range(lo, hi)) and lo > 0 and hi <= max(run.counts[s]), (s, hole)
    _check_summaries(run, holes, thorough=False)  # the late start's test reads the rest


def _check_summaries(run: _Layout, holes: dict[str, set[int]], thorough: bool = True) -> None:
    """The recorder's closing line, the last converter's status (as recorded), inspect and convert, against
    ``holes`` (from the recorded file); ``thorough``: inspect --json and inspect of convert's output too (each
    command is seconds on a loaded machine)."""
    tmp_path, rec = run.tmp_path, run.rec
    total = sum(len(h) for h in holes.values())
    # The recorder's closing line (serve's last line) names them, stream by stream, and says convert fills them.
    last = [line for line in rec.seen if line.startswith("recorder: ")][-1]
    for s, hole in holes.items():
        assert f"{s} seq {_as_text(hole)}" in last, (s, last)
    assert f"; WARNING {total} counts chunk(s) recorded without power (" in last, last
    assert last.rstrip().endswith("offline `mntes-stream convert` of this recording gives their power"), last
    # The (last) converter says from which number it began in its status, as recorded.
    statuses = [StatusMessage.from_bytes(m.payload) for m in Session(tmp_path / "rec").iter_messages()
                if m.topic == "mntes/lab/status/converter"]
    assert statuses[-1].began_at == {s: max(h) + 1 for s, h in holes.items()}, statuses[-1].began_at

    # inspect says the same, from the file's ledger metadata.
    res = _mntes("inspect", "rec", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert (f"counts without power: {total} chunk(s) never converted in this recording; offline `mntes-stream "
            "convert` of it gives their power:") in res.stdout, res.stdout
    for s, hole in holes.items():
        assert re.search(rf"^    {s}: {len(hole)} chunk\(s\), seq {_as_text(hole)}$", res.stdout, re.M), res.stdout
    if thorough:
        js = json.loads(_mntes("inspect", "rec", "--json", cwd=tmp_path).stdout)
        assert js["ledger"]["unpowered"] == {s: {"count": len(h), "ranges": [[min(h), max(h) + 1]]}
                                             for s, h in holes.items()}

    # Offline convert of the recording gives their power, and its result lacks nothing.
    res = _mntes("convert", "rec", "out.mcap", "-q", cwd=tmp_path)
    assert res.returncode == 0, res.stdout + res.stderr
    converted = _seqs(tmp_path / "out.mcap", "power")
    for s, hole in holes.items():
        assert hole <= converted[s] and run.counts[s] <= converted[s], s
    if thorough:
        res = _mntes("inspect", "out.mcap", cwd=tmp_path)
        assert "counts without power: none (every recorded counts chunk has its power)" in res.stdout, res.stdout
