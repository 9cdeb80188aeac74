"""``mntes-stream bench recording``: the recorder's cost for a full focal plane, and its files read back.

Counts and power chunks of ``--modules`` 128-channel modules at ``--rate-hz``
in ``--chunk-s`` chunks (real encoded messages, every chunk its own sequence
number; counts a DC level plus white noise, power a level plus noise, like a
quiet sky) go through the recorder's own per-message path
(:class:`~mntes_stream.service.recorder_sink.RecorderSink`: header read,
ledger, coverage, hand-over to the writer thread that frames, compresses and
writes) into a temporary directory, without zenoh; then they are read back
with :class:`~mntes_stream.io.mcap.Session` and the ledger checked. The
figure that matters is ``cpu_s_per_msamples``: this process's CPU (every
thread, ``time.process_time``) per million counts samples recorded.
``--sweep`` measures every compression and chunk size (how the default was
picked: docs/recording.md).
"""

from __future__ import annotations

import shutil
import statistics
import tempfile
import time
from pathlib import Path

import numpy as np

HELP = "the recorder's CPU per M samples, write and read throughput (counts + power, full focal plane)"

_SWEEP_KB = (128, 256, 1024, 4096)


def add_arguments(p) -> None:
    from mntes_stream.options import deprecated_alias
    from mntes_stream.service.recorder import RecorderConfig

    p.add_argument("--modules", type=int, default=40, help="128-channel modules (default 40 = 5120 detectors)")
    p.add_argument("--rate-hz", type=float, default=200.0, help="sample rate (default 200)")
    p.add_argument("--chunk-s", type=float, default=0.1, help="seconds of samples per chunk (default 0.1)")
    p.add_argument("--duration", type=float, default=5.0, help="seconds of stream to record (default 5)")
    deprecated_alias(p, "--seconds", "--duration", dest="duration", type=float)
    p.add_argument("--compression", default=RecorderConfig.compression, choices=("zstd", "lz4", "none"),
                   help=f"chunk compression (default: the recorder's, {RecorderConfig.compression})")
    p.add_argument("--chunk-kb", type=int, default=RecorderConfig.chunk_size_kb,
                   help=f"chunk size in KiB (default: the recorder's, {RecorderConfig.chunk_size_kb})")
    p.add_argument("--flush-s", type=float, default=1.0, help="flush cadence (default 1)")
    p.add_argument("--repeat", type=int, default=1, help="runs per setting; the median CPU figure is reported")
    p.add_argument("--sweep", action="store_true",
                   help=f"every compression (zstd, lz4, none) x chunk size ({', '.join(map(str, _SWEEP_KB))} KiB)")
    p.add_argument("--out", help="where to write (default: a temporary directory, removed afterwards)")
    deprecated_alias(p, "--dir", "--out", dest="out")


