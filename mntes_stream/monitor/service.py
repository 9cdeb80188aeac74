"""The monitor as a registry service (``[monitor]`` + ``[zenoh]``): the page, or the terminal table."""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.monitor.aggregate import MonitorConfig
from mntes_stream.service.base import Service, stop_on_signals

__all__ = ["MonitorServiceConfig", "MonitorService"]

log = logging.getLogger("mntes_stream.monitor")


@dataclass(frozen=True)
class MonitorServiceConfig(Settings):
    """The ``[monitor]`` and ``[zenoh]`` tables: what to watch, what to keep (:class:`MonitorConfig`), where to serve."""

    view: MonitorConfig = setting(default_factory=MonitorConfig, doc="what the monitor keeps", flatten=True)
    setup: str = setting(keys.DEFAULT_SETUP, "watch mntes/<setup>/{power,hk,status}", pattern=NAME_PATTERN)
    bind: str = setting("127.0.0.1", "address the page listens on (anything but loopback exposes the stream)")
    port: int = setting(8050, "HTTP port (0: any free port)", ge=0, le=65535)
    update_s: float = setting(0.5, "update period of the page or table", unit="s", ge=0.05, le=60)
    text: bool = setting(False, "print a terminal table instead of serving the page")
    duration_s: float = setting(0.0, "stop after this long (0: until stopped)", unit="s", ge=0)
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")


def _run_text(sub, cfg: MonitorServiceConfig, stop, out=sys.stdout) -> None:
    from mntes_stream.monitor.text import render_text

    clear = out.isatty()
    t_end = time.monotonic() + cfg.duration_s if cfg.duration_s > 0 else None
    period = max(cfg.update_s, 0.1)
    stop.wait(min(period, 1.0))  # let a first interval of data arrive
    while not stop.is_set():
        with sub.lock:
            tick = sub.aggregator.tick(time.time_ns())
            screen = render_text(sub.aggregator, tick)
        print(("\x1b[H\x1b[2J" if clear else "") + screen + ("" if clear else "\n"), file=out, flush=True)
        if t_end is not None and time.monotonic() >= t_end:
            return
        stop.wait(period if t_end is None else max(min(period, t_end - time.monotonic()), 0.0))


class MonitorService(Service):
    """Quick-look of a running setup: power, spectra, channel states, housekeeping, service health."""

    name = "monitor"
    Config = MonitorServiceConfig
    summary = "quick-look web page (or terminal table) of power, housekeeping and service health"

    def run(self, stop=None, ready=None) -> dict:
        from mntes_stream.monitor.subscriber import MonitorSubscriber

        cfg = self.config
        with stop_on_signals(stop) as stopping, MonitorSubscriber(cfg.setup, cfg.zenoh, cfg.view) as sub:
            if cfg.text:
                if ready is not None:
                    ready.set()
                _run_text(sub, cfg, stopping)
            else:
                from mntes_stream.monitor.server import serve

                def on_ready(host, port):
                    shown = f"[{host}]" if ":" in host else host
                    print(f"mntes-stream monitor: serving http://{shown}:{port}/ (setup {cfg.setup})", flush=True)
                    if ready is not None:
                        ready.set()

                serve(sub, cfg.bind, cfg.port, cfg.update_s, cfg.duration_s, on_ready, stopping)
            with sub.lock:
                health = sub.aggregator.tick(time.time_ns())["health"]["monitor"]
        return {k: v for k, v in health.items() if isinstance(v, (int, float, str))}
