"""Sharded benchmark: a zenoh router, N converter shards, a recorder and a source, on this machine.

For each N of ``--shards`` (default 1, 2, 4) a fresh set of spawned
processes, every one a zenoh client of the router on 127.0.0.1: the router,
N converters (``shard = i/N``, each loading only its detectors), the MCAP
recorder (``--recorder-shards`` of them), and the minimal physics source
publishing ``--duration`` seconds of the array as fast as it can (flat out:
the aggregate rate is what the shards sustain together, not the rate
offered). Figures come from the recording: aggregate samples/s (power
samples recorded over the time from the first counts published to the last
power published), latency of every power chunk (its ``t_pub_ns`` minus the
recorder's receive time of its counts chunk: flat out, the queueing delay), lost
(counts chunks sent minus distinct power chunks recorded), and the scaling
efficiency ``aggregate / (N x aggregate of N = 1)``.
"""

from __future__ import annotations

import math
import os
import statistics
import tempfile
import time
from pathlib import Path

from mntes_stream.bench.stream import BenchSource
from mntes_stream.options import add_zenoh_args, zenoh_layer

HELP = "router + N converter shards + recorder + source on loopback: aggregate rate, latency, loss, scaling"

# Arrays to size for (detectors, sample rate): what a site needs in shards, from the measured rate per shard.
ARRAYS = {"LiteBIRD": (4_508, 19.0), "SPT-3G": (16_000, 152.587890625), "SO": (70_000, 200.0)}


def add_arguments(p) -> None:
    p.add_argument("--shards", default="1,2,4", help="converter shard counts to run, comma separated (default 1,2,4)")
    p.add_argument("--recorder-shards", type=int, default=1, help="recorder processes (default 1)")
    p.add_argument("--modules", type=int, default=40, help="readout modules (default 40)")
    p.add_argument("--channels", type=int, default=128, help="channels per module (default 128)")
    p.add_argument("--sample-rate", type=float, default=200.0, metavar="HZ", help="default 200")
    p.add_argument("--chunk-s", type=float, default=0.1, help="chunk length (default 0.1 s)")
    p.add_argument("--duration", type=float, default=20.0, metavar="S",
                   help="seconds of data the source publishes flat out per run (default 20)")
    p.add_argument("--kind", default="table", help="conversion kind (default table)")
    p.add_argument("--keep", metavar="DIR", help="keep the recordings and parameters in DIR")
    add_zenoh_args(p)


def _analyse(rec_dir: Path, setup: str) -> dict:
    """Distinct power chunks, their samples, and each one's latency from its counts chunk's arrival.

    Flat out, the counts' ``t_pub_ns`` is the data clock, ahead of the wall clock: the latency is
    taken from when the recorder received the counts chunk (its log time) to the power's publication.
    """
    import msgpack

    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import PowerChunk

    session = Session(rec_dir)
    arrived = {}
    for m in session.iter_messages(f"mntes/{setup}/counts/**"):
        head = msgpack.unpackb(m.payload, raw=False)
        arrived[(head["board"], head["module"], head["seq"])] = m.log_time_ns
    lat_ms, seen = [], set()
    samples = power = 0
    t_last = None
    for m in session.iter_messages(f"mntes/{setup}/power/**"):
        pw = PowerChunk.from_bytes(m.payload)
        power += 1
        key = (pw.board, pw.module, pw.seq)
        if key in seen:
            continue
        seen.add(key)
        samples += pw.p_opt_w.size
        if key in arrived:
            lat_ms.append((pw.t_pub_ns - arrived[key]) / 1e6)
        t_last = pw.t_pub_ns if t_last is None else max(t_last, pw.t_pub_ns)
    return {"lat_ms": lat_ms, "unique": len(seen), "duplicates": power - len(seen), "samples": samples,
            "t_last_ns": t_last}


