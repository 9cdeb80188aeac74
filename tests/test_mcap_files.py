"""MCAP writer/reader: round trips, self-description, rotation, recovery of cut files."""

from __future__ import annotations

import json
import random
import time
import warnings

import msgpack
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.opcode import Opcode
from mcap.reader import make_reader
from mcap_helpers import counts_payload, hk_payload, provenance_payload

from mntes_stream.errors import ConfigError, SchemaError, TransportError
from mntes_stream.io import mcap as mio
from mntes_stream.io.codec import json_schema

T0 = 1_700_000_000_000_000_000

topics = st.sampled_from(["mntes/t/counts/0/0", "mntes/t/counts/0/1", "mntes/t/hk/t_bath", "mntes/t/power/0/0", "odd/key"])
payloads = st.one_of(
    st.binary(max_size=300),
    st.integers(0, 50).map(counts_payload),
    st.integers(0, 50).map(hk_payload),
    st.builds(lambda v: msgpack.packb({"schema": "mntes.counts", "version": v}), st.integers(2, 5)),
)


def _read(source, **kw):
    with warnings.catch_warnings():
        warnings.simplefilter("error", mio.TruncatedFileWarning)
        return list(mio.iter_messages(source, **kw))


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(msgs=st.lists(st.tuples(topics, payloads, st.integers(0, 10**9)), max_size=60),
       compression=st.sampled_from(["zstd", "lz4", "none"]))
def test_round_trip_in_log_time_order(tmp_path_factory, msgs, compression):
    path = tmp_path_factory.mktemp("rt") / "x.mcap"
    with mio.McapFileWriter(path, compression=compression, chunk_size_bytes=2048) as w:
        for k, (topic, payload, dt) in enumerate(msgs):
            w.write(topic, payload, T0 + dt)
            if k % 7 == 6:
                w.flush()
    got = _read(path)
    # Expected: a stable sort of what was written by receive time.
    expected = sorted(((T0 + dt, k, topic, payload) for k, (topic, payload, dt) in enumerate(msgs)), key=lambda e: e[:2])
    assert [(m.log_time_ns, m.topic, m.payload) for m in got] == [(t, topic, p) for t, _, topic, p in expected]
    for m in got:
        env = mio.peek_envelope(m.payload)
        assert (m.schema_name, m.schema_version) == ((env.schema, env.version) if not env.problem else ("", 0))
    # The file is an ordinary MCAP to the reference reader too.
    with open(path, "rb") as f:
        ref = list(make_reader(f).iter_messages(log_time_order=False))
    assert sorted(msg.data for _, _, msg in ref) == sorted(p for _, p, _ in msgs)


def test_file_explains_itself(tmp_path):
    path = tmp_path / "x.mcap"
    bad_version = msgpack.packb({"schema": "mntes.counts", "version": 99})
    with mio.McapFileWriter(path) as w:
        w.write("mntes/t/counts/0/0", counts_payload(1), T0)
        w.write("mntes/t/counts/0/0", b"\xc1not msgpack", T0 + 1)
        w.write("mntes/t/counts/0/0", bad_version, T0 + 2)
        w.write("mntes/t/hk/t_bath", hk_payload(1), T0 + 3)
        assert w.invalid == 1
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        by_topic = {}
        for schema, channel, msg in reader.iter_messages():
            by_topic.setdefault(channel.topic, []).append((schema, channel, msg))
    (s0, c0, m0), (s1, c1, _), (s2, c2, _) = by_topic["mntes/t/counts/0/0"]
    assert c0.message_encoding == "msgpack" and s0.encoding == "jsonschema" and s0.name == "mntes.counts"
    assert json.loads(s0.data) == json_schema("mntes.counts", 1)
    # publish_time is the message's own t_pub_ns; sequence its seq.
    env = msgpack.unpackb(counts_payload(1))
    assert (m0.publish_time, m0.sequence) == (env["t_pub_ns"], 1)
    assert s1 is None and "malformed msgpack" in c1.metadata["mntes.invalid"]
    assert s2 is None and c2.metadata["mntes.schema"] == "mntes.counts" and c2.metadata["mntes.version"] == "99"
    assert "no JSON Schema" in c2.metadata["mntes.invalid"]
    assert len({c.topic for c in summary.channels.values()}) == 2
    hk_schema = by_topic["mntes/t/hk/t_bath"][0][0]
    assert json.loads(hk_schema.data) == json_schema("mntes.hk", 1)
    # The hk message has no t_pub_ns: publish time is its own t_ns? No: t_ns is an array there,
    # so the receive time stands in.
    assert by_topic["mntes/t/hk/t_bath"][0][2].publish_time == T0 + 3


