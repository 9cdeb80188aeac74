"""The monitor shows each converter's ledger and says SHEDDING, LAGGING or REPLAY rather than a green LIVE.

Status messages as the converter publishes them (``ledger``, ``chunks_shed``,
``chunks_set_aside``, ``chunks_late``) and power go over a real zenoh session
on 127.0.0.1 to a :class:`MonitorSubscriber`; the page's server answers
``/api/state`` on a free loopback port; the terminal table is rendered from
the same tick.
"""

from __future__ import annotations

import json
import threading
import time
import urllib.request

import numpy as np
import pytest

pytest.importorskip("aiohttp", reason="the monitor extra (aiohttp) is not installed")


from mntes_stream.core.ledger import Ledger
from mntes_stream.io import keys
from mntes_stream.io.messages import PowerChunk, StatusMessage, detector_ids_for
from mntes_stream.io.transport import Publishers, free_tcp_port, loopback, open_session
from mntes_stream.monitor.aggregate import Aggregator, MonitorConfig
from mntes_stream.monitor.ledger_view import ledger_view
from mntes_stream.monitor.server import serve
from mntes_stream.monitor.subscriber import MonitorSubscriber
from mntes_stream.monitor.text import render_text

FS = 100.0
N = 20  # samples per chunk: 0.2 s


def _power(module: int, seq: int, t0_ns: int, t_recv_offset_ns: int = 0, late: bool | None = None) -> PowerChunk:
    ch = np.arange(4, dtype=np.int32)
    t = t0_ns + int(seq * N / FS * 1e9)
    return PowerChunk("lab", 0, module, ch, detector_ids_for(0, module, ch), seq, t, FS, np.full((4, N), 5e-13),
                      np.zeros((4, N), np.uint16), "tables-x", "table", t, t + int(N / FS * 1e9) + t_recv_offset_ns,
                      late=late)


def _ledger(shed: int, set_aside: int) -> Ledger:
    """A converter's ledger for two modules: module 1 had chunks shed (overload) and 3 never received."""
    led = Ledger("converted")
    led.received("0/0", 100)
    led.done("0/0", 100)
    led.received("0/1", 100 + set_aside)
    led.done("0/1", 100 - shed - 5)
    led.done("0/1", 5, late=True)
    if shed:
        led.shed("0/1", "overload", shed)
    led.set_missing("0/1", 3)
    return led


def _status(t_ns: int, shed: int, set_aside: int) -> bytes:
    led = _ledger(shed, set_aside)
    t = led.totals()
    return StatusMessage("lab", "converter", t_ns, 10.0, 0.2, chunks_received=t.received, chunks_converted=t.done,
                         chunks_lost=t.lost, chunks_shed=shed, chunks_late=5, chunks_set_aside=set_aside,
                         chunks_missing=3, chunks_pending=set_aside, ledger=led.as_dict(),
                         began_at={"0/1": 40},  # it started after 0/1's first 40 chunks left the history
                         conflicts={"0/0": 2}).to_bytes()  # and two sources send 0/0


