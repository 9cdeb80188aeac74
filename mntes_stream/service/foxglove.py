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
from dataclasses import dataclass

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
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

    def preflight(self) -> None:
        require_foxglove()

    def setup(self, ctx) -> None:
        from mntes_stream.foxglove.translate import FoxgloveView

        fg = require_foxglove()
        cfg = self.config
        self._pending = pending = queue.Queue(maxsize=cfg.queue_size)
        self._counts = counts = {"received": 0, "dropped": 0, "bad": 0}

        def on_sample(sample) -> None:
            try:
                pending.put_nowait(sample.payload.to_bytes())
                counts["received"] += 1
            except queue.Full:
                counts["dropped"] += 1

        context = fg.Context()
        self._bridge = ChannelBridge(fg, context, FoxgloveView(cfg.detectors, cfg.per_module, cfg.max_rate_hz))
        self._server = None
        self._subs = [ctx.session.declare_subscriber(k, on_sample)
                      for k in (keys.status_key(cfg.setup), keys.hk_key(cfg.setup), keys.power_key(cfg.setup))]
        try:
            self._server = fg.start_server(name=f"mntes-stream {cfg.setup}", host=cfg.bind, port=cfg.port,
                                           context=context)
        except Exception as exc:  # address in use, bad address: one line
            self._close()
            raise ConfigError(f"foxglove: cannot serve on {cfg.bind}:{cfg.port}: {exc}") from None
        shown = f"[{cfg.bind}]" if ":" in cfg.bind else cfg.bind
        print(f"mntes-stream foxglove: serving ws://{shown}:{self._server.port} (setup {cfg.setup})", flush=True)
        self.heartbeat.beat(port=self._server.port)

    def step(self, ctx) -> bool:
        from mntes_stream.io.messages import decode

        try:
            payload = self._pending.get(timeout=0.1)
        except queue.Empty:
            return True
        try:
            self._bridge.handle(decode(payload, ("mntes.power", "mntes.hk", "mntes.status")))
        except SchemaError:
            self._counts["bad"] += 1
        return True

    def counters(self) -> dict:
        if not hasattr(self, "_bridge"):
            return {}
        return {**self._counts, "logged": self._bridge.logged, "channels": len(self._bridge.channels),
                "queue_depth": self._pending.qsize()}

    def _close(self) -> None:
        for sub in self._subs:
            with contextlib.suppress(Exception):
                sub.undeclare()
        if self._server is not None:
            self._server.stop()

    def finish(self, ctx) -> dict:
        self._close()
        return {**self._counts, "logged": self._bridge.logged, "channels": len(self._bridge.channels)}