def test_provenance_attachment_and_metadata(tmp_path):
    a, b = provenance_payload("a"), provenance_payload("b")
    w = mio.RotatingMcapWriter(tmp_path, "p", rotate_bytes=0, rotate_s=0)
    w.write("mntes/t/provenance", a, T0)
    w.write("mntes/t/provenance", a, T0 + 1)  # unchanged: stored once
    w.write("mntes/t/counts/0/0", counts_payload(0), T0 + 2)
    w._open_next()  # a rotation carries the latest provenance into the new file
    w.write("mntes/t/provenance", b, T0 + 3)
    w.close()
    f1, f2 = w.files
    att1, att2 = mio.read_attachments(f1), mio.read_attachments(f2)
    assert [x.data for x in att1] == [a]
    assert [x.data for x in att2] == [a, b]
    assert mio.latest_provenance(tmp_path) == b and mio.latest_provenance(f1) == a
    meta = [m for m in mio.read_metadata(f1) if m.name == "mntes.provenance"]
    assert len(meta) == 1 and meta[0].data["params_toml"] == msgpack.unpackb(a)["params_toml"]
    assert meta[0].data["table_identity"] == "sha256:a"
    rec = [m for m in mio.read_metadata(f2) if m.name == "mntes.recording"][0].data
    assert rec["software"].startswith("mntes-stream") and rec["previous_file"] == f1.name and rec["file_seq"] == "2"


def test_rotation_by_size_and_duration_reads_as_one_session(tmp_path):
    sent = []
    w = mio.RotatingMcapWriter(tmp_path, "r", rotate_bytes=20_000, rotate_s=0, flush_interval_s=0.01, chunk_size_bytes=4096)
    for i in range(200):
        p = counts_payload(i)
        sent.append(("mntes/t/counts/0/0", p))
        w.write("mntes/t/counts/0/0", p, T0 + i)
    n_size = len(w.files)
    w.rotate_s = 0.05
    time.sleep(0.06)
    w.tick()
    w.write("mntes/t/hk/t_bath", hk_payload(0), T0 + 500)
    sent.append(("mntes/t/hk/t_bath", hk_payload(0)))
    w.close()
    assert n_size >= 4  # ~100 kB in 20 kB files
    assert len(w.files) == n_size + 1
    assert [p.name for p in w.files] == [f"r-{k:06d}.mcap" for k in range(1, n_size + 2)]
    assert all(p.stat().st_size < 20_000 + 8_000 for p in w.files)
    assert [(m.topic, m.payload) for m in _read(tmp_path)] == sent
    assert [(m.topic, m.payload) for m in _read(list(reversed(w.files)))] == sent  # order comes from time
    # A restarted writer continues the numbering instead of overwriting.
    w2 = mio.RotatingMcapWriter(tmp_path, "r")
    w2.close()
    assert w2.files[0].name == f"r-{n_size + 2:06d}.mcap"


def test_time_range_and_topic_patterns(tmp_path):
    path = tmp_path / "x.mcap"
    with mio.McapFileWriter(path, chunk_size_bytes=1024) as w:
        for i in range(100):
            w.write(f"mntes/t/counts/0/{i % 2}", counts_payload(i), T0 + i * 10)
            w.write("mntes/t/hk/t_bath", hk_payload(i), T0 + i * 10 + 5)
    got = _read(path, topics="mntes/*/counts/**", start_ns=T0 + 200, end_ns=T0 + 400)
    assert [m.payload for m in got] == [counts_payload(i) for i in range(20, 40)]
    got = _read(path, topics=["mntes/t/hk/t_bath", "mntes/t/counts/0/1"])
    assert len(got) == 150 and {m.topic for m in got} == {"mntes/t/hk/t_bath", "mntes/t/counts/0/1"}
    s = mio.Session(path)
    assert s.complete and s.count("mntes/t/counts/**") == 100 and s.start_ns == T0 and s.end_ns == T0 + 995


