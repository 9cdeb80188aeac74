"""The recorder's cheap path: the header read, the writer thread and its queue, the ledger per file, the CPU figure.

Real messages, real MCAP files read back by the project's reader and the reference one; no zenoh (the live
recorder is tests/test_recorder.py).
"""

from __future__ import annotations

import json
import os
import random
import subprocess
import sys
import warnings

import msgpack
import numpy as np
import pytest
from mcap.reader import make_reader
from mcap_helpers import counts_payload, hk_payload

from mntes_stream.errors import TransportError
from mntes_stream.io import mcap as mio
from mntes_stream.io.mcap.background import BackgroundMcapWriter
from mntes_stream.io.mcap.envelope import peek_envelope
from mntes_stream.io.mcap.ledger import LEDGER_METADATA
from mntes_stream.io.message_base import detector_ids_for
from mntes_stream.io.messages import PowerChunk, StatusMessage
from mntes_stream.service.recorder import RecorderConfig
from mntes_stream.service.recorder_sink import RecorderSink

T0 = 1_700_000_000_000_000_000


def _power(seq: int, late: bool, n_ch: int = 3, n_samp: int = 5) -> bytes:
    return PowerChunk(setup="t", board=0, module=0, channels=np.arange(n_ch, dtype=np.int32),
                      detector_ids=detector_ids_for(0, 0, np.arange(n_ch)), seq=seq, t0_ns=T0, sample_rate_hz=80.0,
                      p_opt_w=np.full((n_ch, n_samp), 1e-12), flags=np.zeros((n_ch, n_samp), np.uint16),
                      table_identity="x", converter_kind="table", source_t_pub_ns=T0, t_pub_ns=T0 + 7,
                      late=late).to_bytes()


def _reference(payload: bytes):
    """What the header read must find, from a full decode (the recorder's old way)."""
    msg = msgpack.unpackb(payload, raw=False, strict_map_key=False)
    t_pub = next(msg[k] for k in ("t_pub_ns", "t_ns") if isinstance(msg.get(k), int))
    return msg["schema"], msg["version"], t_pub, msg.get("seq"), msg.get("late") is True


def test_header_read_finds_what_a_full_decode_finds_and_the_samples():
    status = StatusMessage(setup="t", service="conv", t_ns=T0 + 3, uptime_s=1.0, interval_s=1.0).to_bytes()
    cases = [(counts_payload(4, n_ch=4, n_samp=8), 32), (_power(9, True), 15), (_power(10, False), 15), (status, 0)]
    for payload, samples in cases:
        env = peek_envelope(payload)
        assert not env.problem
        assert (env.schema, env.version, env.publish_time_ns, env.seq, env.late) == _reference(payload)
        assert env.samples == samples
    # hk: t_ns is an array there, skipped (the publish time falls back to the receive time), no samples
    env = peek_envelope(hk_payload(3))
    assert (env.schema, env.seq, env.publish_time_ns, env.samples, env.problem) == ("mntes.hk", 3, None, 0, "")