def test_shedding_state_and_ledger_from_real_status_messages():
    zport = free_tcp_port()
    cfg = MonitorConfig(shedding_recent_s=1.5, stale_min_s=5.0)
    stop, ready, info = threading.Event(), threading.Event(), {}

    def state(sub):
        with urllib.request.urlopen(f"http://127.0.0.1:{info['port']}/api/state", timeout=5) as r:
            return json.loads(r.read())

    with MonitorSubscriber("lab", loopback(zport), cfg) as sub:
        server = threading.Thread(target=serve, args=(sub, "127.0.0.1", 0, 0.1, 60.0,
                                                      lambda h, p: (info.update(port=p), ready.set()), stop),
                                  daemon=True)
        server.start()
        try:
            assert ready.wait(15)
            with open_session(loopback(None, [zport])) as z:
                pubs = Publishers(z)
                assert pubs.wait_matching([keys.status_key("lab", "converter")], 10)
                t0 = time.time_ns()
                seq = 0

                def send(shed, set_aside, wait_s=0.6):
                    nonlocal seq
                    t_end = time.monotonic() + wait_s
                    while time.monotonic() < t_end:
                        pubs.put(keys.power_key("lab", 0, 0), _power(0, seq, t0).to_bytes())
                        seq += 1
                        pubs.put(keys.status_key("lab", "converter"), _status(time.time_ns(), shed, set_aside))
                        time.sleep(0.1)

                def until(pred, what, timeout_s=10.0):
                    deadline = time.monotonic() + timeout_s
                    while time.monotonic() < deadline:
                        s = state(sub)
                        if pred(s):
                            return s
                        time.sleep(0.1)
                    pytest.fail(f"{what}: {s['freshness']}")

                send(0, 0)
                s = until(lambda s: s["freshness"]["state"] == "live", "live before any shedding")
                # Chunks set aside, none shed yet: amber at once, with the count.
                send(0, 40)
                s = until(lambda s: s["freshness"]["state"] == "shedding" and s["freshness"]["shedding"]["set_aside"] == 40,
                          "set aside")
                assert s["freshness"]["shedding"] == {"services": ["converter"], "shed": 0, "set_aside": 40}
                # 12 shed, then nothing set aside any more: still SHEDDING for shedding_recent_s after the last growth.
                send(12, 0)
                s = until(lambda s: s["freshness"]["shedding"]["shed"] == 12, "shed 12")
                assert s["freshness"]["state"] == "shedding"
                svc = s["health"]["services"][0]
                assert (svc["chunks_shed"], svc["chunks_late"], svc["chunks_set_aside"], svc["shedding"]) == (12, 5, 0, True)
                with sub.lock:
                    tick = sub.aggregator.tick(time.time_ns())
                    text = render_text(sub.aggregator, tick)
                send(12, 0, wait_s=2.5)  # shed count steady for longer than shedding_recent_s (1.5 s)
                s = until(lambda s: s["freshness"]["state"] == "live", "live again after the shedding")
                assert s["health"]["services"][0]["chunks_shed"] == 12 and not s["health"]["services"][0]["shedding"]
        finally:
            stop.set()
            server.join(15)
    assert not server.is_alive()

    # The ledger, per stream and in total, as the page and /api/state carry it: module 1 first (it lost chunks).
    led = svc["ledger"]
    assert [r["stream"] for r in led["streams"]] == ["0/1", "0/0"]
    m1 = led["streams"][0]
    assert {k: m1[k] for k in ("received", "converted", "late", "shed", "rejected", "duplicate", "never_received",
                               "lost", "pending")} == {"received": 100, "converted": 83, "late": 5, "shed": 12,
                                                       "rejected": 0, "duplicate": 0, "never_received": 3,
                                                       "lost": 15, "pending": 0}
    assert m1["shed_by"] == {"overload": 12}
    assert led["totals"]["lost"] == 15 and led["totals"]["converted"] == 183 and svc["chunks_lost"] == 15
    assert led["line"] == ("received 200 chunks: converted 183, late 5, shed 12 (overload 12); never received 3; "
                           "lost 15 of 203")
    # The terminal table: the badge in words, the shed and late columns, the ledger's line and its streams.
    assert "SHEDDING: converter shed 12 chunks, 0 set aside" in text
    assert "ledger converter: received 200 chunks: converted 183, late 5, shed 12 (overload 12)" in text
    began = ("began 0/1 at seq 40 (no checkpoint): what came before never reached this converter; a recording of the "
             "counts has them, and offline convert gives their power")
    assert led["began_line"] == began and f"\n  {began}\n" in text
    conflict = ("CONFLICT: streams sent by more than one publisher side by side (0/0 by 2): each one's chunks are "
                "numbered apart; two sources or bridges on one setup?")
    assert led["conflict_line"] == conflict and f"\n  {conflict}\n" in text
    row = next(line for line in text.splitlines() if line.strip().startswith("0/1 "))
    assert row.split() == ["0/1", "83", "5", "12", "0", "0", "3", "15", "0"]
    conv = next(line for line in text.splitlines() if line.startswith("converter "))
    assert conv.split()[7:10] == ["15", "12", "5"] and conv.rstrip().endswith("SHEDDING")


T0 = 1_700_000_000_000_000_000


def test_power_177_s_behind_its_samples_is_lagging_not_live_and_late_power_is_not_a_lag():
    """Issue 24: a recording replayed through a converter arrived 177 s after its samples with a green LIVE."""
    agg = Aggregator(MonitorConfig())
    lag_ns = 177 * 10**9
    for seq in range(10):  # published fresh (t_pub ~ arrival) but the samples are 177 s old
        c = _power(0, seq, T0)
        t_recv = int(c.times_ns()[-1]) + lag_ns
        agg.add_power(PowerChunk(**{**_fields(c), "t_pub_ns": t_recv - 1_000_000}), t_recv)
    tick = agg.tick(t_recv + 10_000_000)
    fr = tick["freshness"]
    assert fr["state"] == "lagging" and fr["lag_s"] == pytest.approx(177.0, abs=0.01) and not fr["replay"]
    assert "LAGGING: data 177.0 s old on arrival (> 30 s" in render_text(agg, tick)

    live = Aggregator(MonitorConfig())
    for seq in range(10):
        c = _power(0, seq, T0)
        live.add_power(c, int(c.times_ns()[-1]) + 50_000_000)
    t_last = int(c.times_ns()[-1]) + 50_000_000
    # Late power (set aside under overload, converted minutes later) is drawn nowhere new and is no lag.
    old = _power(0, 3, T0, late=True)
    live.add_power(old, t_last + 1_000_000)
    tick = live.tick(t_last + 2_000_000)
    assert tick["freshness"]["state"] == "live" and tick["freshness"]["lag_s"] == pytest.approx(0.05, abs=0.001)
    assert tick["health"]["monitor"]["late_power_chunks"] == 1


def _fields(c: PowerChunk) -> dict:
    import dataclasses

    return {f.name: getattr(c, f.name) for f in dataclasses.fields(c) if f.init}


def test_ledger_view_is_bounded_lossy_first_and_survives_odd_columns():
    led = Ledger("converted")
    for m in range(40):
        led.received(f"0/{m}", 10)
        led.done(f"0/{m}", 10 if m != 33 else 8)
        if m == 33:
            led.rejected(f"0/{m}", "malformed", 2)
    d = led.as_dict()
    d["9/9"] = {"received": "x"}  # not a count: the stream is counted unreadable, the rest shown
    view = ledger_view(d, max_streams=5)
    assert [r["stream"] for r in view["streams"]] == ["0/33", "0/0", "0/1", "0/2", "0/3"]
    assert view["streams_total"] == 40 and view["unreadable"] == 1
    assert view["totals"]["rejected"] == 2 and view["totals"]["lost"] == 2 and view["totals"]["converted"] == 398
    assert ledger_view({}, 5) is None
