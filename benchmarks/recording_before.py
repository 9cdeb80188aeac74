"""The recorder's per-message path before issue 23 item 4, for the before/after in benchmarks/recording.json.

Run it against the tree of commit de36b28 (the recorder's write closure as it was there, verbatim, without zenoh):

    git archive de36b28 mntes_stream schemas | tar -x -C /tmp/old
    PYTHONPATH=/tmp/old python benchmarks/recording_before.py [COMPRESSION[:CHUNK_KB] ...]   (default zstd:4096)

It feeds the same messages as ``mntes-stream bench recording`` (its ``stream``, loaded from this checkout)
and prints one JSON line per compression: this process's CPU per million counts samples.
"""

import importlib.util
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

from mntes_stream.core.sequence import StreamSequence
from mntes_stream.io import keys
from mntes_stream.io.mcap import RotatingMcapWriter
from mntes_stream.io.mcap.ledger import RecordingBook, power_is_late
from mntes_stream.service.coverage import Coverage

_here = Path(__file__).resolve().parents[1] / "mntes_stream" / "bench" / "recording.py"
_spec = importlib.util.spec_from_file_location("bench_recording_now", _here)
_bench = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_bench)


def record_once(messages, compression="zstd", chunk_kb=4096):
    d = tempfile.mkdtemp()
    t0_ns = time.time_ns()
    c0, w0 = time.process_time(), time.perf_counter()
    writer = RotatingMcapWriter(d, "bench", flush_interval_s=1.0, compression=compression,
                                chunk_size_bytes=chunk_kb * 1024, rotate_bytes=256 << 20, rotate_s=0)
    book, coverage, sequences, by_kind = RecordingBook("bench"), Coverage(2.0), {}, {}

    def write(item) -> None:  # run_recorder's closure at de36b28 (shard filter, foxglove off)
        topic, payload, t_ns = item
        env = writer.write(topic, payload, t_ns)
        kind = keys.kind_of(topic) or "other"
        late = kind == "power" and not env.problem and power_is_late(payload)
        coverage.add(topic, env.seq, time.monotonic(), late=late)
        book.add(topic, payload, env, t_ns, late=late)
        by_kind[kind] = by_kind.get(kind, 0) + 1
        if env.seq is not None and kind != "counts":
            seq = sequences.get(topic)
            if seq is None:
                seq = sequences[topic] = StreamSequence()
            seq.observe(env.seq, env.publish_time_ns if env.publish_time_ns is not None else t_ns)

    for m, k, counts, power in messages:
        write((keys.counts_key("bench", 0, m), counts, t0_ns + k * 100_000_000))
        write((keys.power_key("bench", 0, m), power, t0_ns + k * 100_000_000 + 1))
        if m == 0:
            writer.tick()
    writer.close()
    cpu_s, wall_s = time.process_time() - c0, time.perf_counter() - w0
    size = sum(f.stat().st_size for f in writer.files)
    shutil.rmtree(d)
    return cpu_s, wall_s, size, book.ledger_now().line()


def main(compressions, modules=40, duration_s=5.0, repeat=3):
    messages = _bench.stream(modules, 20, int(round(duration_s / 0.1)))
    samples = len(messages) * 128 * 20
    payload = sum(len(c) + len(p) for _, _, c, p in messages)
    for spec in compressions:
        comp, _, kb = spec.partition(":")
        kb = int(kb or 4096)
        runs = [record_once(messages, comp, kb) for _ in range(repeat)]
        cpu_s, wall_s, size, line = sorted(runs)[len(runs) // 2]
        print(json.dumps({"compression": comp, "chunk_kb": kb, "cpu_s_per_msamples": round(cpu_s / (samples / 1e6), 4),
                          "msamples_per_cpu_s": round(samples / 1e6 / cpu_s, 2),
                          "cpu_s_per_msamples_runs": [round(r[0] / (samples / 1e6), 4) for r in runs],
                          "write_wall_msamples_per_s": round(samples / 1e6 / wall_s, 2),
                          "compression_ratio": round(payload / size, 3), "ledger_line": line}), flush=True)


if __name__ == "__main__":
    main(sys.argv[1:] or ["zstd"])
