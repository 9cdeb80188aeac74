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


def _run_text(sub, cfg: MonitorServiceConfig, stop, out=None) -> None:
    from mntes_stream.monitor.text import render_text

    out = sys.stdout if out is None else out  # now: a default bound at import keeps a stream long gone
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

    ready_after_setup = False  # the web page is ready when its server listens

    def duration_s(self) -> float:
        return 0.0  # the text loop and the web server end at duration_s themselves

    def setup(self, ctx) -> None:
        from mntes_stream.monitor.subscriber import MonitorSubscriber

        cfg = self.config
        positions = load_positions(cfg.params) if cfg.params else None
        self._sub = MonitorSubscriber(cfg.setup, cfg.zenoh, cfg.view, positions=positions, session=ctx.session,
                                      params_path=cfg.params)
        self._sub.start()

    def step(self, ctx) -> bool:
        # One step: the terminal table or the web server, until stopped or duration_s.
        cfg, sub = self.config, self._sub
        if cfg.text:
            ctx.mark_ready()
            _run_text(sub, cfg, ctx.stop)
            return False
        from mntes_stream.monitor.server import serve

        def on_ready(host, port):
            shown = f"[{host}]" if ":" in host else host
            print(f"mntes-stream monitor: serving http://{shown}:{port}/ (setup {cfg.setup})", flush=True)
            ctx.mark_ready()

        serve(sub, cfg.bind, cfg.port, cfg.update_s, cfg.duration_s, on_ready, ctx.stop,
              allowed_hosts=cfg.allowed_hosts, max_clients=cfg.max_clients, send_timeout_s=cfg.send_timeout_s,
              limits=cfg.web)
        return False

    def finish(self, ctx) -> dict:
        sub = self._sub
        with sub.lock:
            health = sub.aggregator.tick(time.time_ns())["health"]["monitor"]
        sub.close()
        return {k: v for k, v in health.items() if isinstance(v, (int, float, str))}
