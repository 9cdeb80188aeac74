"""What the Foxglove bridge and the Prometheus metrics cost at full focal-plane rate (part of ``bench monitor``).

Figures are fractions of one core (CPU seconds of this process, all its threads, so a busy
machine slows them less than wall time would) per second of stream, on the power stream of
``bench monitor`` (``--modules`` 128-channel modules at ``--rate-hz`` in
``--chunk-s`` chunks; default 5,120 channels):

- ``metrics``: :class:`~mntes_stream.service.metrics.ServiceMetrics` of a
  converter observing every power chunk it publishes and a status a second,
  plus one scrape (``generate_latest``, the text Prometheus reads) every 5 s;
- ``foxglove_in_process``: the bridge's own work on every power chunk
  (decode, choose detectors, decimate, make json, log it to a foxglove-sdk
  channel that has a sink: an MCAP file, so nothing is skipped);
- ``foxglove_live`` (``--foxglove-live``): ``mntes-stream foxglove`` in a process
  of its own, fed over zenoh in real time by a publisher process, with a
  plain WebSocket client subscribed to every channel it advertises; its
  process CPU time over the run (zenoh receive included).
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path


def add_arguments(p) -> None:
    p.add_argument("--foxglove-live", action="store_true",
                   help="also run mntes-stream foxglove live (publisher process + WebSocket client) and measure its CPU")
    p.add_argument("--per-module", type=int, default=4, help="foxglove: detectors per module served (default 4)")
    p.add_argument("--max-rate-hz", type=float, default=50.0, help="foxglove: samples per second and module (default 50)")


def _status(n_modules: int, t_ns: int):
    from mntes_stream.core import flags as fl
    from mntes_stream.io.messages import StatusMessage

    n = n_modules * 128
    return StatusMessage("bench", "converter", t_ns, 10.0, 1.0, chunks_received=10 * n_modules,
                         chunks_converted=10 * n_modules, samples_converted=153 * n,
                         flag_counts={name: 15 for name in fl.NAMES.values()}, hk_age_s={"t_bath": 0.1, "b_field": 0.1},
                         bad_messages={"invalid": 1}, rate_msamples_per_s=153 * n / 1e6,
                         latency_p50_ms=12.0, latency_p99_ms=30.0, latency_max_ms=40.0).to_bytes()


def metrics_cost(batches, seconds: float, n_modules: int) -> dict:
    """Core fraction of a converter's metrics: observe every publication, scrape every 5 s."""
    from mntes_stream.io import keys
    from mntes_stream.service.converter import ConverterConfig, ConverterService
    from mntes_stream.service.metrics import ServiceMetrics, require_metrics

    require_metrics()  # a one-line error naming the extra, not an ImportError
    from prometheus_client import generate_latest

    svc = ConverterService(ConverterConfig(params="unused.toml"))  # never run: its heartbeat is what a scrape reads
    metrics = ServiceMetrics(svc)
    busy, scrapes, size = 0.0, [], 0
    t_data = 0.0
    next_status, next_scrape = 0.0, 5.0
    for t_data, batch in batches:
        t0 = time.process_time()
        for m, payload in batch:
            metrics.observe(keys.power_key("bench", 0, m), payload)
        if t_data >= next_status:
            metrics.observe(keys.status_key("bench", "converter"), _status(n_modules, time.time_ns()))
            next_status += 1.0
        busy += time.process_time() - t0
        if t_data >= next_scrape:
            t0 = time.process_time()
            text = generate_latest(metrics.registry)
            scrapes.append(time.process_time() - t0)
            size = len(text)
            next_scrape += 5.0
    total = busy + sum(scrapes)
    return {"core_fraction": round(total / seconds, 5),
            "observe_us_per_chunk": round(busy / max(1, int(seconds / 0.1) * n_modules) * 1e6, 2),
            "scrape_ms": round(1e3 * sorted(scrapes)[len(scrapes) // 2], 2) if scrapes else None,
            "scrape_kb": round(size / 1e3, 1)}


def foxglove_cost(batches, seconds: float, per_module: int, max_rate_hz: float) -> dict:
    """Core fraction of the bridge's work on every power chunk, logged to a foxglove channel with a sink."""
    from mntes_stream.foxglove.translate import FoxgloveView
    from mntes_stream.io.messages import decode
    from mntes_stream.service.foxglove import ChannelBridge, require_foxglove

    fg = require_foxglove()
    with tempfile.TemporaryDirectory() as tmp:
        context = fg.Context()
        sink = fg.open_mcap(str(Path(tmp) / "bridge.mcap"), context=context)
        bridge = ChannelBridge(fg, context, FoxgloveView((), per_module, max_rate_hz))
        busy = 0.0
        try:
            for _, batch in batches:
                t0 = time.process_time()
                for _, payload in batch:
                    bridge.handle(decode(payload))
                busy += time.process_time() - t0
        finally:
            sink.close()
    return {"core_fraction": round(busy / seconds, 4), "json_messages_per_s": round(bridge.logged / seconds, 1),
            "channels": len(bridge.channels), "per_module": per_module, "max_rate_hz": max_rate_hz}


def foxglove_live(args) -> dict:
    """``mntes-stream foxglove`` as a process: its CPU time while serving a subscribed WebSocket client."""
    import multiprocessing as mp

    import websocket

    from mntes_stream.bench._power_stream import cpu_s, first_line, publish_power
    from mntes_stream.errors import TransportError
    from mntes_stream.io.transport import free_tcp_port

    zport = free_tcp_port()
    warmup_s = 5.0
    pub = mp.get_context("spawn").Process(target=publish_power, args=(zport, args.modules, args.rate_hz, args.chunk_s,
                                                                  args.seconds + warmup_s + 10), daemon=True)
    fox = subprocess.Popen([sys.executable, "-m", "mntes_stream", "foxglove", "--setup", "bench", "--port", "0",
                            "--per-module", str(args.per_module), "--max-rate-hz", str(args.max_rate_hz),
                            "--connect", f"tcp/127.0.0.1:{zport}"], stdout=subprocess.PIPE, text=True)
    frames = [0]
    stop = threading.Event()
    ws = None
    try:
        line = first_line(fox, 60.0)
        if "serving ws://" not in line:
            raise TransportError(f"mntes-stream foxglove did not start (first output line: {line!r})")
        url = line.split("serving ", 1)[1].split()[0]
        ws = websocket.create_connection(url, timeout=10, subprotocols=["foxglove.websocket.v1", "foxglove.sdk.v1"])

        def client():
            subscribed, next_id = set(), 1
            while not stop.is_set():
                try:
                    op, data = ws.recv_data()
                except Exception:  # closed at the end, or a timeout while nothing flows
                    if stop.is_set():
                        return
                    continue
                if op == websocket.ABNF.OPCODE_BINARY:
                    frames[0] += 1
                elif op == websocket.ABNF.OPCODE_TEXT:
                    msg = json.loads(data)
                    if msg.get("op") == "advertise":
                        subs = []
                        for ch in msg["channels"]:
                            if ch["id"] not in subscribed:
                                subscribed.add(ch["id"])
                                subs.append({"id": next_id, "channelId": ch["id"]})
                                next_id += 1
                        if subs:
                            ws.send(json.dumps({"op": "subscribe", "subscriptions": subs}))

        reader = threading.Thread(target=client, daemon=True)
        reader.start()
        pub.start()
        time.sleep(warmup_s)
        f0, cpu0, t0 = frames[0], cpu_s(fox.pid), time.monotonic()
        time.sleep(args.seconds)
        f1, cpu1, t1 = frames[0], cpu_s(fox.pid), time.monotonic()
    finally:
        stop.set()
        if ws is not None:
            ws.close()
        fox.terminate()
        fox.wait(20)
        if pub.pid is not None:
            pub.terminate()
            pub.join(10)
    return {"process_cpu_core_fraction": round((cpu1 - cpu0) / (t1 - t0), 3),
            "frames_received_per_s": round((f1 - f0) / (t1 - t0), 1),
            "per_module": args.per_module, "max_rate_hz": args.max_rate_hz}


def run(args, chunks) -> dict:
    """The figures above; ``chunks(modules, n_samp, rate_hz, n_chunks, t0_ns)`` makes the power stream."""
    n_samp = max(1, int(round(args.rate_hz * args.chunk_s)))
    n_chunks = int(round(args.seconds / args.chunk_s))

    def batches():
        t0_ns = time.time_ns()
        for k, batch in chunks(args.modules, n_samp, args.rate_hz, n_chunks, t0_ns):
            yield k * args.chunk_s, batch

    from mntes_stream.errors import MissingExtraError

    def part(fn, *a):
        try:
            return fn(*a)
        except MissingExtraError as exc:  # the monitor's own figures still count: say what is missing
            return f"skipped: {exc}"

    # Made as they are consumed (the whole stream would be ~150 MB); making them is outside the timed parts.
    out = {"metrics": part(metrics_cost, batches(), args.seconds, args.modules),
           "foxglove_in_process": part(foxglove_cost, batches(), args.seconds, args.per_module, args.max_rate_hz)}
    if args.foxglove_live:
        out["foxglove_live"] = part(foxglove_live, args)
    return out
