"""The recorder's ledger: real source, converter and recorders as processes on loopback zenoh.

The README's recorder example (``record -e tcp/127.0.0.1:<converter>``: a peer
connected to the converter alone) must record counts and housekeeping too; its
file carries ``mntes.ledger`` at close, ``inspect`` prints it, and it balances:
every counts chunk the source published is recorded, none never received. A
recorder that reaches only the converter (gossip off, not listening) warns that
it records power without counts. Coverage's bookkeeping of late power and of a
converter's shedding runs on the real ledger objects.
"""

from __future__ import annotations

import json
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from mntes_stream.core.ledger import Ledger
from mntes_stream.io import mcap as mio
from mntes_stream.io.mcap.ledger import LEDGER_METADATA, recompute_ledger, recording_ledger
from mntes_stream.io.transport import free_tcp_port
from mntes_stream.service.coverage import Coverage

ROOT = Path(__file__).resolve().parents[1]


class Proc:
    """``mntes-stream ARGS`` in the background, output to files (every wait has a deadline)."""

    def __init__(self, name: str, args: list[str], cwd: Path):
        self.out, self.err = cwd / f"{name}.out", cwd / f"{name}.err"
        with open(self.out, "w") as o, open(self.err, "w") as e:
            self.p = subprocess.Popen([sys.executable, "-m", "mntes_stream", *args], cwd=cwd, stdout=o, stderr=e,
                                      text=True)

    def text(self) -> str:
        return self.out.read_text() + self.err.read_text()

    def wait_for(self, pattern: str, timeout_s: float = 60.0) -> None:
        deadline = time.monotonic() + timeout_s
        while not re.search(pattern, self.text()):
            assert self.p.poll() is None, self.text()
            assert time.monotonic() < deadline, f"no {pattern!r}: {self.text()[-3000:]}"
            time.sleep(0.1)

    def stop(self, timeout_s: float = 30.0) -> int:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
        try:
            return self.p.wait(timeout=timeout_s)
        finally:
            self.kill()

    def kill(self) -> None:
        if self.p.poll() is None:
            self.p.kill()
            self.p.wait()


def _mntes(*args, cwd) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "mntes_stream", *args], cwd=cwd, capture_output=True, text=True,
                          timeout=120)


@pytest.mark.slow
def test_readme_recorder_example_records_counts_and_states_a_balanced_ledger(tmp_path):
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("recordings", "*-params.toml"))
    port = free_tcp_port()
    for name in ("zenoh-converter.json5", "zenoh-local.json5"):
        f = tmp_path / "services" / name
        f.write_text(f.read_text().replace("7447", str(port)))
    ep = f"tcp/127.0.0.1:{port}"
    procs: list[Proc] = []
    try:
        conv = Proc("converter", ["serve", "--config", "services/converter.toml"], tmp_path)
        procs.append(conv)
        conv.wait_for(r"converter converter: \d+ detectors")
        # The README's example, as written but for the port; and a recorder that reaches the converter alone.
        rec = Proc("rec", ["record", "--setup", "lab", "--dir", "rec", "-e", ep], tmp_path)
        alone = Proc("alone", ["record", "--setup", "lab", "--dir", "alone", "-e", ep,
                               "--cfg", "scouting/gossip/enabled:false", "--cfg", "listen/endpoints:[]"], tmp_path)
        procs += [rec, alone]
        for p in (rec, alone):
            p.wait_for(r"recording mntes/lab/\*\* into")
        src = Proc("source", ["serve", "--config", "services/source.toml", "--set", "source.duration_s=3", "--json"],
                   tmp_path)
        procs.append(src)
        assert src.p.wait(timeout=60) == 0, src.text()
        sent = json.loads(src.out.read_text())
        time.sleep(1.5)  # the converter takes in and converts what is on its way
        assert conv.stop() in (0, 130), conv.text()
        time.sleep(0.5)  # its final status reaches the recorders
        assert rec.stop() in (0, 130) and alone.stop() in (0, 130), rec.text() + alone.text()
    finally:
        for p in procs:
            p.kill()
    assert "gossip scouting on" in rec.text() and "Traceback" not in rec.text() + alone.text()

    # Everything the source published is recorded: its counts and housekeeping, each once.
    session = mio.Session(tmp_path / "rec")
    counts = session.message_counts()
    n_counts = sum(n for t, n in counts.items() if "/counts/" in t)
    n_hk = sum(n for t, n in counts.items() if "/hk/" in t)
    assert n_counts > 40 and n_hk > 0 and n_counts + n_hk == sent["messages"], (counts, sent)
    # Its final line is the ledger, balanced: recorded = received = published, never received 0, lost 0.
    last = rec.out.read_text().strip().splitlines()[-1]
    assert last == f"ledger: counts received {n_counts} chunks: recorded {n_counts}; lost 0 of {n_counts}", last
    assert re.search(r"^converter converter \(its last recorded status\): received \d+ chunks: converted \d+",
                     rec.out.read_text(), re.M)

    # The file's mntes.ledger metadata, read back, equals the ledger recomputed from the messages.
    (meta,) = [m.data for m in session.metadata() if m.name == LEDGER_METADATA]
    assert meta["recorder_line"] == f"received {n_counts} chunks: recorded {n_counts}; lost 0 of {n_counts}"
    led = recording_ledger(session)
    again = recompute_ledger(session, "test")
    assert led.source == "metadata" and again.source == "recomputed"
    assert led.recorder.as_dict() == again.recorder.as_dict() and led.power == again.power
    assert led.converters == again.converters and set(led.converters) == {"converter"}
    assert sorted(led.recorder.streams) == ["0/0", "0/1"] and led.recorder.balanced()
    n_power = sum(n for t, n in counts.items() if "/power/" in t)
    assert sum(live + late for live, late in led.power.values()) == n_power > 0
    conv_led = Ledger.from_dict(led.converters["converter"]["ledger"])
    assert conv_led.totals().received == n_counts  # the converter received what the recorder recorded

    # inspect prints it (from the metadata) and in --json.
    res = _mntes("inspect", "rec", cwd=tmp_path)
    assert res.returncode == 0, res.stderr
    assert "ledger (mntes.ledger metadata):" in res.stdout
    assert f"recorder: counts received {n_counts} chunks: recorded {n_counts}; lost 0 of {n_counts}" in res.stdout
    assert re.search(r"^\s+0/1\s+\d+\s+0\s+0\s+\d+\s+0\s+0\s+0$", res.stdout, re.M), res.stdout
    js = json.loads(_mntes("inspect", "rec", "--json", cwd=tmp_path).stdout)
    assert js["ledger"]["recorder_line"] == meta["recorder_line"]

    # The recorder that reached the converter alone recorded power and no counts, and says so.
    alone_counts = mio.Session(tmp_path / "alone").message_counts()
    assert not any("/counts/" in t for t in alone_counts) and any("/power/" in t for t in alone_counts)
    last = alone.out.read_text().strip().splitlines()[-1]
    assert "WARNING power without its counts for 2 stream(s) (0/0, 0/1)" in last, last
    assert "power for 2 s but never its counts" in alone.text()