def _chunked_file(path, n=120):
    sent = []
    with mio.McapFileWriter(path, chunk_size_bytes=1 << 20) as w:
        for i in range(n):
            p = counts_payload(i) if i % 3 else hk_payload(i)
            w.write("mntes/t/counts/0/0" if i % 3 else "mntes/t/hk/t_bath", p, T0 + i)
            sent.append(p)
            if i % 10 == 9:
                w.flush()
        w.write("mntes/t/provenance", provenance_payload(), T0 + n)
        sent.append(provenance_payload())
    with open(path, "rb") as f:
        idx = sorted(make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset)
    return sent, idx


@pytest.fixture(scope="module")
def chunked(tmp_path_factory):
    path = tmp_path_factory.mktemp("cut") / "full.mcap"
    sent, idx = _chunked_file(path)
    return path.read_bytes(), sent, idx


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frac=st.floats(0, 1))
def test_cut_at_any_offset_recovers_every_complete_chunk(chunked, tmp_path_factory, frac):
    data, sent, idx = chunked
    cut = int(frac * len(data))
    path = tmp_path_factory.mktemp("c") / "cut.mcap"
    path.write_bytes(data[:cut])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        session = mio.Session(path)
        got = [m.payload for m in session.iter_messages()]
    # Independent expectation from the reference reader's chunk index of the full file.
    n_complete = sum(1 for c in idx if c.chunk_start_offset + c.chunk_length <= cut)
    per_chunk = [10] * 12 + [1]
    expected = sent[: sum(per_chunk[:n_complete])]
    if cut == len(data):
        assert session.complete and not caught and got == sent
    else:
        assert got == expected
        assert not session.complete and any(issubclass(w.category, mio.TruncatedFileWarning) for w in caught)
        assert session.files[0].recovered_bytes <= cut


def test_unreadable_inputs_raise_transport_error(tmp_path):
    (tmp_path / "junk.mcap").write_bytes(b"PK\x03\x04 definitely not mcap")
    with pytest.raises(TransportError, match="not an MCAP"):
        mio.Session(tmp_path / "junk.mcap")
    with pytest.raises(TransportError, match="no such file"):
        mio.Session(tmp_path / "missing.mcap")
    (tmp_path / "empty").mkdir()
    with pytest.raises(TransportError, match="no .mcap files"):
        mio.Session(tmp_path / "empty")
    with pytest.raises(TransportError, match="cannot create"):
        mio.McapFileWriter(tmp_path / "junk.mcap")  # never overwrite a recording
    with pytest.raises(ConfigError):
        mio.McapFileWriter(tmp_path / "y.mcap", compression="gzip")


_FULL_DISK = """
import os, resource, signal, sys
from mntes_stream.errors import TransportError
from mntes_stream.io.mcap import McapFileWriter
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # writes past the limit fail with EFBIG instead
resource.setrlimit(resource.RLIMIT_FSIZE, (200, 200))
before = len(os.listdir("/proc/self/fd"))
try:
    McapFileWriter(sys.argv[1], metadata={"big": {"k": "x" * 4096}})
except TransportError as exc:
    print("error:", exc)
print("leaked:", len(os.listdir("/proc/self/fd")) - before)
"""


