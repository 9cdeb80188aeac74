"""g3-bridge against malformed G3 streams (issue 22): it stays up, counts each by reason, publishes what follows.

A loopback TCP server plays the DAQ's G3NetworkSender: each connection the
bridge makes is served one byte stream, then closed. The good frames are
spt3g's own serialization (``wire.encode_frame``, the bytes G3NetworkSender
sends); the bad ones are those bytes with a field broken, or frames built
with spt3g whose entries have the wrong class. The issue's 19 streams and two
more (a Timepoint going back in time, blobs spt3g cannot decode under a
correct CRC), in one bridge run:
after every one, good Timepoints follow (on the same connection when
only a frame is bad, on the next when the stream lost its framing) and a
real zenoh subscriber on 127.0.0.1 must see every one of their samples.
"""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np
import pytest

pytest.importorskip("spt3g.core")
psutil = pytest.importorskip("psutil")

from test_g3 import BOARD, LAYOUT, MODULES, N_CH, SAMPLE_NS, T0_NS, raw_frames, true_counts, write  # noqa: E402

from mntes_stream.g3 import frames as F  # noqa: E402
from mntes_stream.g3 import spt3g  # noqa: E402
from mntes_stream.g3.wire import BadFrame, FrameSplitter, encode_frame  # noqa: E402
from mntes_stream.io.messages import decode  # noqa: E402
from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session  # noqa: E402

TP = 4            # good Timepoints after each case (= the bridge's chunk_samples)
FIRST_TP = 60     # sample index of the first Timepoint case (the scans of case 0 cover 0..59)


def tp_bytes(k: int) -> bytes:
    c = true_counts(k)
    return encode_frame(F.timepoint_frame(T0_NS + k * SAMPLE_NS, {(BOARD, m): c[m] for m in MODULES}, N_CH))


def good(case: int) -> bytes:
    k0 = FIRST_TP + TP * case
    return b"".join(tp_bytes(k) for k in range(k0, k0 + TP))


def with_u64(frame: bytes, at: int, value: int) -> bytes:
    return frame[:at] + struct.pack("<Q", value) + frame[at + 8:]


_CRC32C = []
for _n in range(256):
    _c = _n
    for _ in range(8):
        _c = (_c >> 1) ^ (0x82F63B78 if _c & 1 else 0)
    _CRC32C.append(_c)


def with_crc(frame: bytes) -> bytes:
    """``frame`` with the CRC spt3g computes (CRC-32C, no pre/post inversion, over each entry's name and blob)."""
    n, pos, crc = struct.unpack_from("<I", frame, 5)[0], 13, 0
    for _ in range(n):
        n_name = struct.unpack_from("<Q", frame, pos)[0]
        n_blob = struct.unpack_from("<Q", frame, pos + 8 + n_name)[0]
        for b in frame[pos + 8:pos + 8 + n_name] + frame[pos + 16 + n_name:pos + 16 + n_name + n_blob]:
            crc = _CRC32C[(crc ^ b) & 0xFF] ^ (crc >> 8)
        pos += 16 + n_name + n_blob
    return frame[:pos] + struct.pack("<I", crc)


def frame_of(ftype, **entries) -> bytes:
    core, _ = spt3g()
    f = core.G3Frame(ftype)
    for k, v in entries.items():
        f[k] = v
    return encode_frame(f)


