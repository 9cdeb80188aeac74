"""``mntes-stream bench monitor``: can the quick-look monitor keep up with a full focal plane?

Two parts, both on ``--modules`` 128-channel modules (default 40 = 5120 channels)
at ``--rate-hz`` in ``--chunk-s`` chunks:

- in process (no I/O): decoding and aggregating the power stream, as a
  fraction of one core per second of data; the cost of one tick (channel
  states, housekeeping, health) and of one page's view (time streams and
  spectra of the selected channels); the size of one page update;
- ``--browser``: the real thing on loopback: a publisher process puts the
  power stream on zenoh in real time, ``mntes-stream monitor`` serves it and
  headless Chromium draws it; reported are the page's update rate, the
  publication-to-drawn latency it measures, and the monitor's CPU use;
- ``integrations``: the cost of the Foxglove bridge and of the Prometheus
  metrics on the same stream (``bench/_integrations.py``; ``--foxglove-live``
  runs the bridge as a process with a WebSocket client).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import numpy as np

from mntes_stream.bench import _integrations
from mntes_stream.bench._power_stream import cpu_s, first_line, power_chunks, publish_power
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ

HELP = "quick-look monitor: aggregation cost and page latency for a full focal plane"


def add_arguments(p) -> None:
    p.add_argument("--modules", type=int, default=40, help="128-channel modules (default 40 = 5120 channels)")
    p.add_argument("--rate-hz", type=float, default=DFMUX_SAMPLE_RATE_HZ, help="sample rate (Hz; default the DfMux rate)")
    p.add_argument("--chunk-s", type=float, default=0.1, help="chunk length (s; default 0.1)")
    p.add_argument("--seconds", type=float, default=20.0, help="stream time")
    p.add_argument("--selected", type=int, default=4, help="channels plotted by the page")
    p.add_argument("--browser", action="store_true", help="also run publisher + monitor + headless Chromium live")
    _integrations.add_arguments(p)  # the Foxglove bridge and the metrics: what they cost (issue 16)


def _in_process(args) -> dict:
    from mntes_stream.io import keys
    from mntes_stream.io.transport import ZenohSettings
    from mntes_stream.monitor.aggregate import MonitorConfig
    from mntes_stream.monitor.subscriber import MonitorSubscriber

    n_samp = max(1, int(round(args.rate_hz * args.chunk_s)))
    n_chunks = int(round(args.seconds / args.chunk_s))
    sub = MonitorSubscriber("bench", ZenohSettings(), MonitorConfig())  # not started: no session, handle() only
    t_ns = time.time_ns()
    busy = 0.0
    ticks, views, sizes = [], [], []
    for k, batch in power_chunks(args.modules, n_samp, args.rate_hz, n_chunks, t_ns):
        now = t_ns + int(k * args.chunk_s * 1e9)
        t0 = time.perf_counter()
        for m, payload in batch:
            sub.handle(keys.power_key("bench", 0, m), payload, now)
        busy += time.perf_counter() - t0
        if k % max(1, int(round(0.5 / args.chunk_s))) == 0:  # the page's default 0.5 s period
            t0 = time.perf_counter()
            tick = sub.aggregator.tick(now)
            ticks.append(time.perf_counter() - t0)
            sel = sub.aggregator.default_selection(args.selected)
            t0 = time.perf_counter()
            view = sub.aggregator.view(sel)
            views.append(time.perf_counter() - t0)
            sizes.append(len(json.dumps({**tick, **view}, separators=(",", ":"))))
    late = len(ticks) // 2  # once the 30 s history has filled as far as it will
    return {
        "ingest_core_fraction": round(busy / args.seconds, 4),
        "tick_ms_median": round(float(np.median(ticks[late:])) * 1e3, 2),
        "view_ms_median": round(float(np.median(views[late:])) * 1e3, 2),
        "update_kb_median": round(float(np.median(sizes[late:])) / 1e3, 1),
    }


def _browser(args) -> dict:
    import multiprocessing as mp
    import urllib.request

    from mntes_stream.errors import TransportError
    from mntes_stream.io.transport import free_tcp_port
    from mntes_stream.monitor.browser import headless_chromium, page_state

    zport = free_tcp_port()
    warmup_s = 8.0
    pub = mp.get_context("spawn").Process(target=publish_power, args=(zport, args.modules, args.rate_hz, args.chunk_s,
                                                                  args.seconds + warmup_s + 5), daemon=True)
    mon = subprocess.Popen([sys.executable, "-m", "mntes_stream", "monitor", "--setup", "bench", "--port", "0",
                            "--connect", f"tcp/127.0.0.1:{zport}"], stdout=subprocess.PIPE, text=True)
    driver = None
    try:
        line = first_line(mon, 60.0)
        if "serving " not in line:
            raise TransportError(f"mntes-stream monitor did not start (first output line: {line!r})")
        url = line.split("serving ", 1)[1].split()[0]
        pub.start()
        driver = headless_chromium()
        driver.get(url)
        time.sleep(warmup_s)  # history fills, the page settles
        s0, cpu0, t0 = page_state(driver), cpu_s(mon.pid), time.monotonic()
        time.sleep(args.seconds)
        s1, cpu1, t1 = page_state(driver), cpu_s(mon.pid), time.monotonic()
        with urllib.request.urlopen(url + "api/state", timeout=10) as r:
            state = json.loads(r.read())
    finally:
        if driver is not None:
            driver.quit()
        mon.terminate()
        mon.wait(20)
        if pub.pid is not None:  # started
            pub.terminate()
            pub.join(10)
    t_first = s0["renders"][-1]["t_render_ms"] if s0["renders"] else 0
    lat = np.array([r["latency_ms"] for r in s1["renders"] if r["t_render_ms"] > t_first])
    return {
        "page_updates_per_s": round((s1["updates"] - s0["updates"]) / (t1 - t0), 2),
        "page_latency_ms_median": round(float(np.median(lat)), 1) if lat.size else None,
        "page_latency_ms_p95": round(float(np.percentile(lat, 95)), 1) if lat.size else None,
        "page_latency_ms_max": round(float(lat.max()), 1) if lat.size else None,
        "monitor_cpu_core_fraction": round((cpu1 - cpu0) / (t1 - t0), 3),
        "monitor_dropped": state["health"]["monitor"]["dropped"],
        "monitor_lost_chunks": state["health"]["monitor"]["lost_chunks"],
        "channels_on_page": len(s1["grid"]),
        "page_errors": s1["errors"],
    }


def run(args) -> dict:
    out = {
        "channels": args.modules * 128,
        "sample_rate_hz": args.rate_hz,
        "chunk_s": args.chunk_s,
        "stream_seconds": args.seconds,
        "selected": args.selected,
        **_in_process(args),
    }
    if args.browser:
        out["browser"] = _browser(args)
    out["integrations"] = _integrations.run(args, power_chunks)
    return out
