"""The monitor as a registry service (``[monitor]`` + ``[zenoh]``): the page, or the terminal table."""

from __future__ import annotations

import logging
import math
import sys
import time
import tomllib
from dataclasses import dataclass
from pathlib import Path

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.monitor.aggregate import MonitorConfig
from mntes_stream.monitor.web_limits import WebLimits
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["MonitorServiceConfig", "MonitorService", "load_positions"]

log = logging.getLogger("mntes_stream.monitor")


@dataclass(frozen=True)
class MonitorServiceConfig(Settings):
    """The ``[monitor]`` and ``[zenoh]`` tables: what to watch, what to keep (:class:`MonitorConfig`), where to serve."""

    view: MonitorConfig = setting(default_factory=MonitorConfig, doc="what the monitor keeps", flatten=True)
    setup: str = setting(keys.DEFAULT_SETUP, "watch mntes/<setup>/{power,hk,status}", pattern=NAME_PATTERN)
    bind: str = setting("127.0.0.1", "address the page listens on (anything but loopback exposes the stream)")
    allowed_hosts: tuple[str, ...] = setting((), "host names the page may be reached as besides loopback and bind "
                                             "(every other Host header and foreign Origin is refused)")
    max_clients: int = setting(32, "websocket clients served at once", ge=1, le=1024)
    send_timeout_s: float = setting(10.0, "a page that takes longer to accept one update is disconnected", unit="s",
                                    gt=0)
    web: WebLimits = setting(default_factory=WebLimits, doc="the page server's socket limits", flatten=True)
    params: str | None = setting(None, "parameter file whose [metadata.focal_plane] gives sky positions "
                                 "(detector id = [x_deg, y_deg]) for the focal-plane view; its detectors' "
                                 "parameters also make the live leakage's linear baseline (default: the "
                                 "converter's provenance)")
    port: int = setting(8050, "HTTP port (0: any free port)", ge=0, le=65535)
    update_s: float = setting(0.5, "update period of the page or table", unit="s", ge=0.05, le=60)
    text: bool = setting(False, "print a terminal table instead of serving the page")
    duration_s: float = setting(0.0, "stop after this long (0: until stopped)", unit="s", ge=0)
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")


def load_positions(path: str | Path) -> dict[str, tuple[float, float]]:
    """Sky positions ``{detector id: (x_deg, y_deg)}`` from a parameter file's ``[metadata.focal_plane]`` table.

    Raises
    ------
    ConfigError
        Unreadable file, or a position that is not two finite numbers.
    """
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"monitor params {path}: {exc}") from None
    table = doc.get("metadata", {}).get("focal_plane", {})
    if not isinstance(table, dict):
        raise ConfigError(f"{path}: [metadata.focal_plane] must be a table of detector id = [x_deg, y_deg]")
    out = {}
    for det, xy in table.items():
        ok = (isinstance(xy, list) and len(xy) == 2 and all(isinstance(v, (int, float)) and not isinstance(v, bool)
                                                          and math.isfinite(v) for v in xy))
        if not ok:
            raise ConfigError(f"{path}: metadata.focal_plane.{det} must be [x_deg, y_deg], got {xy!r}")
        out[str(det)] = (float(xy[0]), float(xy[1]))
    return out


def _print_table(sub, out=None) -> None:
    from mntes_stream.monitor.text import render_text

    out = sys.stdout if out is None else out  # now: a default bound at import keeps a stream long gone
    clear = out.isatty()
    with sub.lock:
        tick = sub.aggregator.tick(time.time_ns())
        screen = render_text(sub.aggregator, tick)
    print(("\x1b[H\x1b[2J" if clear else "") + screen + ("" if clear else "\n"), file=out, flush=True)


class MonitorService(Service):
    """Quick-look of a running setup: power, spectra, channel states, housekeeping, service health."""

    name = "monitor"
    Config = MonitorServiceConfig
    summary = "quick-look web page (or terminal table) of power, housekeeping and service health"

    # The page is served by its own thread (monitor.server.PageServer) from setup to finish, so each step
    # returns within a beat and the heartbeat shows the monitor alive; the table is printed by steps.
    ready_after_setup = False  # ready when the page listens (setup) or the first table is due (text)

    def duration_s(self) -> float:
        # The table ends at duration_s itself, after the table of that moment (the lifecycle would end first).
        return 0.0 if self.config.text else self.config.duration_s

    def setup(self, ctx) -> None:
        from mntes_stream.monitor.subscriber import MonitorSubscriber

        cfg = self.config
        positions = load_positions(cfg.params) if cfg.params else None
        self._sub = MonitorSubscriber(cfg.setup, cfg.zenoh, cfg.view, positions=positions, session=ctx.session,
                                      params_path=cfg.params)
        self._page, self._url = None, ""
        self._sub.start()
        if cfg.text:
            now = time.monotonic()
            self._t_end = now + cfg.duration_s if cfg.duration_s > 0 else None
            self._next_table = now + min(cfg.update_s, 1.0)  # let a first interval of data arrive
            ctx.mark_ready()
            return
        from mntes_stream.monitor.server import PageServer

        self._page = PageServer(self._sub, cfg.bind, cfg.port, cfg.update_s, allowed_hosts=cfg.allowed_hosts,
                                max_clients=cfg.max_clients, send_timeout_s=cfg.send_timeout_s, limits=cfg.web)
        try:
            address = self._page.start(ctx.stop)
        except BaseException:
            self._sub.close()
            raise
        if address is None:  # stopped while starting: the first step sees it
            return
        host, port = address
        shown = f"[{host}]" if ":" in host else host
        print(f"mntes-stream monitor: serving http://{shown}:{port}/ (setup {cfg.setup})", flush=True)
        self._url = f"http://{shown}:{port}/"
        ctx.mark_ready()

    def step(self, ctx) -> bool:
        if self._page is not None:  # the page: serving until stopped or its server ends (finish says why)
            ctx.stop.wait(self.beat_every_s)
            return self._page.alive()
        now = time.monotonic()
        if ctx.stop.wait(min(max(self._next_table - now, 0.0), self.beat_every_s)):
            return True  # the lifecycle sees the stop
        if time.monotonic() < self._next_table:
            return True
        _print_table(self._sub)
        self._next_table += max(self.config.update_s, 0.1)
        if self._t_end is not None:
            if time.monotonic() >= self._t_end:
                return False
            self._next_table = min(self._next_table, self._t_end)
        return True

    def counters(self) -> dict:
        agg = self._sub.aggregator if getattr(self, "_sub", None) is not None else None
        if agg is None:
            return {}
        out = {"power_chunks": agg.power_chunks, "dropped": agg.dropped}
        if self._url:
            out["url"] = self._url
        return out

    def finish(self, ctx) -> dict:
        sub = self._sub
        try:
            if self._page is not None:
                self._page.stop()  # raises what the server died of, if it did
        finally:
            with sub.lock:
                health = sub.aggregator.tick(time.time_ns())["health"]["monitor"]
            sub.close()
        return {k: v for k, v in health.items() if isinstance(v, (int, float, str))}
