"""The converter pipeline in process, without zenoh: CPU per counts chunk, and a digest of the power.

Feeds ``ConverterPipeline.handle_many`` the messages of a ``MinimalSource`` (40 modules x 128 channels,
200 Hz, 0.1 s chunks: ``bench stream``'s array), ``--steps`` readout steps per batch (1: a converter that
keeps up; 8: one catching up), and prints CPU microseconds per chunk (the best of ``--repeat``; of it, inside the
kernel calls, and the chunks a call took) and a
SHA-256 of every power chunk's values, flags and identity, one of the whole power messages, and the
ledger, so two versions of the code can be compared for speed and for bit-identical power::

    PYTHONPATH=OLD_CHECKOUT python benchmarks/pipeline_inprocess.py --json
    python benchmarks/pipeline_inprocess.py --json
"""

from __future__ import annotations

import argparse
import hashlib
import json
import platform
import time

from mntes_stream.core.convert import make_converter
from mntes_stream.io.messages import PowerChunk
from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
from mntes_stream.service.source import MinimalSource, SourceConfig

T0_NS = 1_700_000_000_000_000_000


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--modules", type=int, default=40)
    ap.add_argument("--channels", type=int, default=128)
    ap.add_argument("--duration", type=float, default=10.0, help="seconds of data")
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--json", action="store_true")
    args = ap.parse_args()
    src = MinimalSource(SourceConfig(modules=args.modules, channels=args.channels, sample_rate_hz=200.0, chunk_s=0.1))
    src.prepare()
    batches = [[(k, p, t + 1_000_000) for k, p in batch] for t, batch in src.batches(T0_NS, args.duration)]
    conv = make_converter("table", {p.detector_id: p for p in src.params})
    out = {"machine": f"{platform.machine()} {platform.processor() or ''}".strip(), "python": platform.python_version()}
    for steps in (1, 8):
        best, kernel, digest, chunks = None, None, None, 0
        for _ in range(args.repeat):
            pipe = ConverterPipeline(conv, PipelineConfig(setup=src.config.setup), clock=None)
            power = []
            c0 = time.process_time()
            for i in range(0, len(batches), steps):
                power += pipe.handle_many([m for b in batches[i:i + steps] for m in b])
            power += pipe.flush()
            cpu = time.process_time() - c0
            if best is None or cpu < best:
                best, kernel = cpu, pipe.kernel_cpu_s
            chunks = pipe.counters.chunks_converted
            h, whole = hashlib.sha256(), hashlib.sha256()
            for key, payload in power:
                if "/power/" in key:
                    pc = PowerChunk.from_bytes(payload)
                    h.update(key.encode() + pc.p_opt_w.tobytes() + pc.flags.tobytes())
                    h.update(repr((pc.seq, pc.t0_ns, pc.late, pc.detector_ids)).encode())
                    whole.update(key.encode() + bytes(payload))  # clock None: publication times are receive times
            digest = h.hexdigest()
        samples = chunks * args.channels * round(0.1 * 200.0)
        out[f"steps_{steps}"] = {"chunks": chunks, "us_per_chunk": round(best / chunks * 1e6, 1),
                                 "kernel_us_per_chunk": round(kernel / chunks * 1e6, 1),
                                 "chunks_per_kernel_call": round(pipe.chunks_per_kernel_call, 1),
                                 "msamples_per_cpu_s": round(samples / best / 1e6, 2), "power_sha256": digest,
                                 "payload_sha256": whole.hexdigest(), "ledger": pipe.ledger_now().line()}
    print(json.dumps(out, indent=1) if args.json else out)


if __name__ == "__main__":
    main()