def _one(args, n_shards: int, work: Path, params_file: Path, sc) -> dict:
    from mntes_stream.errors import TransportError
    from mntes_stream.io import keys
    from mntes_stream.io.messages import StatusMessage
    from mntes_stream.io.transport import QueueSubscriber, ZenohSettings, free_tcp_port, open_session
    from mntes_stream.service.converter import ConverterConfig
    from mntes_stream.service.recorder import RecorderConfig
    from mntes_stream.service.router import RouterConfig
    from mntes_stream.service.supervise import Services

    setup = sc.setup
    port = free_tcp_port()
    base = zenoh_layer(args)
    router = base.over(ZenohSettings(mode="router", listen=(f"tcp/127.0.0.1:{port}",)))
    client = base.over(ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",)))
    rec_dir = work / f"recordings-{n_shards}"
    services = Services()
    names = []
    t_wall = time.monotonic()
    try:
        services.start("router", "router", RouterConfig(setup=setup, log_interval_s=3600, zenoh=router))
        for i in range(args.recorder_shards):
            shard = f"{i}/{args.recorder_shards}" if args.recorder_shards > 1 else ""
            services.start(f"recorder{i}", "recorder", RecorderConfig(
                setup=setup, directory=str(rec_dir), shard=shard, rotate_s=0, log_interval_s=3600, zenoh=client))
        for i in range(n_shards):
            cfg = ConverterConfig(setup=setup, params=str(params_file), kind=args.kind, provenance_interval_s=0,
                                  shard=f"{i}/{n_shards}" if n_shards > 1 else "",
                                  zenoh=client)
            names.append(cfg.name)
            services.start(cfg.name, "converter", cfg)
        # Flat out; the shards' status and claims settle for 1 s before the clock starts.
        src_cfg = {"source": sc, "params": str(params_file), "zenoh": client, "duration_s": args.duration,
                   "match_s": 120.0, "settle_s": 1.0, "label": "bench scale"}
        load_before = os.getloadavg()[0]
        services.start("source", BenchSource, src_cfg)
        n_chunks = math.ceil(args.duration * sc.sample_rate_hz / sc.chunk_samples - 1e-9) * sc.modules
        deadline = time.monotonic() + args.duration * 20 + 120
        with open_session(client) as z:
            sub = QueueSubscriber(z, [keys.status_key(setup, "*")])
            # Done when the shards together hold nothing and have received every chunk (or made no
            # progress for 6 s: then the loss shows in the figures).
            received: dict[str, int] = {}
            pending: dict[str, int] = {}
            last_change = time.monotonic()
            while time.monotonic() < deadline and services.alive():
                item = sub.get(timeout_s=0.5)
                if item is not None:
                    st = StatusMessage.from_bytes(item[1])
                    if received.get(st.service) != st.chunks_received:
                        last_change = time.monotonic()
                    received[st.service], pending[st.service] = st.chunks_received, st.chunks_pending
                total = sum(received.values())
                if total >= n_chunks and not any(pending.values()):
                    break
                if total and time.monotonic() - last_change > 6.0:
                    break
            sub.close()
        time.sleep(1.0)  # the last power on its way to the recorder
        ok = services.stop("source")
        for name in names:
            ok &= services.stop(name)
        for i in range(args.recorder_shards):
            ok &= services.stop(f"recorder{i}")
        ok &= services.stop("router")
    finally:
        for label in ("source", *names, *(f"recorder{i}" for i in range(args.recorder_shards)), "router"):
            services.stop(label, timeout_s=10)
    results, ok_all = services.collect()
    src = results.get("source", {})
    if not isinstance(src, dict) or "t_start_ns" not in src:
        raise TransportError(f"bench scale ({n_shards} shards): the source failed: {src}")
    a = _analyse(rec_dir, setup)
    span = (a["t_last_ns"] - src["t_start_ns"]) / 1e9 if a["t_last_ns"] else 0.0
    lat = a["lat_ms"]
    q = statistics.quantiles(lat, n=100, method="inclusive") if len(lat) >= 2 else [float("nan")] * 99

    def cpu(r):
        return round(r.get("process_cpu_s", 0.0) / r.get("process_wall_s", 1.0), 3) if isinstance(r, dict) else None

    return {
        "shards": n_shards,
        "msamples_per_s": round(a["samples"] / span / 1e6, 3) if span > 0 else 0.0,
        "latency_p50_ms": round(q[49], 1),
        "latency_p99_ms": round(q[98], 1),
        "chunks_sent": src["chunks_sent"],
        "chunks_recorded": a["unique"],
        "duplicates_recorded": a["duplicates"],
        "lost": src["chunks_sent"] - a["unique"],
        "source_wall_s": round((src["t_end_ns"] - src["t_start_ns"]) / 1e9, 2),
        "span_s": round(span, 2),
        "cpu_fraction": {k: cpu(v) for k, v in results.items()},
        "load_average_1min": [round(load_before, 2), round(os.getloadavg()[0], 2)],
        "run_wall_s": round(time.monotonic() - t_wall, 1),
        "all_services_ok": bool(ok and ok_all),
    }


def run(args) -> dict:
    from mntes_stream.errors import ConfigError
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.service.source import MinimalSource, SourceConfig

    try:
        counts = [int(x) for x in str(args.shards).split(",") if x.strip()]
    except ValueError:
        raise ConfigError(f"--shards {args.shards!r}: expected integers separated by commas, e.g. 1,2,4") from None
    if not counts or min(counts) < 1 or args.recorder_shards < 1:
        raise ConfigError("--shards and --recorder-shards take counts >= 1")
    n = max(1, round(args.chunk_s * args.sample_rate))
    sc = SourceConfig(setup="scale", boards=1, modules=args.modules, channels=args.channels,
                      sample_rate_hz=args.sample_rate, chunk_s=args.chunk_s, hk_interval_s=n / args.sample_rate,
                      cycle_s=1.0)
    tmp = None
    if args.keep:
        work = Path(args.keep)
        work.mkdir(parents=True, exist_ok=True)
    else:
        tmp = tempfile.TemporaryDirectory(prefix="mntes-bench-scale-")
        work = Path(tmp.name)
    params_file = work / "params.toml"
    dump_params(MinimalSource(sc).params, params_file)
    runs = [_one(args, k, work, params_file, sc) for k in counts]
    single = next((r["msamples_per_s"] for r in runs if r["shards"] == 1), None)
    for r in runs:
        r["scaling_efficiency"] = round(r["msamples_per_s"] / (r["shards"] * single), 3) if single else None
    best = max(r["msamples_per_s"] / r["shards"] for r in runs)
    per_shard = single or best
    sizing = {}
    for name, (det, rate) in ARRAYS.items():
        need = det * rate / 1e6
        sizing[name] = {"msamples_per_s": round(need, 3),
                        "shards_at_single_rate": max(1, math.ceil(need / per_shard)) if per_shard else None}
    out = {
        "array": {"modules": args.modules, "channels": args.channels, "sample_rate_hz": args.sample_rate,
                  "chunk_s": n / args.sample_rate, "offered_when_real_time_msamples_per_s":
                  round(args.modules * args.channels * args.sample_rate / 1e6, 4)},
        "mode": "flat-out",
        "duration_s": args.duration,
        "recorder_shards": args.recorder_shards,
        "kind": args.kind,
        "runs": runs,
        "single_shard_msamples_per_s": single,
        "sizing": sizing,
    }
    if tmp is not None:
        tmp.cleanup()
    return out
