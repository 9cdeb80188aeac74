"""A paced power stream on zenoh and the child-process probes, shared by ``bench monitor`` and its integrations.

Private (every public module of ``bench/`` is a benchmark); its own module so
that ``bench/monitor.py`` and ``bench/_integrations.py`` both import it
rather than each other (tests/test_layering.py).
"""

from __future__ import annotations

import os
import time

import numpy as np

__all__ = ["cpu_s", "first_line", "power_chunks", "publish_power", "restamp"]


def power_chunks(modules: int, n_samp: int, rate_hz: float, n_chunks: int, t0_ns: int, setup: str = "bench"):
    """Encoded power chunks, chunk-major: a 2f line, white noise, one saturated channel per module."""
    from mntes_stream.core import flags as fl
    from mntes_stream.io.messages import PowerChunk, detector_ids_for

    rng = np.random.default_rng(0)
    ch = np.arange(128, dtype=np.int32)
    for k in range(n_chunks):
        t = (k * n_samp + np.arange(n_samp)) / rate_hz
        out = []
        for m in range(modules):
            p = 0.5e-12 + 1e-14 * np.sin(2 * np.pi * 1.54 * t) + 1e-16 * rng.standard_normal((128, n_samp))
            f = np.zeros((128, n_samp), np.uint16)
            f[7] = fl.SATURATED
            p[7] = np.nan
            t0 = t0_ns + int(round(k * n_samp / rate_hz * 1e9))
            out.append((m, PowerChunk(setup, 0, m, ch, detector_ids_for(0, m, ch), k, t0, rate_hz, p, f,
                                      "bench", "table", t0, t0).to_bytes()))
        yield k, out


def publish_power(port: int, modules: int, rate_hz: float, chunk_s: float, seconds: float) -> None:
    """Publisher process: the power stream on zenoh, paced in real time."""
    from mntes_stream.io import keys
    from mntes_stream.io.transport import Publishers, loopback, open_session

    n_samp = max(1, int(round(rate_hz * chunk_s)))
    n_chunks = int(round(seconds / chunk_s))
    with open_session(loopback(port)) as z:
        pubs = Publishers(z)
        pubs.wait_matching([keys.power_key("bench", 0, 0)], 30)
        t0 = time.time_ns()
        gen = power_chunks(modules, n_samp, rate_hz, n_chunks, t0)
        for k, batch in gen:
            due = t0 + int(round((k + 1) * n_samp / rate_hz * 1e9))  # a chunk goes out once its last sample is taken
            time.sleep(max(due - time.time_ns(), 0) / 1e9)
            for m, payload in batch:
                # Stamp publication now: PowerChunk.t_pub_ns is what the page's latency counts from.
                pubs.put(keys.power_key("bench", 0, m), restamp(payload))


def restamp(payload: bytes) -> bytes:
    from mntes_stream.io.messages import PowerChunk

    c = PowerChunk.from_bytes(payload)
    object.__setattr__(c, "t_pub_ns", time.time_ns())
    return c.to_bytes()


def cpu_s(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        fields = f.read().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def first_line(proc, timeout_s: float) -> str:
    """The child's first stdout line, or "" after ``timeout_s`` (readline alone would wait forever)."""
    import queue
    import threading

    lines: queue.Queue = queue.Queue()
    threading.Thread(target=lambda: lines.put(proc.stdout.readline()), daemon=True).start()
    try:
        return lines.get(timeout=timeout_s)
    except queue.Empty:
        return ""