def cases(meta: bytes, scans: list[bytes]):
    """(name, bytes of one connection, reason counted or None): the issue's 19 streams and three more, in order."""
    core, dfmux = spt3g()
    T = core.G3FrameType
    tp = tp_bytes(0)
    assert with_crc(tp) == tp
    times = frame_of(T.Scan, DetectorSampleTimes=core.G3VectorTime([core.G3Time(t) for t in (5, 6, 7)]))
    assert struct.pack("<IQ", 1, 3) in times  # the vector's version and its length
    blob_len_at = 13 + 8 + len(b"DfMux")  # first entry of a Timepoint frame: u64 name length, name, u64 blob length
    names = sorted(F.timepoint_frame(T0_NS, {(BOARD, MODULES[0]): true_counts(0)[MODULES[0]]}, N_CH).keys())
    assert names[0] == "DfMux"  # spt3g writes entries in name order: the patched length is DfMux's blob
    frame_level = [
        ("wrong type in Wiring", frame_of(T.Wiring, WiringMap=core.G3Int(3)), "wrong_type"),
        ("wrong type in Scan", frame_of(T.Scan, RawTimestreams_I=core.G3String("x"),
                                        RawTimestreams_Q=core.G3String("y")), "wrong_type"),
        ("wrong type of Scan sample times", frame_of(T.Scan, DetectorSampleTimes=core.G3Int(7)), "wrong_type"),
        ("wrong type in Housekeeping", frame_of(T.Housekeeping, DfMuxHousekeeping=core.G3VectorDouble([1.0])),
         "wrong_type"),
        ("wrong type in Timepoint", frame_of(T.Timepoint, DfMux=core.G3Int(1), EventHeader=core.G3Time(1)),
         "wrong_type"),
        ("empty wiring map", frame_of(T.Wiring, WiringMap=dfmux.DfMuxWiringMap()), "empty_map"),
        ("empty housekeeping map", frame_of(T.Housekeeping, DfMuxHousekeeping=dfmux.DfMuxHousekeepingMap()),
         "empty_map"),
        ("empty DfMux map", frame_of(T.Timepoint, DfMux=dfmux.DfMuxMetaSample(), EventHeader=core.G3Time(1)),
         "empty_map"),
        ("CRC mismatch", tp[:-1] + bytes([tp[-1] ^ 0xFF]), "crc"),
        # beyond the 19: blobs spt3g cannot decode although the frame's CRC is right
        ("a Timepoint back in time", tp, "out_of_order"),  # sample 0 again, long after it
        ("unknown class in a blob", with_crc(tp.replace(b"DfMuxMetaSample", b"XfMuxMetaSample", 1)), "undecodable"),
        ("2**62 sample times claimed", with_crc(times.replace(struct.pack("<IQ", 1, 3), struct.pack("<IQ", 1, 1 << 62),
                                                              1)), "undecodable"),
    ]
    stream_level = [
        ("big-endian flag", b"\x00" + tp[1:], "big_endian"),
        ("garbage bytes", b"GET / HTTP/1.1\r\nHost: daq\r\n\r\n" + bytes(range(256)) * 4, "bad_header"),
        ("frame version 2", tp[:1] + struct.pack("<I", 2) + tp[5:], "frame_version"),
        ("2**20 entries", tp[:5] + struct.pack("<I", 1 << 20) + tp[9:], "too_many_entries"),
        ("name of 1 TB", with_u64(tp, 13, 1 << 40), "name_too_long"),
        ("blob of 1 TB", with_u64(tp, blob_len_at, 1 << 40), "frame_too_large"),
        ("blob of 2**63", with_u64(tp, blob_len_at, 1 << 63), "frame_too_large"),
        ("blob of 2 GB", with_u64(tp, blob_len_at, 2 << 30), "frame_too_large"),
        ("truncated frame", tp[: len(tp) // 2], "truncated"),
    ]
    out = [("Scan before the Wiring frame", b"".join(scans) + meta + good(0), None)]
    for k, (name, bad, reason) in enumerate(frame_level, start=1):
        out.append((name, meta + bad + good(k), reason))
    for k, (name, bad, reason) in enumerate(stream_level, start=1 + len(frame_level)):
        out.append((name, meta + good(k) + bad, reason))  # what follows the break is never read
    return out


class Daq:
    """Loopback server: connection i is served payloads[i] and closed; the bridge reconnects for the next."""

    def __init__(self, payloads):
        self.payloads = list(payloads)
        self.srv = socket.create_server(("127.0.0.1", 0))
        self.srv.settimeout(30)
        self.port = self.srv.getsockname()[1]
        self.served = 0
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        for data in self.payloads:
            try:
                conn, _ = self.srv.accept()
            except OSError:
                return
            with conn:
                try:
                    conn.sendall(data)
                    conn.shutdown(socket.SHUT_WR)
                    conn.settimeout(5)
                    while conn.recv(1 << 16):  # until the bridge hangs up (it reads everything first)
                        pass
                except OSError:
                    pass
            self.served += 1
        self.srv.close()


@pytest.fixture(scope="module")
def scan_frames(tmp_path_factory):
    """The collated Scan frames of a 60-sample run (three of 25, 25, 10 samples), as bytes."""
    from mntes_stream.g3.wire import iter_file_frames

    core, _ = spt3g()
    path = write(raw_frames(), tmp_path_factory.mktemp("scans") / "scans.g3", collate=True)
    frames = [f for f in iter_file_frames(path, 1 << 30) if f.type == core.G3FrameType.Scan and
              "RawTimestreams_I" in f]
    assert len(frames) == 3
    return [encode_frame(f) for f in frames]


def test_splitter_refuses_claims_before_allocating():
    tp = tp_bytes(0)
    s = FrameSplitter(1 << 20)
    s.feed(tp + tp[:10])
    assert s.next() == tp and s.next() is None and s.pending() == 10
    s = FrameSplitter(1 << 20)
    s.feed(with_u64(tp, 13 + 8 + 5, 1 << 63)[:40])  # only the header and the claim have arrived
    with pytest.raises(BadFrame) as e:
        s.next()
    assert e.value.reason == "frame_too_large"


def test_bridge_survives_malformed_streams(scan_frames):
    from mntes_stream.g3.bridge import BridgeSettings, G3BridgeConfig, G3BridgeService, ledger_line
    from mntes_stream.service.base import StopFlag

    meta = b"".join(encode_frame(f) for f in raw_frames(n=0))  # Wiring, Housekeeping, GcpSlow
    todo = cases(meta, scan_frames)
    assert len(todo) == 22
    daq = Daq([data for _, data, _ in todo])
    port = free_tcp_port()
    cfg = G3BridgeConfig(bridge=BridgeSettings(source=f"tcp://127.0.0.1:{daq.port}", setup="lab", chunk_samples=TP,
                                               reconnect_s=0.05, reconnect_max_s=0.2, timeout_s=5.0,
                                               max_frame_mb=64, max_held_frames=2, wait_subscribers_s=5.0),
                         zenoh=loopback(connect_ports=[port]))
    svc = G3BridgeService(cfg)
    stop = StopFlag()
    result: dict = {}
    live: dict = {}
    proc = psutil.Process()
    rss0 = peak = proc.memory_info().rss
    with open_session(loopback(port)) as z:
        sub = QueueSubscriber(z, ["mntes/lab/counts/**"])
        th = threading.Thread(target=lambda: result.update(svc.start(stop=stop)), daemon=True)
        th.start()
        try:
            want = len(LAYOUT) * (35 + TP * len(todo))  # Scans 2 and 3 (25 + 10 samples; the first dropped) + every case
            deadline = time.monotonic() + 60
            while (len(live) < want or daq.served < len(todo)) and time.monotonic() < deadline:
                peak = max(peak, proc.memory_info().rss)
                item = sub.get(timeout_s=0.1)
                if item is None:
                    continue
                msg = decode(item[1])
                for row, ch in enumerate(msg.channels):
                    for t, i, q in zip(msg.times_ns(), msg.counts_i[row], msg.counts_q[row]):
                        live[(msg.module, int(ch), int(t))] = (int(i), int(q))
            alive = th.is_alive()
        finally:
            stop.set()
            th.join(30)
            sub.close()
    assert alive, "the bridge stopped on its own"
    status = svc.status()
    assert status["state"] == "stopped"
    assert any(w.startswith("G3 frames rejected (") for w in status["warnings"])  # each cause said once
    assert len(set(status["warnings"])) == len(status["warnings"])  # once each, not every time
    want_reasons: dict = {}
    for _, _, reason in todo:
        if reason:
            want_reasons[reason] = want_reasons.get(reason, 0) + 1
    want_reasons["before_wiring"] = 1  # three Scans held with room for two: the oldest is counted
    assert result["rejected"] == want_reasons
    assert result["rejected_frames"] == sum(want_reasons.values()) == 22
    assert result["connections"] == len(todo)
    # Every sample after every bad frame reached a real subscriber, with the counts the DAQ sent.
    for k in range(FIRST_TP, FIRST_TP + TP * len(todo)):
        c = true_counts(k)
        for m in MODULES:
            for ch in range(N_CH):
                assert live[(m, ch, T0_NS + k * SAMPLE_NS)] == (int(c[m][0][ch]), int(c[m][1][ch]))
    held = {t for (_, _, t) in live if t < T0_NS + FIRST_TP * SAMPLE_NS}
    assert held == {T0_NS + k * SAMPLE_NS for k in range(25, 60)}  # the held Scans 2 and 3, after the wiring
    assert len(live) == want
    assert peak - rss0 < 150 * 2**20, f"RSS grew by {(peak - rss0) / 2**20:.0f} MB"
    # per module: the two held Scans, then one chunk of TP Timepoints per case
    assert result["published"] == {f"{BOARD}/{m}": 2 + len(todo) for m in MODULES}
    assert result["ledger"]["other"]["rejected"] == want_reasons
    assert {k: v["done"] for k, v in result["ledger"].items() if k != "other"} == result["published"]
    assert result["lost"] == 22 and result["gap_samples"] == 0
    line = ledger_line(result)
    assert line.count("\n") == 0 and "rejected 22 (" in line and "frame_too_large 3" in line and "lost 22 of" in line


def test_empty_and_wrong_frames_do_not_reach_the_history():
    """A rejected housekeeping frame leaves the bias history as it was (what the converter later sees)."""
    from mntes_stream.g3.translate import FrameTranslator
    from mntes_stream.g3.wire import decode_frame

    core, dfmux = spt3g()
    tr = FrameTranslator("lab", chunk_samples=TP)
    for f in raw_frames(n=0):
        tr.accept(f)
    before = tr.hk.latest()
    bad = decode_frame(frame_of(core.G3FrameType.Housekeeping, DfMuxHousekeeping=dfmux.DfMuxHousekeepingMap()))
    assert tr.accept(bad) == [] and tr.counters.rejected == {"empty_map": 1}
    assert tr.hk.latest() is before
    assert np.isfinite(before.v_bias_rms_v).all()


def _with_bad_frames(src, dst, bad_at: dict):
    """``src`` rewritten to ``dst`` with the frame at each index of ``bad_at`` replaced by its bytes."""
    from mntes_stream.g3.wire import AtomicG3Writer, decode_frame, iter_file_frames

    with AtomicG3Writer(dst) as w:
        for k, f in enumerate(iter_file_frames(src, 1 << 30)):
            w(decode_frame(bad_at[k]) if k in bad_at else f)
    return dst


@pytest.mark.parametrize("layout", ["scans", "timepoints"])
def test_convert_skips_a_wrong_typed_frame_and_marks_the_output(tmp_path, layout, capsys):
    """RUN.g3 -> OUT.g3 with one frame of the wrong class: counted, skipped, said, and marked in OUT.g3."""
    import json

    from mntes_stream.cli import main
    from mntes_stream.g3.wire import iter_file_frames

    core, _ = spt3g()
    T = core.G3FrameType
    collate = layout == "scans"
    run = write(raw_frames(), tmp_path / "run.g3", collate=collate)
    frames = list(iter_file_frames(run, 1 << 30))
    data = [k for k, f in enumerate(frames) if f.type == (T.Scan if collate else T.Timepoint)
            and ("RawTimestreams_I" in f or not collate)]
    bad = frame_of(T.Scan, RawTimestreams_I=core.G3Int(1), RawTimestreams_Q=core.G3Int(2)) if collate else \
        frame_of(T.Timepoint, DfMux=core.G3String("x"), EventHeader=core.G3Time(1))
    damaged = _with_bad_frames(run, tmp_path / "damaged.g3", {data[1]: bad})
    out = tmp_path / "out.g3"
    assert main(["convert", str(damaged), str(out), "--kind", "electrical", "--json"]) == 0
    result = json.loads(capsys.readouterr().out)
    assert result["rejected_frames"] == {"wrong_type": 1}
    written = list(core.G3File(str(out)))
    marks = [dict(f["MntesRejectedFrames"]) for f in written if f.type == T.PipelineInfo and
             "MntesRejectedFrames" in f]
    assert marks == [{"wrong_type": 1}]
    samples = sum(f["MntesOpticalPower"].n_samples for f in written if "MntesOpticalPower" in f)
    assert samples == (60 - 25 if collate else 60 - 1)  # the skipped frame's samples, and no others, are missing
    assert not (tmp_path / "out.g3.partial").exists()


DISK_FULL = r"""
import resource, signal, sys
signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails with EFBIG, as a full disk does
resource.setrlimit(resource.RLIMIT_FSIZE, (int(sys.argv[1]), int(sys.argv[1])))
from mntes_stream.cli import main
sys.exit(main(sys.argv[2:]))
"""


def test_convert_on_a_full_disk_is_one_line_and_leaves_nothing(tmp_path):
    """A G3 output that cannot be written whole: rc 2, one line, neither OUT.g3 nor OUT.g3.partial."""
    import subprocess
    import sys

    run = write(raw_frames(), tmp_path / "run.g3", collate=True)
    out = tmp_path / "out.g3"
    p = subprocess.run([sys.executable, "-c", DISK_FULL, "4096", "convert", str(run), str(out), "--kind",
                        "electrical"], capture_output=True, text=True, timeout=120)
    err = p.stderr.strip().splitlines()
    assert p.returncode == 2 and len(err) == 1 and "out.g3" in err[0] and "write failed" in err[0], p.stderr
    assert not out.exists() and not (tmp_path / "out.g3.partial").exists()
    p = subprocess.run([sys.executable, "-c", DISK_FULL, str(1 << 30), "convert", str(run), str(out), "--kind",
                        "electrical"], capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and out.exists(), p.stderr  # the same command with room for it


def test_g3_to_mcap_counts_and_says_what_it_skipped(tmp_path, caplog):
    """RUN.g3 -> messages (-> OUT.mcap): a wrong-typed Timepoint is counted and said; every other sample is there."""
    from mntes_stream.core.params import table1_params
    from mntes_stream.g3.files import g3_messages, g3_to_mcap
    from mntes_stream.g3.wire import iter_file_frames
    from mntes_stream.io.mcap import Session

    core, _ = spt3g()
    T = core.G3FrameType
    run = write(raw_frames(), tmp_path / "run.g3")
    tps = [k for k, f in enumerate(iter_file_frames(run, 1 << 30)) if f.type == T.Timepoint]
    damaged = _with_bad_frames(run, tmp_path / "damaged.g3",
                               {tps[7]: frame_of(T.Timepoint, DfMux=core.G3Int(1), EventHeader=core.G3Time(1))})
    bad: dict = {}
    times = set()
    for _, key, payload in g3_messages(damaged, "lab", bad=bad):
        if "/counts/" in key:
            times |= set(decode(payload).times_ns().tolist())
    assert bad == {"wrong_type": 1}
    assert times == {T0_NS + k * SAMPLE_NS for k in range(60) if k != 7}
    params = {n: table1_params(n) for n in LAYOUT}
    with caplog.at_level("WARNING", logger="mntes_stream.g3"):
        g3_to_mcap(damaged, tmp_path / "out.mcap", params=params)
    assert any("1 G3 frame(s) skipped (wrong_type 1)" in r.getMessage() for r in caplog.records)
    assert Session(tmp_path / "out.mcap").message_counts()[f"mntes/lab/counts/{BOARD}/2"] == 4


def test_g3_bridge_command_survives_and_ends_with_its_ledger(tmp_path):
    """The `g3-bridge` command (its own process) on three bad streams: rc 0, no traceback, the ledger last."""
    import subprocess
    import sys

    core, _ = spt3g()
    T = core.G3FrameType
    meta = b"".join(encode_frame(f) for f in raw_frames(n=0))
    tp = tp_bytes(FIRST_TP)
    daq = Daq([meta + b"\x00" + tp[1:],                                                    # big-endian flag
               meta + frame_of(T.Scan, RawTimestreams_I=core.G3String("x"),
                               RawTimestreams_Q=core.G3String("y")) + good(0),              # wrong type in Scan
               meta + with_u64(tp, 13 + 8 + 5, 2 << 30)])                                  # a 2 GB claim
    cfg = tmp_path / "bridge.toml"
    cfg.write_text(f'[g3-bridge]\nsource = "tcp://127.0.0.1:{daq.port}"\nchunk_samples = {TP}\nreconnect_s = 0.05\n'
                   'duration_s = 4.0\nwait_subscribers_s = 0\n\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:0"]\n')
    p = subprocess.run([sys.executable, "-m", "mntes_stream", "g3-bridge", "--config", str(cfg)],
                       capture_output=True, text=True, timeout=120)
    assert p.returncode == 0 and "Traceback" not in p.stderr, p.stderr[-2000:]
    last = p.stdout.strip().splitlines()[-1]
    assert last.startswith("g3-bridge done: received 5 chunks: published 2, rejected 3 ("), last
    assert "big_endian 1" in last and "frame_too_large 1" in last and "wrong_type 1" in last and "lost 3 of 5" in last
    assert daq.served == 3
