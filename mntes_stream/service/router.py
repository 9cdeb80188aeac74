"""Router service: a zenoh session in router mode, the hub services connect to as clients.

``mntes-stream router`` (or ``serve --config services/router.toml``) runs
what zenoh's own ``zenohd`` runs, with the project's layering and flags: it
listens on ``tcp/127.0.0.1:7447`` unless told otherwise and routes every key
between its clients and to other routers it connects to (``-e``), so the
monitor and the recorder see every stream without gossip. A site that has
``zenohd`` can run that instead: the services cannot tell the difference.
"""

from __future__ import annotations

import dataclasses
import logging
import time

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings, open_session
from mntes_stream.service.base import Service, stop_on_signals
from mntes_stream.service.metrics import MetricsSettings

log = logging.getLogger(__name__)


@dataclasses.dataclass(frozen=True)
class RouterConfig(Settings):
    """``[router]`` and its ``[zenoh]`` table (whose mode is always ``router``)."""

    setup: str = setting(keys.DEFAULT_SETUP, "announced as mntes/<setup>/alive/router/<name>", pattern=NAME_PATTERN)
    name: str = setting("router", "instance name (ps, logs)", pattern=NAME_PATTERN)
    duration_s: float = setting(0.0, "stop after this long (0: until stopped)", unit="s", ge=0)
    log_interval_s: float = setting(10.0, "how often the connected peers and clients are logged", unit="s", gt=0)
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to listen and which routers to join ([zenoh])")


class RouterService(Service):
    """A zenoh router: clients and peers connect to it; it forwards every key between them."""

    name = "router"
    Config = RouterConfig
    summary = "zenoh router: the hub every service connects to as a client"

    def run(self, stop=None, ready=None) -> dict:
        cfg = self.config
        t0 = time.monotonic()
        seen: set[str] = set()
        with stop_on_signals(stop) as stopping, open_session(dataclasses.replace(cfg.zenoh, mode="router")) as session:
            log.info("router %s: zenoh id %s", cfg.name, session.zid())
            if ready is not None:
                ready.set()
            next_log = 0.0
            while not stopping.wait(0.2):
                if cfg.duration_s and time.monotonic() - t0 >= cfg.duration_s:
                    break
                peers = [str(z) for z in session.info.peers_zid()] + [str(z) for z in session.info.routers_zid()]
                seen.update(peers)
                links = len(list(session.info.links()))
                self.heartbeat.beat(links=links, zenoh_ids_seen=len(seen))
                if time.monotonic() >= next_log:
                    log.info("router %s: %d links, %d zenoh ids seen", cfg.name, links, len(seen))
                    next_log = time.monotonic() + cfg.log_interval_s
        return {"zenoh_ids_seen": len(seen), "duration_s": time.monotonic() - t0}
