"""The ``g3-bridge`` service: SPT-3G DfMux readout (G3 frames) published as the project's messages.

A ``G3Reader`` on the DAQ's network tee (``tcp://HOST:PORT``, spt3g's
``G3NetworkSender``; ``record_bolodata.py`` uses port 5353) or on a G3 file
feeds a :class:`~mntes_stream.g3.translate.FrameTranslator`; its counts,
bias, bath-temperature (and constant field) messages go out on zenoh with
BLOCK publishers, so the converter, recorder, monitor and every other
service run unchanged on real readout.

When the DAQ goes away (connection refused, stream ended, no frame for
``timeout_s``), the bridge reconnects every ``reconnect_s``; the sender
resends its cached metadata (wiring, housekeeping) to a new client, and
samples the bridge never saw are counted (``gap_samples``) from the DfMux
clock. Sequence numbers run on across reconnects, so the converter sees a
gap in time, not a restart.
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError
from mntes_stream.g3.mapping import G3InputConfig
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["BridgeSettings", "G3BridgeConfig", "G3BridgeService", "bridge_config", "G3Source"]

log = logging.getLogger("mntes_stream.g3.bridge")


@dataclass(frozen=True)
class BridgeSettings(Settings):
    """Where the frames come from and how they go out (the ``[g3-bridge]`` table)."""

    source: str = setting("", "tcp://HOST:PORT of the DAQ's G3NetworkSender, or a G3 file")
    setup: str = setting(keys.DEFAULT_SETUP, "keys mntes/<setup>/...", pattern=NAME_PATTERN)
    chunk_samples: int = setting(16, "raw Timepoints per counts chunk (16 = 0.105 s at the DfMux rate)", ge=1)
    boards: tuple[int, ...] = setting((), "only these board serials (one bridge per group of boards); empty: all")
    params: str = setting("", "the converter's parameter file: counts are published in units of its gain, so a "
                          "DfMux gain change applies from its sample on ('': the DfMux's own counts, a gain change "
                          "is only reported)", path=True)
    duration_s: float = setting(0.0, "stop after this long (0: until stopped or, for a file, its end)", unit="s", ge=0)
    reconnect_s: float = setting(1.0, "wait between connection attempts", unit="s", gt=0)
    timeout_s: float = setting(10.0, "a connection silent this long is dead: reconnect", unit="s", gt=0)
    max_reconnects: int = setting(0, "give up after this many failed attempts in a row (0: never)", ge=0)
    bath_wait_s: float = setting(30.0, "data time without any bath reading (and no default) before it is an error",
                                 unit="s", gt=0)
    wait_subscribers_s: float = setting(5.0, "wait this long for subscribers to the first keys", unit="s", ge=0)


@dataclass(frozen=True)
class G3BridgeConfig(Settings):
    """A bridge config document: ``[g3-bridge]``, ``[g3]``, ``[metrics]``, ``[zenoh]``."""

    bridge: BridgeSettings = setting(default_factory=BridgeSettings, doc="source and publication", flatten=True)
    g3: G3InputConfig = setting(default_factory=G3InputConfig, doc="how G3 frames are read ([g3])")
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")

    @property
    def setup(self) -> str:
        return self.bridge.setup


class G3Source:
    """Frames from a network tee or a file, one list at a time; reconnects a network source.

    ``next()`` returns a list of frames, ``[]`` when a file has ended, or
    None while (re)connecting; ``reconnects`` and ``connected`` say how it went.
    """

    def __init__(self, source: str, timeout_s: float = 10.0, reconnect_s: float = 1.0, max_reconnects: int = 0):
        from mntes_stream.g3 import spt3g

        self.core, _ = spt3g()
        self.source = source
        self.network = source.startswith("tcp://")
        self.timeout_s, self.reconnect_s, self.max_reconnects = timeout_s, reconnect_s, max_reconnects
        self._reader = None
        self._failures = 0
        self._t_retry = 0.0
        self.connections = 0
        self.reconnects = 0
        self.finished = False
        if not self.network:
            from mntes_stream.g3.files import expand_inputs

            self._files = expand_inputs(source)

    def _open(self):
        if not self.network:
            self._reader = self.core.G3Reader(filename=self._files)
            return
        now = time.monotonic()
        if now < self._t_retry:
            return
        try:
            self._reader = self.core.G3Reader(filename=self.source, timeout=float(self.timeout_s))
        except RuntimeError as exc:
            self._failures += 1
            self._t_retry = now + self.reconnect_s
            if self.max_reconnects and self._failures > self.max_reconnects:
                raise ConfigError(f"g3-bridge: {self.source}: {exc} ({self._failures} attempts)") from None
            if self._failures == 1:
                log.warning("g3-bridge: cannot connect to %s (%s); retrying every %g s", self.source, exc,
                            self.reconnect_s)
            return
        self.connections += 1
        self.reconnects += self.connections > 1
        self._failures = 0
        log.info("g3-bridge: connected to %s", self.source)

    def next(self):
        if self._reader is None:
            self._open()
            if self._reader is None:
                return None
        try:
            frames = self._reader(None)
        except RuntimeError as exc:  # timeout or a broken connection
            log.warning("g3-bridge: %s: %s; reconnecting", self.source, exc)
            frames = []
        if frames:
            return list(frames)
        self._reader = None
        if not self.network:
            self.finished = True
            return []
        self._t_retry = time.monotonic() + self.reconnect_s
        return None

    def close(self) -> None:
        self._reader = None


def bridge_config(args) -> G3BridgeConfig:
    """The config from ``--config``/``--set`` and the command line (which wins)."""
    import dataclasses

    from mntes_stream.service.config import load_service_config

    if args.config:
        service, cfg = load_service_config(args.config, args.set)
        if service is not G3BridgeService:
            raise ConfigError(f"{args.config}: a [{service.name}] config, not a [g3-bridge] one")
    elif args.set:
        raise ConfigError("--set needs --config")
    else:
        cfg = G3BridgeConfig()
    flags = {k: getattr(args, a) for k, a in (("source", "source"), ("setup", "setup"), ("boards", "boards"),
                                              ("params", "params"),
                                              ("chunk_samples", "chunk_samples"), ("duration_s", "duration_s"))
             if getattr(args, a, None) is not None}
    g3 = {k: getattr(args, k) for k in ("t_bath_key", "t_bath_default_k") if getattr(args, k) is not None}
    try:
        cfg = dataclasses.replace(cfg, bridge=dataclasses.replace(cfg.bridge, **flags),
                                  g3=dataclasses.replace(cfg.g3, **g3))
    except ConfigError as exc:
        raise ConfigError(f"command line: {exc}") from None
    if not cfg.bridge.source:
        raise ConfigError("g3-bridge: give the source (--from tcp://HOST:PORT or a G3 file, or source = in the config)")
    return cfg


class G3BridgeService(Service):
    """SPT-3G readout (G3 frames) -> counts, bias and housekeeping messages on zenoh."""

    name = "g3-bridge"
    Config = G3BridgeConfig
    summary = "SPT-3G DfMux readout (G3 over TCP or a file) published as counts + housekeeping"

    def owns(self) -> dict:
        return {"source": self.config.bridge.source, "boards": list(self.config.bridge.boards) or "all"}

    def run(self, stop=None, ready=None) -> dict:
        from mntes_stream.g3.translate import FrameTranslator
        from mntes_stream.io.transport import Publishers, open_session
        from mntes_stream.service.base import stop_on_signals

        b = self.config.bridge
        gref = None
        if b.params:
            from mntes_stream.io.paramfile import load_params

            gref = {d: abs(p.gain_a_per_count) for d, p in load_params(b.params).items()}
        tr = FrameTranslator(b.setup, self.config.g3, b.chunk_samples, b.boards, gain_reference=gref)
        src = G3Source(b.source, b.timeout_s, b.reconnect_s, b.max_reconnects)
        t_start = time.monotonic()
        first_data_ns = None
        waited = False
        with stop_on_signals(stop) as stopping, open_session(self.config.zenoh) as session:
            pubs = Publishers(session)
            if ready is not None:
                ready.set()
            try:
                while not stopping.is_set():
                    if b.duration_s and time.monotonic() - t_start >= b.duration_s:
                        break
                    frames = src.next()
                    if frames is None:  # (re)connecting: what the last connection gave goes out now
                        for key, payload in tr.flush():
                            pubs.put(key, payload)
                        stopping.wait(min(0.05, b.reconnect_s))
                        self._beat(tr, src, pubs)
                        continue
                    if not frames and src.finished:
                        break
                    out = []
                    for frame in frames:
                        out += tr.handle(frame)
                    counts = [k for k, _ in out if keys.kind_of(k) == "counts"]
                    if counts:
                        t_last = tr._t_last_ns
                        first_data_ns = first_data_ns or t_last
                        if not len(tr.bath):
                            if self.config.g3.t_bath_default_k is not None:
                                out = tr.default_bath(t_last) + out
                            elif t_last - first_data_ns > b.bath_wait_s * 1e9:
                                tr.bath.require()  # the one-line error naming the thermometer setting
                    if out and not waited and b.wait_subscribers_s > 0:
                        waited = True
                        pubs.wait_matching([k for k, _ in out], b.wait_subscribers_s, stopping)
                    for key, payload in out:
                        pubs.put(key, payload)
                    while tr.gain_changed_at:
                        self.heartbeat.warn(f"DfMux gain changed at {tr.gain_changed_at.pop(0)} ns: the converter "
                                            "keeps the gain of its parameters")
                    self._beat(tr, src, pubs)
                for key, payload in tr.flush():
                    pubs.put(key, payload)
            finally:
                src.close()
                pubs.close()
        result = self._beat(tr, src, pubs)
        log.info("g3-bridge stopped: %s", result)
        return result

    def _beat(self, tr, src, pubs) -> dict:
        c = tr.counters
        counters = {"frames": c.frames, "timepoints": c.timepoints, "scans": c.scans, "samples": c.samples,
                    "invalid_samples": c.invalid_samples, "gap_samples": c.gap_samples,
                    "housekeeping": c.housekeeping, "gain_changes": c.gain_changes, "bias_changes": c.bias_changes,
                    "bath_readings": c.bath_readings,
                    "messages": pubs.messages, "bytes": pubs.bytes, "connections": src.connections,
                    "reconnects": src.reconnects}
        self.heartbeat.beat(**counters)
        return counters