def test_a_writer_that_cannot_start_closes_its_file(tmp_path):
    """A disk that fills up while the file starts: a one-line error and no leaked handle."""
    import subprocess
    import sys

    res = subprocess.run([sys.executable, "-c", _FULL_DISK, str(tmp_path / "full.mcap")],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    assert "error: cannot write" in res.stdout and "File too large" in res.stdout
    assert "leaked: 0" in res.stdout


def test_the_folder_up_writes_is_a_session(tmp_path):
    rec = tmp_path / "mntes-up" / "recordings"
    rec.mkdir(parents=True)
    (tmp_path / "mntes-up" / "params.toml").write_text("")
    with mio.McapFileWriter(rec / "mntes-000001.mcap") as w:
        w.write("mntes/t/counts/0/0", counts_payload(1), T0)
    assert mio.session_files(tmp_path / "mntes-up") == [rec / "mntes-000001.mcap"]
    assert [m.topic for m in _read(tmp_path / "mntes-up")] == ["mntes/t/counts/0/0"]


def test_damaged_chunk_is_skipped_with_a_warning(chunked, tmp_path):
    data, sent, idx = chunked
    bad = bytearray(data)
    c = idx[3]
    mid = c.chunk_start_offset + c.chunk_length - 20  # inside the compressed data
    bad[mid] ^= 0xFF
    path = tmp_path / "bad.mcap"
    path.write_bytes(bytes(bad))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = [m.payload for m in mio.iter_messages(path)]
    assert got == sent[:30] + sent[40:]
    assert any("damaged chunk" in str(w.message) for w in caught)


def test_messages_whose_channel_was_lost_keep_a_channel_rebuilt_from_their_payloads(chunked, tmp_path):
    data, sent, idx = chunked
    bad = bytearray(data[: idx[-1].chunk_start_offset + idx[-1].chunk_length])  # unfinished: scan path
    c = idx[0]  # the chunk that defines the counts and hk channels
    bad[c.chunk_start_offset + c.chunk_length - 20] ^= 0xFF
    path = tmp_path / "orphans.mcap"
    path.write_bytes(bytes(bad))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = [m.payload for m in mio.iter_messages(path)]
    # Every readable message: the counts and hk payloads name their keys, so their channels are rebuilt.
    assert got == sent[10:]
    assert any("1 damaged chunk(s), 10 messages lost" in str(w.message) for w in caught)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        topics = {m.topic for m in mio.iter_messages(path)}
    assert topics == {"mntes/t/counts/0/0", "mntes/t/hk/t_bath", "mntes/t/provenance"}


# Envelopes that claim mntes.provenance but are not one: a bytes-keyed map (json.dumps
# cannot write it), mixed-type map keys (sort_keys cannot order them), missing fields.
BAD_PROVENANCE = [
    msgpack.packb({"schema": "mntes.provenance", "version": 1, "x": {b"k": 1}}),
    msgpack.packb({"schema": "mntes.provenance", "version": 1, "setup": {1: "a", "b": 2}}, strict_types=False),
    msgpack.packb({"schema": "mntes.provenance", "version": 1, "setup": "t"}),
]


def test_malformed_provenance_is_recorded_as_invalid_and_writing_goes_on(tmp_path):
    good = provenance_payload("a")
    sent = [("mntes/t/provenance", p) for p in BAD_PROVENANCE]
    sent += [("mntes/t/provenance", good), ("mntes/t/counts/0/0", counts_payload(0)), ("mntes/t/provenance", BAD_PROVENANCE[0])]
    w = mio.RotatingMcapWriter(tmp_path, "p", rotate_bytes=0, rotate_s=0)
    envs = [w.write(k, p, T0 + i) for i, (k, p) in enumerate(sent)]
    w.close()
    assert w.invalid == 4 and [bool(e.problem) for e in envs] == [True, True, True, False, False, True]
    assert all("invalid mntes.provenance" in e.problem for e in envs if e.problem)
    assert [(m.topic, m.payload) for m in _read(tmp_path)] == sent  # every one recorded verbatim
    # Only the valid one became the file's provenance (attachment and metadata).
    assert [a.data for a in mio.read_attachments(tmp_path)] == [good]
    assert [m.data["table_identity"] for m in mio.read_metadata(tmp_path) if m.name == "mntes.provenance"] == ["sha256:a"]
    with open(w.files[0], "rb") as f:
        invalid = [c for c in make_reader(f).get_summary().channels.values() if "mntes.invalid" in c.metadata]
    assert {c.topic for c in invalid} == {"mntes/t/provenance"} and all(c.schema_id == 0 for c in invalid)
    with pytest.raises(SchemaError):  # a bad provenance to repeat is the caller's bug, not peer data
        mio.McapFileWriter(tmp_path / "q.mcap", provenance=(BAD_PROVENANCE[2], T0))
    assert not (tmp_path / "q.mcap").exists()


def _unchunked_file():
    """Bytes of an MCAP file written without chunks (other tools do): loose schema, channel, message,
    attachment and metadata records; a second channel is declared half way."""
    import io

    from mcap.writer import Writer

    buf = io.BytesIO()
    w = Writer(buf, use_chunking=False)
    w.start()
    sid = w.register_schema("mntes.counts", "jsonschema", b"{}")
    ch = w.register_channel("mntes/t/counts/0/0", "msgpack", sid)
    sent = []
    for i in range(12):
        if i == 6:
            ch = w.register_channel("mntes/t/counts/0/1", "msgpack", sid)
            w.add_attachment(T0, T0 + i, "note", "text/plain", b"hello")
            w.add_metadata("m", {"k": "v"})
        p = counts_payload(i)
        w.add_message(ch, log_time=T0 + i, data=p, publish_time=T0 + i)
        sent.append(p)
    w.finish()
    return buf.getvalue(), sent


def _records(data):
    """(opcode, offset, length) of the top-level records after the magic."""
    import struct

    out, pos = [], 8
    while pos + 9 <= len(data):
        op, ln = struct.unpack_from("<BQ", data, pos)
        out.append((op, pos, ln))
        pos += 9 + ln
    return out


@pytest.mark.parametrize("opcode", [Opcode.SCHEMA, Opcode.CHANNEL, Opcode.MESSAGE])
def test_damaged_loose_record_stops_the_scan_with_what_came_before(tmp_path, opcode):
    import struct

    data, sent = _unchunked_file()
    recs = _records(data)
    footer = next(off for op, off, _ in recs if op == Opcode.DATA_END)  # cut here: the writer "died"
    # The last record of that kind before the end; its first string/field length made impossible.
    op, off, ln = [r for r in recs if r[0] == opcode and r[1] < footer][-1]
    bad = bytearray(data[:footer])
    if opcode == Opcode.MESSAGE:
        struct.pack_into("<Q", bad, off + 1, 5)  # a message record too short for its header
    else:
        struct.pack_into("<I", bad, off + 9 + 2 + (2 if opcode == Opcode.CHANNEL else 0), 10**6)  # name / topic length
    path = tmp_path / "bad.mcap"
    path.write_bytes(bytes(bad))
    with pytest.warns(mio.TruncatedFileWarning, match="not finished"):
        session = mio.Session(path)
    got = [m.payload for m in session.iter_messages()]
    info = session.files[0]
    assert "damaged record" in info.problem and not info.complete and info.recovered_bytes == off
    # Exactly the messages whose records (and channel) precede the damaged record.
    n_before = sum(1 for o, p, _ in recs if o == Opcode.MESSAGE and p < off)
    if opcode == Opcode.CHANNEL:  # the second channel is lost: its messages come after it anyway
        assert n_before == 6
    assert got == sent[:n_before]


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(pick=st.integers(0, 10**6), xor=st.integers(1, 255), cut=st.booleans())
def test_any_damage_to_an_unchunked_file_is_recovered_or_a_transport_error(tmp_path_factory, pick, xor, cut):
    data, _ = _unchunked_file()
    # Damage where it matters: record headers and the length fields that open each record.
    structural = [off + j for _, off, ln in _records(data) for j in range(min(9 + ln, 24))]
    k = structural[pick % len(structural)]
    bad = bytearray(data[:k] if cut else data)
    if not cut:
        bad[k] ^= xor
    path = tmp_path_factory.mktemp("d") / "d.mcap"
    path.write_bytes(bytes(bad))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        try:
            session = mio.Session(path)
            # Loose records carry no CRC: a flipped byte can rename a topic or turn a channel
            # record into a "message" nobody sent, so what comes back is not checked; what must
            # hold is that reading raises nothing but TransportError, whatever the damage.
            list(session.iter_messages())
            session.metadata(), session.attachments()
        except TransportError:  # e.g. the magic itself was hit
            pass


def test_inspect_verify_calls_a_crc_damaged_file_what_it_is(chunked, tmp_path):
    """A finished file whose chunk fails its CRC: the summary alone says complete; --verify does not."""
    import subprocess
    import sys

    data, sent, idx = chunked
    bad = bytearray(data)
    c = idx[3]
    bad[c.chunk_start_offset + c.chunk_length - 20] ^= 0xFF
    path = tmp_path / "bad.mcap"
    path.write_bytes(bytes(bad))
    from mntes_stream.io.mcap.repair import verify_file

    check = verify_file(path)
    assert check.complete and not check.ok and [off for off, _ in check.damaged_chunks] == [c.chunk_start_offset]
    assert check.readable_messages == len(sent) - 10
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "inspect", "--verify", "--json", str(path)],
                         capture_output=True, text=True, timeout=60)
    doc = json.loads(res.stdout)
    assert res.returncode == 2 and doc["complete"] is False and doc["verified"][0]["readable_messages"] == len(sent) - 10
    assert "DAMAGED" in res.stderr
    assert verify_file(_write_ok(tmp_path)).ok


