"""The monitor's edges without a browser: real zenoh messages in, the real aiohttp server out.

Power, housekeeping, status and a malformed message go over a zenoh session on
127.0.0.1 to a :class:`MonitorSubscriber`; the page's server runs on a free
loopback port and is read with aiohttp's client (HTTP and the websocket
protocol the page speaks). ``mntes-stream monitor --text`` runs as a process.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import subprocess
import sys
import threading
import time

import numpy as np
import pytest

pytest.importorskip("aiohttp", reason="the monitor extra (aiohttp) is not installed")

import aiohttp  # noqa: E402

from mntes_stream.core import flags as fl
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.messages import HousekeepingChunk, PowerChunk, StatusMessage, detector_ids_for
from mntes_stream.io.transport import Publishers, free_tcp_port, loopback, open_session
from mntes_stream.monitor.aggregate import MonitorConfig
from mntes_stream.monitor.server import _parse_f_hwp, is_loopback, serve
from mntes_stream.monitor.subscriber import MonitorSubscriber

FS = 100.0
N = 20  # samples per chunk: 0.2 s


def chunk_bytes(module: int, seq: int, t0_ns: int) -> bytes:
    ch = np.arange(16, dtype=np.int32)
    k = seq * N + np.arange(N)
    p = 0.5e-12 + 1e-14 * np.sin(2 * np.pi * 1.54 * k / FS) * np.ones((16, 1))
    f = np.zeros((16, N), np.uint16)
    f[3] = fl.SATURATED
    p[3] = np.nan
    t = t0_ns + int(seq * N / FS * 1e9)
    return PowerChunk("lab", 0, module, ch, detector_ids_for(0, module, ch), seq, t, FS, p, f,
                      "tables-x", "table", t, time.time_ns()).to_bytes()


class Worker(threading.Thread):
    """A daemon thread that keeps what its target raised; :meth:`check` joins and re-raises it in the test."""

    def __init__(self, target, *args):
        super().__init__(target=target, args=args, daemon=True)
        self.error: BaseException | None = None

    def run(self) -> None:
        try:
            super().run()
        except BaseException as exc:
            self.error = exc

    def check(self, timeout_s: float = 10.0) -> None:
        self.join(timeout_s)
        assert not self.is_alive(), f"{self.name} did not stop within {timeout_s} s"
        if self.error is not None:
            raise self.error


def publish_stream(port: int, stop: threading.Event, modules=(0, 1)) -> None:
    """Power for two modules, housekeeping and a status, paced in real time; one malformed message."""
    with open_session(loopback(None, [port])) as z:
        pubs = Publishers(z)
        if not pubs.wait_matching([keys.power_key("lab", 0, 0)], 10, stop) and not stop.is_set():
            raise TimeoutError("the monitor never subscribed")
        pubs.put(keys.power_key("lab", 0, 9), b"\x93not a message")
        t0 = time.time_ns()
        seq = 0
        while not stop.is_set():
            for m in modules:
                pubs.put(keys.power_key("lab", 0, m), chunk_bytes(m, seq, t0))
            t = np.array([t0 + int(seq * N / FS * 1e9)])
            pubs.put(keys.hk_key("lab", "t_bath"), HousekeepingChunk("lab", "t_bath", seq, t, np.array([0.1]), "K").to_bytes())
            pubs.put(keys.hk_key("lab", "b_field"), HousekeepingChunk("lab", "b_field", seq, t, np.array([2e-6]), "T").to_bytes())
            pubs.put(keys.status_key("lab", "converter"), StatusMessage(
                "lab", "converter", time.time_ns(), 1.0, 0.2, chunks_received=2 * seq, rate_chunks_per_s=10.0).to_bytes())
            seq += 1
            stop.wait(max(t0 + seq * N / FS * 1e9 - time.time_ns(), 0) / 1e9)


@contextlib.contextmanager
def monitor_with_stream():
    zport = free_tcp_port()
    stop = threading.Event()
    info: dict = {}
    ready = threading.Event()
    with MonitorSubscriber("lab", loopback(zport), MonitorConfig(history_s=10.0)) as sub:
        server = Worker(serve, sub, "127.0.0.1", 0, 0.2, 60.0, lambda h, p: (info.update(port=p), ready.set()), stop)
        server.start()
        pub = Worker(publish_stream, zport, stop)
        pub.start()
        try:
            if not ready.wait(15):
                server.check(0.1)
                pytest.fail("server did not start")
            yield sub, f"http://127.0.0.1:{info['port']}"
        finally:
            stop.set()
            pub.check()
            server.check()


async def _until(fn, timeout_s=15.0):
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        result = await fn()
        if result:
            return result
        await asyncio.sleep(0.1)
    pytest.fail("condition not met in time")


def test_page_assets_state_and_websocket_protocol():
    async def scenario(base):
        async with aiohttp.ClientSession() as http:
            async with http.get(base + "/") as r:
                page = await r.text()
                assert r.status == 200 and "/static/plotly.min.js" in page and "/static/monitor.js" in page
            async with http.get(base + "/static/plotly.min.js") as r:
                js = await r.read()
                assert r.status == 200 and len(js) > 1_000_000 and b"plotly" in js[:2000].lower()
            async with http.get(base + "/static/../server.py") as r:
                assert r.status == 404

            async def state():
                async with http.get(base + "/api/state") as r:
                    s = await r.json()
                    return s if s.get("health", {}).get("monitor", {}).get("channels") == 32 and s["health"]["services"] else None

            s = await _until(state)
            assert [(row["board"], row["module"]) for row in s["layout"]] == [(0, 0), (0, 1)]
            assert s["codes"][3] == "1" and s["codes"][16 + 3] == "1"  # the saturated channel of each module
            assert s["state_counts"]["saturated"] == 2
            assert s["health"]["monitor"]["bad_messages"] == {"malformed": 1}
            assert s["health"]["hk"]["t_bath"]["value"] == 0.1

            async with http.ws_connect(base + "/ws") as ws:
                first = json.loads((await ws.receive(timeout=5)).data)
                assert first["type"] == "update" and first["layout"] and len(first["codes"]) == 32
                assert first["selection"] == ["b0m0c000", "b0m1c000", "b0m0c001"]  # default: in transition
                await ws.send_str(json.dumps({"type": "select", "channels": ["b0m1c005", "b0m0c003", "bogus"]}))
                await ws.send_str(json.dumps({"type": "f_hwp", "value": "auto"}))

                async def selected():
                    msg = json.loads((await ws.receive(timeout=5)).data)
                    ok = msg.get("selection") == ["b0m1c005", "b0m0c003"] and msg["spectrum"]["f_hwp_source"] != "configured"
                    return msg if ok else None

                msg = await _until(selected)
                assert "layout" not in msg  # sent once per layout change
                assert msg["unknown"] == ["bogus"]
                live, sat = msg["streams"]
                assert live["state"] == "transition" and len(live["t_ms"]) > 10
                assert max(live["p_pw"]) == pytest.approx(0.51, abs=1e-3)
                assert sat["state"] == "saturated" and all(v is None for v in sat["p_pw"])
                assert [c["id"] for c in msg["spectrum"]["channels"]] == ["b0m1c005"]  # no spectrum from NaN
                await ws.send_str(json.dumps({"type": "rendered", "newest_t_pub_ns": msg["newest_t_pub_ns"],
                                              "t_render_ns": time.time_ns()}))
                await ws.send_str("{not json")
                while True:
                    err = json.loads((await ws.receive(timeout=5)).data)
                    if err["type"] == "error":
                        break

            async def rendered():
                async with http.get(base + "/api/state") as r:
                    s = await r.json()
                    return s if s["health"]["page_latency_ms"]["n"] == 1 else None

            s = await _until(rendered)
            assert 0 < s["health"]["page_latency_ms"]["p50"] < 2000
            async with http.get(base + "/api/view", params=[("ch", "b0m0c001"), ("f_hwp", "1.02")]) as r:
                view = await r.json()
                assert view["spectrum"]["harmonics_hz"] == pytest.approx([1.02, 2.04, 4.08])
            for bad in ("-1", "abc", "nan"):
                async with http.get(base + "/api/view", params=[("ch", "b0m0c001"), ("f_hwp", bad)]) as r:
                    assert r.status == 400 and "f_HWP" in await r.text()
            async with http.ws_connect(base + "/ws") as ws:  # bad requests get an error reply, the connection stays
                for bad, why in (("[1, 2]", "JSON object"), ('{"type": "rendered"}', "newest_t_pub_ns"),
                                 ('{"type": "f_hwp", "value": "x"}', "f_HWP"), ('{"type": "select", "channels": 3}', "list"),
                                 ('{"type": "nope"}', "unknown message type")):
                    await ws.send_str(bad)
                    while (msg := json.loads((await ws.receive(timeout=5)).data))["type"] != "error":
                        pass
                    assert why in msg["message"], (bad, msg)
                assert json.loads((await ws.receive(timeout=5)).data)["type"] == "update"

    with monitor_with_stream() as (_, base):
        asyncio.run(scenario(base))


def test_text_mode_prints_a_bounded_live_table():
    zport = free_tcp_port()
    stop = threading.Event()
    proc = subprocess.Popen(
        [sys.executable, "-m", "mntes_stream", "monitor", "--text", "--duration", "4", "--update-s", "1",
         "--listen", f"tcp/127.0.0.1:{zport}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    pub = Worker(publish_stream, zport, stop)
    pub.start()
    try:
        out, err = proc.communicate(timeout=60)
    finally:
        stop.set()
        if proc.poll() is None:
            proc.kill()
            proc.wait(10)
    pub.check()
    assert proc.returncode == 0, err
    screens = [s for s in out.split("\n\n") if s.strip()]
    assert 3 <= len(screens) <= 6  # about one per second, and it stopped by itself
    last = screens[-1]
    assert "channels 32 in 2 modules  LIVE (newest data" in last
    assert "saturated 2" in last and "b0m0c003 saturated, b0m1c003 saturated" in last
    assert "t_bath 100.0000 mK" in last and "b_field 2.000 uT" in last
    row = next(line for line in last.splitlines() if line.startswith("monitor"))
    # chunks/s received in the last 1 s tick: 2 modules x 5 chunks/s offered; a loaded machine bunches
    # arrivals across ticks, so only the order of magnitude is checked (not samples/s, not per module)
    assert 3.0 <= float(row.split()[1]) <= 20.0, row


def test_bad_f_hwp_is_a_config_error():
    assert _parse_f_hwp("auto") is None and _parse_f_hwp(None) == "config" and _parse_f_hwp("0.5") == 0.5
    for bad in ("abc", "-1", "inf", "0", [1]):
        with pytest.raises(ConfigError, match="f_HWP"):
            _parse_f_hwp(bad)


def test_only_loopback_counts_as_loopback():
    assert is_loopback("127.0.0.1") and is_loopback("127.3.0.1") and is_loopback("::1") and is_loopback("localhost")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.5") and not is_loopback("example.org")


def test_monitor_shows_a_replayed_recording(tmp_path):
    """simulate -> MCAP -> offline convert -> ``mntes-stream replay --all`` -> the monitor holds the recorded power."""
    from mntes_stream.cli import main
    from mntes_stream.core.sim import ArraySimulator, SimConfig
    from mntes_stream.io.mcap import Session

    with contextlib.redirect_stdout(None):
        assert main(["simulate", "--out", str(tmp_path / "in.mcap"), "--duration", "4", "--modules", "1",
                     "--channels", "8", "--setup", "lab", "--no-truth", "--json"]) == 0
        assert main(["convert", str(tmp_path / "in.mcap"), str(tmp_path / "out.mcap"), "--params",
                     str(tmp_path / "in.params.toml"), "-q", "--json"]) == 0
    recorded = [PowerChunk.from_bytes(m.payload) for m in Session(tmp_path / "out.mcap").iter_messages("mntes/lab/power/**")]
    kinds = {ch.detector_id: ch.kind for ch in ArraySimulator(SimConfig(modules=1, channels=8)).channels}
    zport = free_tcp_port()
    with MonitorSubscriber("lab", loopback(zport), MonitorConfig(history_s=30.0)) as sub:
        replay = subprocess.run([sys.executable, "-m", "mntes_stream", "replay", str(tmp_path / "out.mcap"), "--all",
                                 "--speed", "4", "--wait-s", "2", "--connect", f"tcp/127.0.0.1:{zport}", "-q", "--json"],
                                capture_output=True, text=True, timeout=60)
        assert replay.returncode == 0, replay.stderr
        assert json.loads(replay.stdout)["by_kind"]["power"] == len(recorded)
        deadline = time.monotonic() + 10
        while sub.aggregator.power_chunks < len(recorded) and time.monotonic() < deadline:
            time.sleep(0.05)
        with sub.lock:
            agg = sub.aggregator
            buf = agg.modules[(0, 0)]
            tick = agg.tick(buf.last_recv_ns)
            t, p = buf.read(np.arange(8))
            states = {d: agg.state_of(d) for d in agg.detector_ids()}
            view = agg.view(["b0m0c000"])
    # Exactly the recorded samples, at their recorded times (float32 in the ring).
    np.testing.assert_array_equal(t, np.concatenate([c.times_ns() for c in recorded]))
    np.testing.assert_allclose(p, np.concatenate([c.p_opt_w for c in recorded], axis=1), rtol=1e-6, equal_nan=True)
    assert tick["health"]["monitor"]["lost_chunks"] == 0 and tick["health"]["monitor"]["bad_messages"] == {}
    # The simulated states: latched -> superconducting; the saturated channel (R ~ 0.997 R_n, loop gain
    # collapsed) is flagged SATURATED by the converter: "saturated"; the rest in transition.
    want = {"ok": "transition", "latched": "superconducting", "saturated": "saturated"}
    assert states == {d: want[k] for d, k in kinds.items()}
    # Recorded housekeeping and converter status are shown too.
    assert tick["hk"]["t_bath"]["value"] and tick["hk"]["b_field"]["value"]
    assert [s["service"] for s in tick["health"]["services"]] == ["converter"]
    assert view["streams"][0]["t_ms"][0] == pytest.approx(recorded[0].t0_ns / 1e6, abs=1)


def test_replayed_power_is_labelled_replay_with_the_recordings_latency():
    """Payloads as `mntes-stream replay` re-publishes them: published in 2023, arriving now, over real zenoh."""
    from mntes_stream.monitor.text import render_text

    t_rec = 1_700_000_000_000_000_000  # 2023-11-14 22:13:20 UTC
    zport = free_tcp_port()
    with MonitorSubscriber("lab", loopback(zport), MonitorConfig(stale_min_s=0.5)) as sub:
        with open_session(loopback(None, [zport])) as z:
            pubs = Publishers(z)
            assert pubs.wait_matching([keys.power_key("lab", 0, 0)], 10)
            for seq in range(20):
                t0 = t_rec + int(seq * N / FS * 1e9)
                ch = np.arange(4, dtype=np.int32)
                chunk = PowerChunk("lab", 0, 0, ch, detector_ids_for(0, 0, ch), seq, t0, FS, np.full((4, N), 5e-13),
                                   np.zeros((4, N), np.uint16), "tables-x", "table", t0, t0 + int(N / FS * 1e9) + 25_000_000)
                pubs.put(keys.power_key("lab", 0, 0), chunk.to_bytes())
                time.sleep(0.05)
        deadline = time.monotonic() + 10
        while sub.aggregator.power_chunks < 20 and time.monotonic() < deadline:
            time.sleep(0.05)
        with sub.lock:
            tick = sub.aggregator.tick(time.time_ns())
            text = render_text(sub.aggregator, tick)
        fr = tick["freshness"]
        assert fr["state"] == "replay" and fr["newest_t_ns"] == t_rec + int(20 * N / FS * 1e9) - int(1e9 / FS)
        # Latency on the recording's clock: last sample (t0 + 0.19 s) to publication (t0 + 0.2 s + 25 ms).
        assert tick["health"]["monitor"]["latency_p50_ms"] == pytest.approx(35.0, abs=0.01)
        assert "REPLAY: recorded 2023-11-14 22:13:" in text
        time.sleep(fr["threshold_s"] + 0.3)
        with sub.lock:
            assert sub.aggregator.tick(time.time_ns())["freshness"]["state"] == "stale"  # a replay that ended


def test_the_monitor_service_beats_while_it_serves_the_page():
    """The page is served from its own thread (``PageServer``): the service's steps return, so its heartbeat
    beats and its counters advance while the page answers; a stop ends it cleanly with its statistics."""
    from mntes_stream.monitor.service import MonitorService, MonitorServiceConfig

    zport = free_tcp_port()
    stop, ready, done = threading.Event(), threading.Event(), {}
    svc = MonitorService(MonitorServiceConfig(setup="lab", port=0, update_s=0.2, zenoh=loopback(zport),
                                              view=MonitorConfig(history_s=10.0)))
    server = Worker(lambda: done.update(svc.start(stop, ready)))  # as serve and up run it
    server.start()
    pub = Worker(publish_stream, zport, stop)
    pub.start()
    try:
        assert ready.wait(30), "the monitor never became ready"
        url = svc.status()["url"]

        async def page_answers():
            async with aiohttp.ClientSession() as http, http.get(url + "api/state") as r:
                return r.status == 200 and "health" in await r.json()

        seen = []
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and not (len(seen) > 2 and seen[-1]["power_chunks"] > seen[0]["power_chunks"]):
            time.sleep(1.0)
            assert asyncio.run(page_answers())
            seen.append(svc.status())
        assert all(s["state"] == "running" and s["since_beat_s"] < 2.0 for s in seen), seen
        assert seen[-1]["power_chunks"] > seen[0]["power_chunks"] > 0, seen
    finally:
        stop.set()
        pub.check()
        server.check(15)
    assert done["power_chunks"] >= seen[-1]["power_chunks"] and svc.status()["state"] != "running"
