"""The ``ocs-bridge`` service: housekeeping from OCS feeds (a crossbar WAMP router) on zenoh.

An OCS agent (a Lakeshore 372/240, the fake-data agent) publishes each feed
on the WAMP topic of its address (``observatory.LS372.feeds.temperatures``):
``(data, feed)``, ``data`` holding blocks of ``timestamps`` and fields. The
bridge is a WAMP client of the router (autobahn, the library OCS itself
uses; optional extra ``ocs``): it subscribes to the feed of every field its
config names (``t_bath_field``, ``b_field_field``) and publishes each
publication's readings of a field as one
:class:`~mntes_stream.io.messages.HousekeepingChunk` of its sensor, in SI
units, stamped with the readings' own times, exactly as the simulator
publishes housekeeping. So the converter's staleness rules apply unchanged:
a sample whose nearest reading is older than ``hk_staleness_s`` is
HK_STALE, one without any reading HK_MISSING. The bridge itself says when a
sensor's newest reading is older than ``stale_s`` (a warning once per
episode, ``stale`` in its heartbeat), and never makes a reading up.

Readings not after the last one published of their sensor (a feed that
repeats itself, a clock step back) are counted (``out_of_order``) and
skipped; values that are not numbers are published as NaN (failed readings,
which the converter counts) and counted as ``bad``. A router that goes away
is dialled again, backing off up to ``reconnect_max_s``; nothing stops the
service but ``duration_s`` or a stop.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from dataclasses import dataclass

import numpy as np

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError
from mntes_stream.g3.ocs_hk import OcsFields
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["OcsBridgeConfig", "OcsBridgeService", "OcsBridgeSettings"]

log = logging.getLogger("mntes_stream.ocs.bridge")
_WS_URL = re.compile(r"wss?://\S+")


@dataclass(frozen=True)
class OcsBridgeSettings(Settings):
    """The router, the fields and how they go out (the ``[ocs-bridge]`` table)."""

    router: str = setting("ws://127.0.0.1:8001/ws", "the crossbar router's WAMP websocket URL (OCS site config: "
                          "hub.wamp_server)", pattern=_WS_URL)
    realm: str = setting("test_realm", "the WAMP realm (hub.wamp_realm)")
    setup: str = setting(keys.DEFAULT_SETUP, "keys mntes/<setup>/...", pattern=NAME_PATTERN)
    t_bath_field: str = setting("", "bath temperature, e.g. observatory.LS372.feeds.temperatures.Channel_06_T "
                                "('': none)")
    t_bath_unit: str = setting("K", "unit of the t_bath field", choices=("K", "mK"))
    b_field_field: str = setting("", "magnetic field at the array ('': none)")
    b_field_unit: str = setting("T", "unit of the b_field field", choices=("T", "mT", "G"))
    stale_s: float = setting(10.0, "a sensor whose newest reading is older than this is reported stale",
                             unit="s", gt=0)
    duration_s: float = setting(0.0, "stop after this long (0: until stopped)", unit="s", ge=0)
    reconnect_s: float = setting(1.0, "wait before dialling the router again", unit="s", gt=0)
    reconnect_max_s: float = setting(10.0, "failed attempts back off, doubling up to this", unit="s", gt=0)

    @property
    def fields(self) -> OcsFields:
        """Which OCS field is which sensor."""
        return OcsFields(self.t_bath_field, self.t_bath_unit, self.b_field_field, self.b_field_unit)


@dataclass(frozen=True)
class OcsBridgeConfig(Settings):
    """An ocs-bridge config document: ``[ocs-bridge]``, ``[metrics]``, ``[zenoh]``."""

    bridge: OcsBridgeSettings = setting(default_factory=OcsBridgeSettings, doc="router and fields", flatten=True)
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")

    @property
    def setup(self) -> str:
        return self.bridge.setup


class _Sensor:
    """One configured sensor: its field, scale, sequence and newest reading."""

    def __init__(self, sensor: str, field: str, scale: float):
        self.sensor, self.field, self.scale = sensor, field, scale
        self.feed = field.rpartition(".")[0]
        self.key = field.rpartition(".")[2]
        self.seq = 0
        self.t_last_ns = -1
        self.t_seen = None  # monotonic time of the newest reading's arrival
        self.readings = self.out_of_order = self.bad = 0
        self.stale = False


class OcsBridgeService(Service):
    """OCS feeds (WAMP, through a crossbar router) -> t_bath / b_field housekeeping messages on zenoh."""

    name = "ocs-bridge"
    Config = OcsBridgeConfig
    summary = "OCS housekeeping (crossbar WAMP feeds) published as t_bath / b_field messages"

    def owns(self) -> dict:
        return {"router": self.config.bridge.router, "fields": {s: f for s, (f, _) in self._fields().items()}}

    def _fields(self) -> dict:
        sensors = self.config.bridge.fields.sensors()
        if not sensors:
            raise ConfigError("ocs-bridge: name at least one field (t_bath_field = 'observatory.LS372.feeds."
                              "temperatures.Channel_06_T', or --t-bath-field)")
        return sensors

    def duration_s(self) -> float:
        return 0.0  # [ocs-bridge] duration_s ends the WAMP loop itself (_serve)

    def setup(self, ctx) -> None:
        from mntes_stream.errors import import_extra

        self._wamp = import_extra("autobahn.asyncio.wamp", "ocs")
        self._sensors = [_Sensor(s, f, k) for s, (f, k) in self._fields().items()]
        self._counts = {"publications": 0, "connections": 0, "connect_failures": 0, "disconnects": 0,
                        "router_state": "connecting", "router_error": ""}
        self._said: set = set()
        self._t0 = time.monotonic()
        self._pubs = ctx.publishers

    def step(self, ctx) -> bool:
        # One step: the WAMP client's own loop (reconnecting, beating) until stopped or its duration ends.
        loop = asyncio.new_event_loop()
        try:
            loop.run_until_complete(self._serve(self._wamp, ctx.stop))
        finally:
            loop.close()
        return False

    def finish(self, ctx) -> dict:
        result = self._beat()
        log.info("ocs-bridge stopped: %s", result)
        return result

    async def _serve(self, wamp, stopping) -> None:
        b = self.config.bridge
        t_end = time.monotonic() + b.duration_s if b.duration_s else None
        backoff = b.reconnect_s
        while not stopping.is_set() and (t_end is None or time.monotonic() < t_end):
            gone = asyncio.get_running_loop().create_future()
            runner = wamp.ApplicationRunner(b.router, b.realm)
            try:
                transport, _ = await asyncio.wait_for(runner.run(self._session_class(wamp, gone), start_loop=False),
                                                      timeout=10)
            except (TimeoutError, OSError) as exc:
                self._router("unreachable", f"{b.router}: {exc or 'timed out'}")
                self._counts["connect_failures"] += 1
                await self._sleep(backoff, stopping, t_end)
                backoff = min(2 * backoff, b.reconnect_max_s)
                continue
            self._counts["connections"] += 1
            while not gone.done() and not stopping.is_set() and (t_end is None or time.monotonic() < t_end):
                await asyncio.sleep(0.1)
                self._check_stale()
                self._beat()
            if gone.done():
                self._counts["disconnects"] += 1
                self._router("lost", f"{b.router}: connection lost")
                await self._sleep(b.reconnect_s, stopping, t_end)
            else:
                transport.close()
                await asyncio.sleep(0.1)  # let the close go out
            backoff = b.reconnect_s

    @staticmethod
    async def _sleep(seconds, stopping, t_end) -> None:
        t = time.monotonic() + seconds
        while time.monotonic() < t and not stopping.is_set() and (t_end is None or time.monotonic() < t_end):
            await asyncio.sleep(0.05)

    def _router(self, state: str, error: str) -> None:
        self._counts["router_state"], self._counts["router_error"] = state, error
        if f"router:{state}" not in self._said:  # each cause once (status and log), not at every retry
            self._said.add(f"router:{state}")
            self.heartbeat.warn(f"OCS router {error}")
            log.warning("OCS router %s", error)

    def _session_class(self, wamp, gone):
        bridge = self

        class _Session(wamp.ApplicationSession):
            async def onJoin(self, details):
                for feed in sorted({s.feed for s in bridge._sensors}):
                    await self.subscribe(lambda *args, _feed=feed, **kw: bridge._on_feed(_feed, args), feed)
                bridge._counts["router_state"], bridge._counts["router_error"] = "joined", ""
                bridge._said.discard("router:lost")
                bridge._said.discard("router:unreachable")

            def onDisconnect(self):
                if not gone.done():
                    gone.set_result(True)

        return _Session

    def _on_feed(self, feed: str, args) -> None:
        from mntes_stream.g3.ocs_hk import feed_readings
        from mntes_stream.io.messages import SENSOR_UNITS, HousekeepingChunk

        self._counts["publications"] += 1
        message = args[0] if len(args) == 1 else list(args)
        for s in self._sensors:
            if s.feed != feed:
                continue
            t, v, bad = feed_readings(message, s.key)
            s.bad += bad
            newer = t > s.t_last_ns
            if newer.size and np.any(newer[1:] & ~np.diff(t).astype(bool)):
                newer[1:] &= np.diff(t) > 0  # the same time twice in one publication
            s.out_of_order += int(t.size - np.count_nonzero(newer))
            t, v = t[newer], v[newer]
            if not t.size:
                continue
            msg = HousekeepingChunk(setup=self.config.bridge.setup, sensor=s.sensor, seq=s.seq, t_ns=t,
                                    value=v * s.scale, unit=SENSOR_UNITS[s.sensor])
            self._pubs.put(keys.hk_key(self.config.bridge.setup, s.sensor), msg.to_bytes())
            s.seq += 1
            s.readings += int(t.size)
            s.t_last_ns = int(t[-1])
            s.t_seen = time.monotonic()

    def _check_stale(self) -> None:
        """A sensor whose newest reading (or, before any, the start) is older than stale_s: said once per episode."""
        limit = self.config.bridge.stale_s
        now_ns = time.time_ns()
        for s in self._sensors:
            if s.t_last_ns < 0:
                stale, why = time.monotonic() - self._t0 > limit, f"no reading in {limit:g} s"
            else:
                age = (now_ns - s.t_last_ns) / 1e9
                stale, why = age > limit, f"newest reading {age:.1f} s old (stale_s {limit:g})"
            if stale and not s.stale:
                self.heartbeat.warn(f"{s.sensor} ({s.field}) stale: {why}")
                log.warning("%s (%s) stale: %s", s.sensor, s.field, why)
            s.stale = stale

    def _beat(self) -> dict:
        now_ns = time.time_ns()
        sensors = {s.sensor: {"field": s.field, "messages": s.seq, "readings": s.readings,
                              "out_of_order": s.out_of_order, "bad": s.bad,
                              "age_s": None if s.t_last_ns < 0 else round((now_ns - s.t_last_ns) / 1e9, 3),
                              "stale": s.stale} for s in self._sensors}
        counters = dict(self._counts) | {"sensors": sensors, "stale": sorted(s.sensor for s in self._sensors if s.stale),
                                         "messages": self._pubs.messages, "bytes": self._pubs.bytes}
        self.heartbeat.beat(**counters)
        return counters


def bridge_line(result: dict) -> str:
    """The final line: what each sensor published, and what was skipped."""
    parts = [f"{name} {s['readings']} readings in {s['messages']} messages"
             + (f" ({s['out_of_order']} out of order, {s['bad']} bad)" if s["out_of_order"] or s["bad"] else "")
             for name, s in result["sensors"].items()]
    return (f"ocs-bridge done: {'; '.join(parts)}; router {result['router_state']}, "
            f"{result['connections']} connections, {result['connect_failures']} failed")