def stream(modules: int, n_samp: int, n_chunks: int, rate_hz: float = 200.0, seed: int = 0, variants: int = 8):
    """``(counts, power)`` payload pairs for every chunk index and module (each chunk its own ``seq``).

    Noise arrays are drawn for ``variants`` chunks per module and reused; every message is encoded (not timed).
    """
    from mntes_stream.core.ids import detector_id
    from mntes_stream.io.messages import CountsChunk, PowerChunk

    rng = np.random.default_rng(seed)
    n_ch = 128
    ch = np.arange(n_ch, dtype=np.int32)
    t0 = time.time_ns()
    step_ns = int(round(n_samp / rate_hz * 1e9))
    arrays = []
    for _ in range(modules):
        level = rng.integers(-2_000_000, 2_000_000, (n_ch, 1))
        arrays.append([((level + rng.normal(0, 300, (n_ch, n_samp))).astype(np.int32),
                        (level // 3 + rng.normal(0, 300, (n_ch, n_samp))).astype(np.int32),
                        rng.normal(1e-12, 1e-15, (n_ch, n_samp))) for _ in range(variants)])
    ids = [[detector_id(0, m, c) for c in ch] for m in range(modules)]
    flags = np.zeros((n_ch, n_samp), np.uint16)
    out = []
    for k in range(n_chunks):
        t = t0 + k * step_ns
        for m in range(modules):
            ci, cq, p = arrays[m][k % variants]
            counts = CountsChunk(setup="bench", board=0, module=m, channels=ch, seq=k, t0_ns=t, sample_rate_hz=rate_hz,
                                 counts_i=ci, counts_q=cq, t_pub_ns=t).to_bytes()
            power = PowerChunk(setup="bench", board=0, module=m, channels=ch, detector_ids=ids[m], seq=k, t0_ns=t,
                               sample_rate_hz=200.0, p_opt_w=p, flags=flags, table_identity="bench",
                               converter_kind="table", source_t_pub_ns=t, t_pub_ns=t).to_bytes()
            out.append((m, k, counts, power))
    return out


def record_once(messages, directory: Path, compression: str, chunk_kb: int, flush_s: float) -> dict:
    """Feed ``messages`` through the recorder's per-message path into ``directory``; CPU and wall clock."""
    from mntes_stream.io import keys
    from mntes_stream.service.recorder import RecorderConfig
    from mntes_stream.service.recorder_sink import RecorderSink

    cfg = RecorderConfig(setup="bench", directory=str(directory), prefix="bench", compression=compression,
                         chunk_size_kb=chunk_kb, flush_interval_s=flush_s, rotate_mb=256.0, rotate_s=0.0)
    topics = {}
    t0_ns = time.time_ns()
    c0, w0, r0 = time.process_time(), time.perf_counter(), time.thread_time()
    sink = RecorderSink(cfg)
    for m, k, counts, power in messages:
        tc = topics.get(m)
        if tc is None:
            tc = topics[m] = (keys.counts_key("bench", 0, m), keys.power_key("bench", 0, m))
        sink.add(tc[0], counts, t0_ns + k * 100_000_000)
        sink.add(tc[1], power, t0_ns + k * 100_000_000 + 1)
        if m == 0:
            sink.writer.tick()
    receive_s = time.thread_time() - r0  # before close: the writer's last work is not the receive thread's
    sink.writer.close()
    cpu_s, wall_s = time.process_time() - c0, time.perf_counter() - w0
    w = sink.writer
    return {"cpu_s": cpu_s, "receive_s": receive_s, "wall_s": wall_s, "samples": sink.samples, "files": [Path(f) for f in w.files],
            "messages": w.messages, "payload": w.payload_bytes, "queue_full": w.queue_full, "wait_s": w.wait_s,
            "ledger_line": sink.book.ledger_now().line()}


def run(args) -> dict:
    from mntes_stream.errors import ConfigError, TransportError
    from mntes_stream.io.mcap import Session

    if args.modules < 1 or args.rate_hz <= 0 or args.chunk_s <= 0 or args.duration <= 0 or args.repeat < 1:
        raise ConfigError("bench recording: --modules, --rate-hz, --chunk-s, --duration and --repeat must be > 0")
    n_samp = max(1, int(round(args.rate_hz * args.chunk_s)))
    n_chunks = max(1, int(round(args.duration / args.chunk_s)))
    messages = stream(args.modules, n_samp, n_chunks, args.rate_hz)
    payload = sum(len(c) + len(p) for _, _, c, p in messages)
    samples = n_chunks * args.modules * 128 * n_samp
    settings = ([(c, kb) for c in ("zstd", "lz4", "none") for kb in _SWEEP_KB] if args.sweep
                else [(args.compression, args.chunk_kb)])
    base = Path(args.out) if args.out else Path(tempfile.mkdtemp(prefix="mntes-bench-"))
    rows = []
    try:
        for compression, kb in settings:
            runs = []
            for i in range(args.repeat):
                directory = base / f"{compression}-{kb}k-{i}"
                shutil.rmtree(directory, ignore_errors=True)
                runs.append(record_once(messages, directory, compression, kb, args.flush_s))
            r = sorted(runs, key=lambda x: x["cpu_s"])[len(runs) // 2]
            if r["samples"] != samples or r["messages"] != len(messages) * 2 or r["payload"] != payload:
                raise TransportError(f"the recorder booked {r['samples']} samples, {r['messages']} messages, "
                                     f"{r['payload']} bytes; sent {samples}, {len(messages) * 2}, {payload}")
            expected = f"received {len(messages)} chunks: recorded {len(messages)}; lost 0 of {len(messages)}"
            if r["ledger_line"] != expected:
                raise TransportError(f"ledger {r['ledger_line']!r}, expected {expected!r}")
            size = sum(f.stat().st_size for f in r["files"])
            row = {
                "compression": compression,
                "chunk_kb": kb,
                "cpu_s_per_msamples": round(r["cpu_s"] / (samples / 1e6), 4),
                "msamples_per_cpu_s": round(samples / 1e6 / r["cpu_s"], 2),
                "cpu_s_per_msamples_runs": [round(x["cpu_s"] / (samples / 1e6), 4) for x in runs],
                "receive_cpu_s_per_msamples": round(r["receive_s"] / (samples / 1e6), 4),
                "write_wall_msamples_per_s": round(samples / 1e6 / statistics.median(x["wall_s"] for x in runs), 2),
                "compression_ratio": round(payload / size, 3),
                "file_mb": round(size / 1e6, 1),
                "writer_queue_full": r["queue_full"],
            }
            rows.append((row, r))
        best_row, best = rows[0] if len(rows) == 1 else (None, None)
        read = None
        if best is not None:
            t0 = time.perf_counter()
            n_read = read_bytes = 0
            for msg in Session(best["files"]).iter_messages():
                n_read += 1
                read_bytes += len(msg.payload)
            t_read = time.perf_counter() - t0
            if n_read != 2 * len(messages) or read_bytes != payload:
                raise TransportError(f"read back {n_read} messages / {read_bytes} bytes, wrote {2 * len(messages)} / "
                                     f"{payload}")
            read = {"read_mb_per_s": round(read_bytes / 1e6 / t_read, 1),
                    "read_realtime_factor": round(args.duration / t_read, 2)}
    finally:
        if not args.out:
            shutil.rmtree(base, ignore_errors=True)
    out = {
        "channels": args.modules * 128,
        "sample_rate_hz": args.rate_hz,
        "chunk_s": args.chunk_s,
        "stream_seconds": args.duration,
        "samples": samples,
        "messages": 2 * len(messages),
        "payload_mb": round(payload / 1e6, 1),
        "ledger_line": rows[0][1]["ledger_line"],
    }
    if best_row is not None:
        out.update(best_row)
        out["write_realtime_factor"] = round(best_row["write_wall_msamples_per_s"] * 1e6 / (samples / args.duration), 2)
        out.update(read)
    else:
        out["sweep"] = [row for row, _ in rows]
    return out