def _write_ok(tmp_path):
    p = tmp_path / "ok.mcap"
    with mio.McapFileWriter(p) as w:
        w.write("mntes/t/counts/0/0", counts_payload(1), T0)
    return p


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(frac=st.floats(0.05, 1))
def test_recover_writes_a_killed_recording_that_any_reader_opens(chunked, tmp_path_factory, frac):
    """mntes-stream recover: every complete chunk of a cut file, in a finished file mcap's own reader indexes."""
    from mntes_stream.io.mcap.repair import recover_file

    data, sent, idx = chunked
    cut = int(frac * len(data))
    d = tmp_path_factory.mktemp("rec")
    (d / "cut.mcap").write_bytes(data[:cut])
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mio.TruncatedFileWarning)
        expected = [m.payload for m in mio.Session(d / "cut.mcap").iter_messages()]
    check = recover_file(d / "cut.mcap", d / "fixed.mcap")
    assert check.readable_messages == len(expected)
    with open(d / "fixed.mcap", "rb") as f:  # the reference reader, from the summary it now has
        reader = make_reader(f)
        summary = reader.get_summary()
        got = [bytes(m.data) for _, _, m in reader.iter_messages(log_time_order=True)]
    assert summary is not None and summary.statistics.message_count == len(expected)
    assert got == expected
    assert mio.Session(d / "fixed.mcap").complete


