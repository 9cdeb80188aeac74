"""``mntes-stream bench recording``: MCAP write/read throughput for a full focal plane.

The recorder's side of the stream target: counts and power chunks of
``--modules`` 128-channel modules at ``--rate-hz`` in ``--chunk-s`` chunks go
through :class:`~mntes_stream.io.mcap.RotatingMcapWriter` (zstd, flush
cadence, rotation) into a temporary directory and are read back with
:func:`~mntes_stream.io.mcap.iter_messages`. Payloads are real encoded
messages (pre-generated pool, so encoding is not timed); counts carry a DC
level plus white noise, power a level plus noise, like a quiet sky.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

HELP = "MCAP recorder write and read throughput (counts + power, full focal plane)"


def add_arguments(p) -> None:
    p.add_argument("--modules", type=int, default=40, help="128-channel modules (default 40 = 5120 detectors)")
    p.add_argument("--rate-hz", type=float, default=200.0)
    p.add_argument("--chunk-s", type=float, default=0.1)
    p.add_argument("--seconds", type=float, default=5.0, help="stream time to record")
    p.add_argument("--compression", default="zstd", choices=("zstd", "lz4", "none"))
    p.add_argument("--flush-s", type=float, default=1.0)
    p.add_argument("--dir", help="where to write (default: a temporary directory, removed afterwards)")


def _pool(modules: int, n_samp: int, rng, variants: int = 4):
    from mntes_stream.core.ids import detector_id
    from mntes_stream.io.messages import CountsChunk, PowerChunk

    n_ch = 128
    ch = np.arange(n_ch, dtype=np.int32)
    t0 = time.time_ns()
    out = []
    for m in range(modules):
        ids = [detector_id(0, m, c) for c in ch]
        level = rng.integers(-2_000_000, 2_000_000, (n_ch, 1))
        for v in range(variants):
            noise = lambda: rng.normal(0, 300, (n_ch, n_samp)).astype(np.int32)  # noqa: E731
            counts = CountsChunk(setup="bench", board=0, module=m, channels=ch, seq=v, t0_ns=t0, sample_rate_hz=200.0,
                                 counts_i=(level + noise()).astype(np.int32), counts_q=(level // 3 + noise()).astype(np.int32),
                                 t_pub_ns=t0).to_bytes()
            power = PowerChunk(setup="bench", board=0, module=m, channels=ch, detector_ids=ids, seq=v, t0_ns=t0,
                               sample_rate_hz=200.0, p_opt_w=rng.normal(1e-12, 1e-15, (n_ch, n_samp)),
                               flags=np.zeros((n_ch, n_samp), np.uint16), table_identity="bench", converter_kind="table",
                               source_t_pub_ns=t0, t_pub_ns=t0).to_bytes()
            out.append((m, counts, power))
    return out


def run(args) -> dict:
    from mntes_stream.errors import TransportError
    from mntes_stream.io import keys
    from mntes_stream.io.mcap import RotatingMcapWriter, Session

    n_samp = int(round(args.rate_hz * args.chunk_s))
    rng = np.random.default_rng(0)
    pool = _pool(args.modules, n_samp, rng)
    n_chunks = int(round(args.seconds / args.chunk_s))
    by_module = {}
    for m, c, p in pool:
        by_module.setdefault(m, []).append((c, p))
    directory = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="mntes-bench-"))
    try:
        w = RotatingMcapWriter(directory, "bench", flush_interval_s=args.flush_s, compression=args.compression,
                               rotate_bytes=256 << 20, rotate_s=0)
        t_ns = time.time_ns()
        step_ns = int(args.chunk_s * 1e9)
        payload = 0
        t0 = time.perf_counter()
        for k in range(n_chunks):
            for m, variants in by_module.items():
                c, p = variants[k % len(variants)]
                w.write(keys.counts_key("bench", 0, m), c, t_ns + k * step_ns)
                w.write(keys.power_key("bench", 0, m), p, t_ns + k * step_ns + 1)
                payload += len(c) + len(p)
            w.tick()
        w.close()
        t_write = time.perf_counter() - t0
        size = sum(f.stat().st_size for f in w.files)
        t0 = time.perf_counter()
        n_read = read_bytes = 0
        for msg in Session(directory).iter_messages():
            n_read += 1
            read_bytes += len(msg.payload)
        t_read = time.perf_counter() - t0
    finally:
        if not args.dir:
            shutil.rmtree(directory, ignore_errors=True)
    samples = n_chunks * args.modules * 128 * n_samp
    if n_read != 2 * n_chunks * args.modules or read_bytes != payload:
        raise TransportError(f"read back {n_read} messages / {read_bytes} bytes, wrote {2 * n_chunks * args.modules} / {payload}")
    return {
        "channels": args.modules * 128,
        "sample_rate_hz": args.rate_hz,
        "chunk_s": args.chunk_s,
        "stream_seconds": args.seconds,
        "compression": args.compression,
        "messages": n_read,
        "payload_mb": round(payload / 1e6, 1),
        "file_mb": round(size / 1e6, 1),
        "files": len(w.files),
        "compression_ratio": round(payload / size, 2),
        "write_mb_per_s": round(payload / 1e6 / t_write, 1),
        "write_realtime_factor": round(args.seconds / t_write, 2),
        "write_msamples_per_s": round(samples / 1e6 / t_write, 2),
        "read_mb_per_s": round(read_bytes / 1e6 / t_read, 1),
        "read_realtime_factor": round(args.seconds / t_read, 2),
    }
