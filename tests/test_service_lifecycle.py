"""The Service lifecycle (service/base.py): hooks only, stop/ready/duration/presence run by the base.

Real zenoh sessions on 127.0.0.1, real MCAP files; each test stops by itself within seconds.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

import pytest
from mcap_helpers import counts_payload

from mntes_stream.core.settings import Settings, setting
from mntes_stream.io import mcap as mio
from mntes_stream.io.presence import list_services
from mntes_stream.io.transport import free_tcp_port, loopback, open_session
from mntes_stream.service.base import Service
from mntes_stream.service.replay import ReplayConfig, ReplayService

T0 = 1_700_000_000_000_000_000


def _recording(path, n: int, spacing_ns: int):
    with mio.McapFileWriter(path) as w:
        for i in range(n):
            w.write("mntes/lc/counts/0/0", counts_payload(i), T0 + i * spacing_ns)
    return path


def test_replay_is_ready_when_it_publishes_and_is_seen_without_a_context(tmp_path):
    port = free_tcp_port()
    rec = _recording(tmp_path / "r.mcap", 16, int(0.25e9))  # 3.75 s of messages at speed 1
    cfg = ReplayConfig(source=(str(rec),), speed=1.0, wait_subscribers_s=1.0, linger_s=0.0,
                       zenoh=loopback(port))
    svc = ReplayService(cfg)
    stop, ready, out = threading.Event(), threading.Event(), {}
    t = threading.Thread(target=lambda: out.update(svc.start(stop, ready)), daemon=True)
    t0 = time.monotonic()
    t.start()
    try:
        # It waits up to 1 s for a subscriber before its first message: not ready meanwhile.
        assert not ready.wait(0.6), "replay said ready before publishing anything"
        assert ready.wait(5.0)
        assert time.monotonic() - t0 >= 0.9
        assert svc.status()["state"] == "running"
        # Presence is passed to the session explicitly (no ContextVar set in this thread or its).
        with open_session(loopback(None, [port])) as z:
            deadline, alive = time.monotonic() + 3.0, []
            while not alive and time.monotonic() < deadline:  # the peer link takes a moment
                alive = [s for s in list_services(z, "lab", timeout_s=1.0) if s["service"] == "replay"]
        assert alive and alive[0]["state"] == "running", alive
    finally:
        stop.set()
        t.join(10)
    assert not t.is_alive()
    assert svc.status()["state"] == "stopped"
    assert 1 <= out["messages"] < 16  # stopped part-way, by the caller's stop


def test_replay_with_nothing_selected_is_never_ready(tmp_path):
    rec = _recording(tmp_path / "r.mcap", 3, 1000)
    cfg = ReplayConfig(source=(str(rec),), topics=("nothing/**",), speed=0, wait_subscribers_s=0, linger_s=0,
                       zenoh=loopback(free_tcp_port()))
    ready = threading.Event()
    out = ReplayService(cfg).start(None, ready)
    assert out["messages"] == 0 and not ready.is_set()


@dataclass(frozen=True)
class TickConfig(Settings):
    duration_s: float = setting(0.3, "run this long", unit="s", ge=0)


class Ticker(Service):
    """A service of hooks only, no zenoh: counts steps until its duration ends."""

    name = "ticker"
    Config = TickConfig

    def zenoh_settings(self):
        return None

    def setup(self, ctx):
        self.calls = ["setup"]
        self.ticks = 0

    def step(self, ctx):
        self.ticks += 1
        time.sleep(0.01)
        return True

    def counters(self):
        return {"ticks": getattr(self, "ticks", 0)}

    def finish(self, ctx):
        self.calls.append("finish")
        return {"ticks": self.ticks}


@pytest.mark.parametrize("duration_s", [0.3, 0.6])
def test_duration_ends_a_hook_service_and_finish_runs(duration_s):
    svc = Ticker(TickConfig(duration_s=duration_s))
    ready = threading.Event()
    t0 = time.monotonic()
    out = svc.start(None, ready)
    took = time.monotonic() - t0
    assert ready.is_set() and svc.calls == ["setup", "finish"]
    assert duration_s <= took < duration_s + 1.0
    assert out["ticks"] >= 5 and svc.status()["ticks"] == out["ticks"] and svc.status()["state"] == "stopped"


def test_stop_ends_a_hook_service_before_its_duration():
    svc = Ticker(TickConfig(duration_s=30.0))
    stop = threading.Event()
    threading.Timer(0.2, stop.set).start()
    t0 = time.monotonic()
    svc.start(stop, None)
    assert time.monotonic() - t0 < 2.0 and svc.calls == ["setup", "finish"]


@pytest.mark.parametrize("method", ["run", "start"])
def test_a_service_overriding_the_lifecycle_is_refused_when_defined(method):
    # The skeleton is the base's: a class running its own would get no presence, router waiting or metrics.
    with pytest.raises(TypeError, match=f"overrides Service.{method}"):
        type("OwnSkeleton", (Ticker,), {method: lambda self, stop=None, ready=None: {}})


def test_a_client_outside_a_service_fails_at_once_without_its_router():
    # No policy passed, none picked up from the context: one TransportError line, no waiting.
    from mntes_stream.errors import TransportError
    from mntes_stream.io.transport import ZenohSettings

    t0 = time.monotonic()
    with pytest.raises(TransportError, match="cannot open zenoh session"):
        open_session(ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{free_tcp_port()}",)))
    assert time.monotonic() - t0 < 5.0
