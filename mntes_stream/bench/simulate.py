"""``mntes-stream bench simulate``: simulator throughput, detector-samples per second.

Times, on ``--modules`` x ``--channels`` detectors at ``--rate-hz``:

- ``core``: :meth:`ArraySimulator.next_block` (signals, noise, per-sample
  forward solve, counts, housekeeping) in ``--chunk-s`` blocks;
- ``messages``: the same through :class:`SimulatorSource` (plus msgpack
  encoding of every counts and housekeeping message).

Figures are medians over ``--repeat`` runs of ``--seconds`` of stream time
each; the real-time factor is stream seconds per wall-clock second, and
``realtime_detectors`` how many detectors one core keeps up with.
"""

from __future__ import annotations

import statistics
import time

from mntes_stream.bench import machine
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ

HELP = "simulator throughput: detector-samples per second, core and with messages"


def add_arguments(p) -> None:
    p.add_argument("--modules", type=int, default=8, help="modules (default 8)")
    p.add_argument("--channels", type=int, default=128, help="channels per module (default 128)")
    p.add_argument("--rate-hz", type=float, default=DFMUX_SAMPLE_RATE_HZ, help="sample rate (Hz; default the DfMux rate)")
    p.add_argument("--chunk-s", type=float, default=0.1, help="chunk length (s; default 0.1)")
    p.add_argument("--seconds", type=float, default=10.0, help="stream time per run")
    p.add_argument("--repeat", type=int, default=3, help="timed repetitions (default 3)")


def run(args) -> dict:
    from mntes_stream.core.sim import ArraySimulator, SimConfig
    from mntes_stream.service.simulator import SimulatorSource

    cfg = SimConfig(modules=args.modules, channels=args.channels, sample_rate_hz=args.rate_hz)
    n_det = cfg.n_detectors
    t0 = time.perf_counter()
    src = SimulatorSource(cfg, chunk_s=args.chunk_s)
    setup_s = time.perf_counter() - t0
    n_chunk = src.chunk_samples
    n_chunks = max(1, round(args.seconds * args.rate_hz / n_chunk))
    samples = n_det * n_chunk * n_chunks
    core, messages = [], []
    for _ in range(args.repeat):
        sim = ArraySimulator(cfg)
        sim.next_block(n_chunk)  # first block: solver start-up from mid-transition
        t = time.perf_counter()
        for _ in range(n_chunks):
            sim.next_block(n_chunk)
        core.append(samples / (time.perf_counter() - t))
        batches = src.batches(0, 0.0)
        next(batches)
        t = time.perf_counter()
        for _ in range(n_chunks):
            next(batches)
        messages.append(samples / (time.perf_counter() - t))
    core_rate, msg_rate = statistics.median(core), statistics.median(messages)
    return {
        "detectors": n_det,
        "sample_rate_hz": args.rate_hz,
        "chunk_samples": n_chunk,
        "samples": samples,
        "setup_s": setup_s,
        "msamples_per_s": core_rate / 1e6,
        "msamples_per_s_with_messages": msg_rate / 1e6,
        "realtime_factor": msg_rate / (n_det * args.rate_hz),
        "realtime_detectors": int(msg_rate / args.rate_hz),
        "machine": machine(),
    }