def test_header_read_rejects_what_cannot_be_parsed_and_never_raises():
    good = counts_payload(1)
    for bad in (b"", b"\x93garbage", b"\xc1not msgpack", msgpack.packb([1, 2]), good[:-1], good + b"\x00",
                good[: len(good) // 2], msgpack.packb({"schema": 3, "version": 1}), msgpack.packb({b"k": 1})):
        env = peek_envelope(bad)
        assert env.problem and env.schema == "" and env.seq is None, bad[:20]
    # Random damage to real messages: a verdict every time (the converter validates the arrays of what it takes).
    rng = random.Random(7)
    base = [good, _power(2, True), hk_payload(2)]
    for _ in range(3000):
        b = bytearray(rng.choice(base))
        i = rng.randrange(len(b))
        if rng.random() < 0.5:
            b[i] = rng.randrange(256)
        else:
            del b[i:]
        env = peek_envelope(bytes(b))
        assert isinstance(env.problem, str) and env.samples >= 0


def _messages(n: int):
    return [(f"mntes/t/counts/0/{i % 3}", counts_payload(i, module=i % 3, n_ch=16, n_samp=40), T0 + i) for i in range(n)]


def test_writer_thread_writes_everything_in_order_and_each_file_carries_its_own_ledger(tmp_path):
    msgs = _messages(300)
    w = BackgroundMcapWriter(tmp_path, "r", rotate_bytes=40_000, rotate_s=0, chunk_size_bytes=8192,
                             compression="lz4")
    handed = [0]
    w.closing_metadata = lambda file_seq: {"test.book": {"file_seq": str(file_seq), "handed": str(handed[0])}}
    for topic, payload, t in msgs:
        w.write(topic, payload, t, peek_envelope(payload))
        handed[0] += 1
        w.rotate_if_full()
    w.close()
    files = w.files
    assert len(files) > 3 and w.messages == 300 and w.unwritten == 0
    got = list(mio.iter_messages(tmp_path))
    assert [(m.topic, m.payload) for m in got] == [(t, p) for t, p, _ in msgs]
    # Each file's closing record counts exactly the messages handed over before its end: those in it and before.
    total = 0
    for seq, path in enumerate(files, 1):
        with open(path, "rb") as f:
            reader = make_reader(f)
            total += reader.get_summary().statistics.message_count
            (meta,) = [m for m in reader.iter_metadata() if m.name == "test.book"]
        assert meta.metadata == {"file_seq": str(seq), "handed": str(total)}


def test_a_full_queue_is_counted_and_loses_nothing(tmp_path):
    msgs = _messages(200)
    # A queue of one message: nearly every hand-over waits for the writer thread.
    w = BackgroundMcapWriter(tmp_path, "q", queue_messages=1, queue_bytes=1, rotate_s=0, compression="zstd")
    for topic, payload, t in msgs:
        w.write(topic, payload, t, peek_envelope(payload))
    w.close()
    assert w.queue_full > 0 and w.wait_s > 0 and w.queue_high_water <= 2  # one message (and the close command)
    assert [m.payload for m in mio.iter_messages(tmp_path)] == [p for _, p, _ in msgs]


@pytest.fixture
def small_disk(tmp_path):
    """A 1 MB tmpfs (skipped where mounting is not permitted), unmounted afterwards."""
    d = tmp_path / "disk"
    d.mkdir()
    res = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=1m", "tmpfs", str(d)], capture_output=True, text=True)
    if res.returncode != 0:
        pytest.skip(f"cannot mount a small tmpfs here: {res.stderr.strip() or res.returncode}")
    try:
        yield d
    finally:
        subprocess.run(["umount", "-l", str(d)], capture_output=True)


def test_a_failed_write_on_the_writer_thread_is_raised_once_and_the_rest_counted(small_disk):
    w = BackgroundMcapWriter(small_disk, "f", rotate_s=0, rotate_bytes=0, compression="none", flush_interval_s=0.01)
    raised = []
    for i, (topic, payload, t) in enumerate(_messages(2000)):  # about 5 kB each: 10 MB onto 1 MB
        try:
            w.write(topic, payload, t, peek_envelope(payload))
        except TransportError as exc:
            raised.append((i, str(exc)))
    try:  # the writer thread may fail after every message was handed over: then close() says it
        w.close()
    except TransportError as exc:
        raised.append((-1, str(exc)))
    said = (raised, w.messages, w.unwritten, w.error)
    assert len(raised) == 1 and "No space left on device" in raised[0][1] and "\n" not in raised[0][1], said
    # Every message handed over is either in the file (up to its last flush) or counted as unwritten.
    assert w.messages + w.unwritten == 2000 and w.unwritten > 0, said
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        assert len(list(mio.iter_messages(small_disk / "f-000001.mcap"))) >= w.messages, said


def test_the_sink_books_counts_power_and_garbage_and_states_its_cpu(tmp_path):
    cfg = RecorderConfig(setup="t", directory=str(tmp_path), prefix="s", compression="lz4", rotate_s=0.0)
    sink = RecorderSink(cfg)
    for i in range(20):
        sink.add("mntes/t/counts/0/0", counts_payload(i, n_ch=4, n_samp=8), T0 + i)
        sink.add("mntes/t/power/0/0", _power(i, late=i >= 18), T0 + i)
    sink.add("mntes/t/counts/0/0", b"\x93garbage", T0 + 99)  # cannot be parsed: rejected, still recorded
    sink.writer.close()
    assert sink.book.ledger_now().line() == "received 21 chunks: recorded 20, rejected 1 (malformed 1); lost 1 of 21"
    assert sink.book.power == {"0/0": [18, 2]}
    cpu = sink.cpu()
    assert cpu["samples"] == 20 * 32 and cpu["cpu_s_per_msamples"] > 0 and cpu["receive_cpu_s_per_msamples"] > 0
    assert sink.writer.messages == 41 and sink.writer.invalid == 1
    (meta,) = [m.data for m in mio.read_metadata(tmp_path) if m.name == LEDGER_METADATA]
    assert meta["recorder_line"] == sink.book.ledger_now().line() and meta["file_seq"] == "1"


def test_bench_recording_reports_cpu_per_million_samples_and_a_balanced_ledger(tmp_path):
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "bench", "recording", "--modules", "2",
                          "--duration", "0.5", "--json"], capture_output=True, text=True, timeout=120,
                         env={**os.environ, "PYTHONWARNINGS": "error::DeprecationWarning"})
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["samples"] == 2 * 128 * 20 * 5 and out["messages"] == 20
    assert out["ledger_line"] == "received 10 chunks: recorded 10; lost 0 of 10"
    assert out["cpu_s_per_msamples"] > 0 and out["compression"] == RecorderConfig.compression
    assert out["chunk_kb"] == RecorderConfig.chunk_size_kb