def test_killed_recorder_file_is_recomputed_by_inspect(tmp_path):
    """A file without mntes.ledger (its recorder died before the close): inspect recomputes the ledger."""
    from mcap_helpers import counts_payload

    from mntes_stream.io.mcap.writer import McapFileWriter

    path = tmp_path / "k-000001.mcap"
    with McapFileWriter(path) as w:  # a plain writer adds no ledger, as a killed recorder leaves none
        for t, seq in enumerate((0, 1, 2, 5, 5, 6)):  # 3 and 4 never came, 5 twice
            w.write("mntes/t/counts/0/1", counts_payload(seq, module=1), 10**9 + t)
    led = recording_ledger(mio.Session(path))
    assert led.source == "recomputed" and "without mntes.ledger" in led.note
    s = led.recorder.streams["0/1"]
    assert (s.received, s.done, s.duplicate, s.missing, s.lost) == (6, 5, 1, 2, 2)
    res = _mntes("inspect", str(path), cwd=tmp_path)
    assert "recorder: counts received 6 chunks: recorded 5, duplicate 1; never received 2; lost 2 of 8" in res.stdout


def test_coverage_names_the_converters_shedding_and_counts_late_power():
    cov = Coverage(after_s=1.0)
    for k in range(6):
        cov.add("mntes/lab/counts/0/1", k, float(k))
    cov.add("mntes/lab/power/0/1", 0, 0.0)
    assert cov.reason("0/1") == "no converter publishes it"
    conv = Ledger("converted")  # what the converter's status ledger says: 3 shed, 2 set aside
    conv.received("0/1", 6)
    conv.done("0/1", 1)
    conv.shed("0/1", "overload", 3)
    cov.converter_status("conv-a", conv.as_dict(), set_aside=2)
    assert cov.unconverted(5.0) == ["0/1"]
    assert cov.summary(5.0)["unconverted_why"] == {"0/1": "converter conv-a shed 3 chunks of it (overload)"}
    held = Ledger("converted")
    held.received("0/1", 6)
    held.done("0/1", 1)
    cov.converter_status("conv-a", held.as_dict(), set_aside=5)
    assert cov.reason("0/1") == "converter conv-a holds 5 chunks of it set aside (overload)"
    waiting = Ledger("converted")
    waiting.received("0/1", 6)
    cov.converter_status("conv-a", waiting.as_dict(), set_aside=0)
    assert cov.reason("0/1") == "converter conv-a holds 6 chunks of it (waiting for housekeeping, or starting)"
    waiting.done("0/1", 6)
    cov.converter_status("conv-a", waiting.as_dict(), set_aside=0)
    assert cov.reason("0/1").startswith("converter conv-a converted 6 chunks of it by its last status, but no power")
    cov.converter_status("conv-a", held.as_dict(), set_aside=5)
    # Live power jumps 0 -> 5 (1-4 set aside): a gap of 4; then 2 and 3 come late: the gap is 2, late 2.
    cov.add("mntes/lab/power/0/1", 5, 5.0)
    assert cov.gaps == {"0/1": 4}
    cov.add("mntes/lab/power/0/1", 2, 5.1, late=True)
    cov.add("mntes/lab/power/0/1", 3, 5.2, late=True)
    s = cov.summary(5.3)
    assert s["power_gaps"] == {"0/1": 2} and s["power_late"] == {"0/1": 2} and s["unconverted"] == []
    cov.add("mntes/lab/power/0/1", 1, 5.4, late=True)
    cov.add("mntes/lab/power/0/1", 4, 5.5, late=True)
    assert cov.gaps == {} and cov.late == {"0/1": 4} and cov.live == {"0/1": 2}
    # Power of a stream whose counts never came: said once it lasted after_s.
    cov.add("mntes/lab/power/0/2", 0, 5.0)
    assert cov.power_only(5.5) == [] and cov.power_only(6.1) == ["0/2"]


