"""``mntes-stream foxglove``: a setup served live to the Foxglove app (Foxglove WebSocket protocol).

Subscribes to ``mntes/<setup>/{power,hk,status}/**`` and logs the json
channels of :mod:`mntes_stream.foxglove.translate` to a foxglove-sdk
WebSocket server (``foxglove.websocket.v1``; open ``ws://127.0.0.1:8765`` in
the app). The zenoh callback never blocks (a full queue drops, counted): the
converter publishes with BLOCK congestion control, so a slow viewer must not
slow the conversion it shows. Power of a module whose channel nobody
subscribes to is not translated at all.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import time
from dataclasses import dataclass

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings, open_session
from mntes_stream.service.base import Service, stop_on_signals
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["ChannelBridge", "FoxgloveConfig", "FoxgloveService", "require_foxglove"]

log = logging.getLogger("mntes_stream.foxglove")


def require_foxglove():
    """The ``foxglove`` module (foxglove-sdk), or a one-line error naming the extra."""
    from mntes_stream.errors import import_extra

    return import_extra("foxglove", "foxglove")


@dataclass(frozen=True)
class FoxgloveConfig(Settings):
    """The ``[foxglove]``, ``[metrics]`` and ``[zenoh]`` tables."""

    setup: str = setting(keys.DEFAULT_SETUP, "serve mntes/<setup>/{power,hk,status}", pattern=NAME_PATTERN)
    bind: str = setting("127.0.0.1", "address the WebSocket server listens on (anything but loopback exposes the "
                                     "stream; the protocol has no authentication)")
    port: int = setting(8765, "WebSocket port (0: any free port)", ge=0, le=65535)
    detectors: tuple[str, ...] = setting((), "detector ids whose power is served ([] = first per_module of each module)")
    per_module: int = setting(4, "detectors per module served when detectors is empty (0: all)", ge=0)
    max_rate_hz: float = setting(50.0, "power samples per second and module at most (0: every sample)", unit="Hz",
                                 ge=0)
    queue_size: int = setting(8192, "received messages waiting; beyond, dropped (counted), never blocking the "
                                    "publishers", ge=1)
    duration_s: float = setting(0.0, "stop after this long (0: until stopped)", unit="s", ge=0)
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")


class ChannelBridge:
    """Decoded messages -> foxglove channels of one context (created on first message of a topic)."""

    def __init__(self, foxglove, context, view):
        self.fg, self.context, self.view = foxglove, context, view
        self.channels: dict[str, object] = {}
        self.logged = 0

    def channel(self, topic: str, schema: str):
        from mntes_stream.foxglove.translate import SCHEMAS

        ch = self.channels.get(topic)
        if ch is None:
            ch = self.channels[topic] = self.fg.Channel(topic, schema=SCHEMAS[schema], context=self.context,
                                                        metadata={"mntes.schema": schema})
        return ch

    def handle(self, msg) -> None:
        from mntes_stream.io.messages import PowerChunk

        if isinstance(msg, PowerChunk):
            topic = f"/mntes/{msg.setup}/power/{msg.board}/{msg.module}"
            ch = self.channels.get(topic)
            if ch is not None and not ch.has_sinks():
                return  # nobody watches this module: no json made
        for out in self.view.translate(msg):
            self.channel(out.topic, out.schema).log(out.message, log_time=out.log_time_ns)
            self.logged += 1


class FoxgloveService(Service):
    """Power, flag rates, housekeeping and converter status of a setup, live in the Foxglove app."""

    name = "foxglove"
    Config = FoxgloveConfig
    summary = "serve a setup to the Foxglove app (Foxglove WebSocket protocol, json channels)"

    def run(self, stop=None, ready=None) -> dict:
        from mntes_stream.foxglove.translate import FoxgloveView
        from mntes_stream.io.messages import decode

        fg = require_foxglove()
        cfg = self.config
        pending: queue.Queue = queue.Queue(maxsize=cfg.queue_size)
        counts = {"received": 0, "dropped": 0, "bad": 0}

        def on_sample(sample) -> None:
            try:
                pending.put_nowait(sample.payload.to_bytes())
                counts["received"] += 1
            except queue.Full:
                counts["dropped"] += 1

        context = fg.Context()
        bridge = ChannelBridge(fg, context, FoxgloveView(cfg.detectors, cfg.per_module, cfg.max_rate_hz))
        t_end = time.monotonic() + cfg.duration_s if cfg.duration_s else None
        server = None
        with stop_on_signals(stop) as stopping, open_session(cfg.zenoh) as session:
            subs = [session.declare_subscriber(k, on_sample)
                    for k in (keys.status_key(cfg.setup), keys.hk_key(cfg.setup), keys.power_key(cfg.setup))]
            try:
                try:
                    server = fg.start_server(name=f"mntes-stream {cfg.setup}", host=cfg.bind, port=cfg.port,
                                             context=context)
                except Exception as exc:  # address in use, bad address: one line
                    raise ConfigError(f"foxglove: cannot serve on {cfg.bind}:{cfg.port}: {exc}") from None
                shown = f"[{cfg.bind}]" if ":" in cfg.bind else cfg.bind
                print(f"mntes-stream foxglove: serving ws://{shown}:{server.port} (setup {cfg.setup})", flush=True)
                self.heartbeat.beat(port=server.port)
                if ready is not None:
                    ready.set()
                while not stopping.is_set() and (t_end is None or time.monotonic() < t_end):
                    try:
                        payload = pending.get(timeout=0.1)
                    except queue.Empty:
                        continue
                    try:
                        bridge.handle(decode(payload, ("mntes.power", "mntes.hk", "mntes.status")))
                    except SchemaError:
                        counts["bad"] += 1
                    self.heartbeat.beat(**counts, logged=bridge.logged, channels=len(bridge.channels),
                                        queue_depth=pending.qsize())
            finally:
                for sub in subs:
                    with contextlib.suppress(Exception):
                        sub.undeclare()
                if server is not None:
                    server.stop()
        return {**counts, "logged": bridge.logged, "channels": len(bridge.channels)}
