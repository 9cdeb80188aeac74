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
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
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

    def zenoh_settings(self) -> ZenohSettings:
        return dataclasses.replace(self.config.zenoh, mode="router")

    def setup(self, ctx) -> None:
        self._t0 = time.monotonic()
        self._seen: set[str] = set()
        self._links = 0
        self._next_log = 0.0
        log.info("router %s: zenoh id %s", self.config.name, ctx.session.zid())

    def step(self, ctx) -> bool:
        if ctx.stop.wait(0.2):
            return False
        session = ctx.session
        self._seen.update([str(z) for z in session.info.peers_zid()] + [str(z) for z in session.info.routers_zid()])
        self._links = len(list(session.info.links()))
        if time.monotonic() >= self._next_log:
            log.info("router %s: %d links, %d zenoh ids seen", self.config.name, self._links, len(self._seen))
            self._next_log = time.monotonic() + self.config.log_interval_s
        return True

    def counters(self) -> dict:
        return {"links": getattr(self, "_links", 0), "zenoh_ids_seen": len(getattr(self, "_seen", ()))}

    def finish(self, ctx) -> dict:
        return {"zenoh_ids_seen": len(self._seen), "duration_s": time.monotonic() - self._t0}