def test_coverage_says_when_power_reaches_the_recorder_late_not_that_it_stopped():
    """Backpressure (a recorder whose intake falls behind; zenoh's BLOCK then slows converter and source): its
    power still comes, later and later, so the reason says so instead of 'stalled, or does not reach'. Stamps
    that are old by a constant (a replay of a recording) are not lateness."""
    conv = Ledger("converted")
    conv.received("0/1", 20)
    conv.done("0/1", 20)
    for offset_s, behind in ((0.0, True), (86_400.0, True), (86_400.0, False)):
        cov = Coverage(after_s=1.0)
        cov.converter_status("conv-a", conv.as_dict())
        for k in range(10):  # counts on time; power 0.2 s later each chunk (its receive lag grows): 1.8 s behind
            cov.add("mntes/lab/counts/0/1", k, float(k))
            lag = offset_s + (0.2 * k if behind else 0.01)
            cov.add("mntes/lab/power/0/1", k, float(k) + 0.01, lag_s=lag)
            cov.add("mntes/lab/power/0/1", k, float(k) + 0.02, late=True, lag_s=offset_s + 50.0)  # late: not counted
        for k in range(10, 13):
            cov.add("mntes/lab/counts/0/1", k, float(k))
        assert cov.unconverted(12.5) == ["0/1"]
        why = cov.reason("0/1")
        assert why.startswith("converter conv-a converted 20 chunks of it by its last status, but no power for 1 s")
        if behind:
            assert cov.behind_s("0/1") == pytest.approx(1.8) and "reaches this recorder late: the last 1.8 s" in why
        else:
            assert cov.behind_s("0/1") == 0.0 and why.endswith("(stalled, or its power does not reach this recorder)")


def test_a_recorded_status_ledger_names_the_shedding_converter():
    """The converter's real status bytes (ledger with shed chunks) -> the recorder's book -> Coverage's reason,
    and the file's mntes.ledger record carries the converter's ledger."""
    from mntes_stream.io.mcap.envelope import peek_envelope
    from mntes_stream.io.mcap.ledger import RecordingBook
    from mntes_stream.io.messages import StatusMessage

    conv = Ledger("converted")
    conv.received("0/3", 40)
    conv.done("0/3", 30)
    conv.shed("0/3", "overload", 10)
    payload = StatusMessage(setup="lab", service="conv-b", t_ns=5, uptime_s=1.0, interval_s=1.0, chunks_received=40,
                            chunks_converted=30, chunks_shed=10, chunks_lost=10, ledger=conv.as_dict()).to_bytes()
    book = RecordingBook("lab")
    book.add("mntes/lab/status/conv-b", payload, peek_envelope(payload), 5)
    assert book.status_topics == {"mntes/lab/status/conv-b": "conv-b"}
    entry = book.converters["conv-b"]
    assert entry["chunks_shed"] == 10 and entry["ledger"] == {"0/3": {"received": 40, "done": 30, "shed": {"overload": 10}}}
    cov = Coverage(after_s=1.0)
    cov.converter_status("conv-b", entry["ledger"], entry["chunks_set_aside"])
    cov.add("mntes/lab/counts/0/3", 0, 0.0)
    cov.add("mntes/lab/counts/0/3", 1, 1.5)
    assert cov.summary(2.0)["unconverted_why"] == {"0/3": "converter conv-b shed 10 chunks of it (overload)"}
    meta = book.metadata("run-1", 1)
    assert meta["converter.conv-b"] == "received 40 chunks: converted 30, shed 10 (overload 10); lost 10 of 40"
    assert json.loads(meta["converters"])["conv-b"]["chunks_shed"] == 10