@pytest.mark.parametrize("compression", ["lz4", "zstd", "none"])
def test_lean_writer_writes_the_mcap_librarys_file_byte_for_byte(compression):
    """The recorder's message path (``_LeanWriter``) against ``mcap.writer.Writer`` on the same calls: same bytes.

    Messages out of time order, on channels registered before and inside a chunk, across several chunks, with
    metadata, an attachment and a flush in between."""
    import io

    from mcap.writer import CompressionType, Writer

    from mntes_stream.io.mcap.writer import _LeanWriter

    kind = {"lz4": CompressionType.LZ4, "zstd": CompressionType.ZSTD, "none": CompressionType.NONE}[compression]
    noise = random.Random(7).randbytes(60 * 700)

    def write(cls) -> bytes:
        out = io.BytesIO()
        w = cls(out, chunk_size=4096, compression=kind)
        w.start(profile="", library="test")
        w.add_metadata("m", {"a": "1"})
        sid = w.register_schema("s", "jsonschema", b"{}")
        a = w.register_channel("mntes/t/counts/0/0", "msgpack", sid, {"k": "v"})
        for i in range(60):
            if i == 25:
                w.add_attachment(create_time=1, log_time=T0, name="x", media_type="application/octet-stream",
                                 data=b"abc")
                b = w.register_channel("mntes/t/power/0/0", "msgpack", 0)
            if i == 40:
                w.flush()
            cid = a if i < 25 or i % 2 else b
            w.add_message(cid, log_time=T0 + (i * 7919) % 101, data=noise[i * 700:i * 700 + i * 37 % 700],
                          publish_time=T0 - i, sequence=i)
        w.finish()
        return out.getvalue()

    lean = write(_LeanWriter)
    assert len(lean) > 10_000 and lean.count(b"\x06") >= 5  # several chunks (0x06: the chunk opcode)
    assert lean == write(Writer)


def test_the_mcap_internals_the_lean_writer_uses_are_there_and_behave(tmp_path):
    """``_LeanWriter`` uses ``mcap.writer.Writer``'s name-mangled internals (pyproject pins mcap to the tested
    minor release for that): every ``_Writer__*`` name in writer.py exists on a library ``Writer`` with the kind
    of value it expects, the library's ``flush``/``finish`` reach the overridden ``__finalize_chunk``, and a real
    file written through the lean path reads back with mcap's own reader, indexes and statistics included."""
    import inspect
    import io
    import re
    from collections import defaultdict

    from mcap.data_stream import RecordBuilder
    from mcap.records import Chunk, Message, Statistics
    from mcap.stream_reader import StreamReader
    from mcap.writer import CompressionType, IndexType, Writer

    from mntes_stream.io.mcap import writer as lean_module

    used = set(re.findall(r"_Writer__\w+", inspect.getsource(lean_module)))
    expected_kinds = {"_Writer__enable_data_crcs": bool, "_Writer__enable_crcs": bool,
                      "_Writer__chunk_builder": object, "_Writer__statistics": Statistics,
                      "_Writer__compression": CompressionType, "_Writer__chunk_size": int,
                      "_Writer__stream": object, "_Writer__record_builder": RecordBuilder,
                      "_Writer__index_types": IndexType, "_Writer__chunk_indices": list}
    methods = {"_Writer__flush", "_Writer__finalize_chunk"}
    assert used == set(expected_kinds) | methods, "writer.py uses an mcap internal this test does not check"
    plain = Writer(io.BytesIO())
    for name, kind in expected_kinds.items():
        assert isinstance(getattr(plain, name), kind), f"mcap.writer.Writer.{name} is gone or changed kind"
    assert isinstance(plain._Writer__statistics.channel_message_counts, defaultdict)
    for name in methods:
        assert callable(getattr(Writer, name)), f"mcap.writer.Writer.{name} is gone"
    # The library's own paths must close chunks through the name the lean writer overrides.
    for caller in (Writer.flush, Writer.finish, Writer._Writer__maybe_finalize_chunk):
        assert "_Writer__finalize_chunk" in caller.__code__.co_names, f"{caller.__name__} no longer closes chunks so"
    assert list(inspect.signature(lean_module._LeanWriter.add_message).parameters) == \
        list(inspect.signature(Writer.add_message).parameters)

    path = tmp_path / "lean.mcap"
    sent = []
    with open(path, "wb") as f:
        w = lean_module._LeanWriter(f, chunk_size=2048, compression=CompressionType.LZ4)
        assert isinstance(w._Writer__chunk_builder, lean_module._Chunk)
        w.start(profile="", library="test")
        a = w.register_channel("a", "msgpack", 0)
        b = w.register_channel("b", "msgpack", 0)
        for i in range(40):
            cid = a if i % 3 else b
            data = bytes([i]) * (100 + i)
            w.add_message(cid, log_time=T0 + 40 - i, data=data, publish_time=T0, sequence=i)
            sent.append((cid, T0 + 40 - i, i, data))
            if i == 20:
                w.flush()
                assert w._Writer__chunk_builder.num_messages == 0  # flush went through the lean chunk close
        w.finish()
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        got = [(m.channel_id, m.log_time, m.sequence, bytes(m.data)) for _, _, m in reader.iter_messages()]
    assert summary.statistics.message_count == 40 and summary.statistics.chunk_count == len(summary.chunk_indexes) > 2
    assert summary.statistics.channel_message_counts == {a: 26, b: 14}
    assert all(ci.compression == "lz4" and ci.message_index_offsets for ci in summary.chunk_indexes)
    assert sorted(got, key=lambda m: m[2]) == sent
    with open(path, "rb") as f:  # the non-seeking reader decompresses every chunk and checks its CRC
        assert sum(isinstance(r, Message) for r in StreamReader(f, validate_crcs=True).records) == 40
    with open(path, "rb") as f:
        chunks = [r for r in StreamReader(f, emit_chunks=True).records if isinstance(r, Chunk)]
    assert len(chunks) == len(summary.chunk_indexes) and all(c.uncompressed_crc for c in chunks)