def _power_payload(seq: int, module: int = 1) -> bytes:
    import numpy as np

    from mntes_stream.core.ids import detector_id
    from mntes_stream.io.messages import PowerChunk

    t0 = 1_700_000_000_000_000_000 + seq * 100_000_000
    ch = np.arange(4, dtype=np.int32)
    return PowerChunk(setup="t", board=0, module=module, channels=ch, detector_ids=[detector_id(0, module, c) for c in ch],
                      seq=seq, t0_ns=t0, sample_rate_hz=80.0, p_opt_w=np.full((4, 8), 1e-12),
                      flags=np.zeros((4, 8), np.uint16), table_identity="tab", converter_kind="exact",
                      source_t_pub_ns=t0, t_pub_ns=t0).to_bytes()


def test_counts_without_power_are_merged_over_recorder_runs_and_recomputed_for_a_killed_file(tmp_path):
    """Two recorder runs (a restart: the second records the sources' history again), then a killed one: the
    counts without power are those no run recorded power for, from the files' mntes.ledger or the messages."""
    from mcap_helpers import counts_payload

    from mntes_stream.io.mcap.writer import McapFileWriter
    from mntes_stream.service.recorder import RecorderConfig
    from mntes_stream.service.recorder_sink import RecorderSink

    def run(counts, power):
        sink = RecorderSink(RecorderConfig(setup="t", directory=str(tmp_path / "rec")))
        for seq in counts:
            sink.add("mntes/t/counts/0/1", counts_payload(seq, module=1), 10**9 + seq)
            if seq in power:
                sink.add("mntes/t/power/0/1", _power_payload(seq), 10**9 + seq)
        sink.writer.close()
        return sink.book.unpowered()

    # The converter was down for 10-19 and stopped at 25: the first run's file lacks 10-19 and 25-29 ...
    first = run(range(30), {*range(10), *range(20, 25)})
    assert first == {"0/1": {"count": 15, "ranges": [[10, 20], [25, 30]]}}
    # ... the second recorder run (history 25-29 again, the converter back) has power for 25-39.
    assert run(range(25, 40), set(range(25, 40))) == {}
    led = recording_ledger(mio.Session(tmp_path / "rec"))
    assert led.source == "metadata" and led.runs == 2
    assert led.unpowered == {"0/1": {"count": 10, "ranges": [[10, 20]]}}
    res = _mntes("inspect", "rec", cwd=tmp_path)
    assert "    0/1: 10 chunk(s), seq 10-19\n" in res.stdout, res.stdout

    # A killed recorder's file (no mntes.ledger): the same book from its messages.
    path = tmp_path / "k-000001.mcap"
    with McapFileWriter(path) as w:
        for seq in range(12):
            w.write("mntes/t/counts/0/1", counts_payload(seq, module=1), 10**9 + seq)
            if seq % 4:
                w.write("mntes/t/power/0/1", _power_payload(seq), 10**9 + seq)
    again = recording_ledger(mio.Session(path))
    assert again.source == "recomputed" and again.unpowered == {"0/1": {"count": 3, "ranges": [[0, 1], [4, 5], [8, 9]]}}
    assert "0/1: 3 chunk(s), seq 0, 4, 8" in "\n".join(again.lines())


def test_coverage_gives_a_streams_first_counts_their_grace_and_names_a_converter_not_yet_announced():
    """The first seconds of any start (issue 34): a stream's counts come before its first power; that is no
    missing power until after_s has passed since its first counts, and before any converter's provenance or
    status the reason says none has announced itself yet, not that none publishes it."""
    cov = Coverage(after_s=2.0)
    cov.add("mntes/lab/counts/0/0", 0, 10.0)
    cov.add("mntes/lab/counts/0/0", 1, 10.1)
    assert cov.unconverted(10.1) == [] and cov.unconverted(11.9) == []  # before: warned at once, with no power yet
    cov.add("mntes/lab/counts/0/0", 2, 12.1)
    assert cov.unconverted(12.1) == ["0/0"]
    assert cov.summary(12.1)["unconverted_why"] == {
        "0/0": "no converter has announced itself yet (one is starting, or none runs)"}
    cov.add("mntes/lab/provenance", None, 12.2)  # a converter's provenance: it runs
    assert cov.reason("0/0") == "no converter publishes it"
    assert cov.summary(12.3)["unconverted_why"] == {"0/0": "no converter publishes it"}
    cov.add("mntes/lab/power/0/0", 0, 12.4)
    assert cov.unconverted(12.5) == []
