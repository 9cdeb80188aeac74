"""The ``g3-bridge`` service: SPT-3G DfMux readout (G3 frames) published as the project's messages.

A ``G3Reader`` on the DAQ's network tee (``tcp://HOST:PORT``, spt3g's
``G3NetworkSender``; ``record_bolodata.py`` uses port 5353) or on a G3 file
feeds a :class:`~mntes_stream.g3.translate.FrameTranslator`; its counts,
bias, bath-temperature (and constant field) messages go out on zenoh with
BLOCK publishers, so the converter, recorder, monitor and every other
service run unchanged on real readout.

When the DAQ goes away (connection refused, stream ended, no frame for
``timeout_s``), the bridge reconnects, backing off from ``reconnect_s`` to
``reconnect_max_s``, forever unless ``max_reconnects`` says otherwise; the
sender resends its cached metadata (wiring, housekeeping) to a new client,
and samples the bridge never saw are counted (``gap_samples``) from the
DfMux clock. Sequence numbers run on across reconnects, so the converter
sees a gap in time, not a restart.

No input stops it: the byte stream is split into frames by
:mod:`~mntes_stream.g3.wire` with every length claim bounded by
``max_frame_mb`` before anything is allocated, and every frame it cannot
use (wrong class, empty map, undecodable, CRC, before any wiring beyond
``max_held_frames``) is counted by reason in ``rejected`` and skipped. The
heartbeat and the final result carry the bridge's ledger: per stream the
counts chunks published and the samples never received, the frames
rejected by reason (:func:`ledger_line` is its one line).
"""

from __future__ import annotations

import logging
import time
from dataclasses import dataclass

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError
from mntes_stream.g3.settings import G3InputConfig
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["BridgeSettings", "G3BridgeConfig", "G3BridgeService", "G3Source"]

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
    reconnect_max_s: float = setting(10.0, "failed attempts back off, doubling from reconnect_s up to this",
                                     unit="s", gt=0)
    max_reconnects: int = setting(0, "give up after this many failed attempts in a row (0: never)", ge=0)
    max_frame_mb: float = setting(512.0, "the largest G3 frame accepted: a frame claiming more is refused (and "
                                  "the connection made again) before anything is allocated for it", unit="MB", gt=0)
    max_held_frames: int = setting(256, "Scan/Timepoint frames kept while no Wiring frame has come; beyond, the "
                                   "oldest are counted (before_wiring) and dropped", ge=0)
    bath_wait_s: float = setting(30.0, "data time without any bath reading (and no default) before it is an error",
                                 unit="s", gt=0)
    wait_subscribers_s: float = setting(5.0, "wait this long for subscribers to the first keys", unit="s", ge=0)
    hk: str = setting("", "OCS HK G3 file or directory: the bath temperature comes from its t_bath_field, aligned "
                      "by time, instead of the DAQ's ('': the DAQ's GcpSlow frames)", path=True)
    t_bath_field: str = setting("", "with hk: the thermometer's full field name, e.g. observatory.LS372.feeds."
                                "temperatures.Channel_06_T (K)")


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
    """Frames from a network tee or a file, a few at a time; reconnects a network source, forever by default.

    The bytes go through :class:`~mntes_stream.g3.wire.FrameSplitter`: every
    length a frame claims is checked against ``max_frame_bytes`` before it is
    kept, and spt3g decodes only complete, sound frames. A stream that
    breaks its framing (big-endian flag, unknown version, a claim over the
    budget, a cut-off frame) is counted in :attr:`rejected` by reason and the
    connection dropped and made again; a frame spt3g cannot decode (CRC) is
    counted and skipped.

    ``next()`` returns a list of frames (empty when nothing arrived within
    ``poll_s``, or at a file's end, then :attr:`finished`), or None while
    (re)connecting. Failed attempts back off from ``reconnect_s`` to
    ``reconnect_max_s``; ``max_reconnects`` failed attempts in a row (0:
    never) raise ConfigError.
    """

    def __init__(self, source: str, timeout_s: float = 10.0, reconnect_s: float = 1.0, max_reconnects: int = 0,
                 max_frame_bytes: int = 512 << 20, reconnect_max_s: float = 10.0, poll_s: float = 0.1):
        self.source = source
        self.network = source.startswith("tcp://")
        self.timeout_s, self.reconnect_s, self.max_reconnects = timeout_s, reconnect_s, max_reconnects
        self.reconnect_max_s, self.poll_s = max(reconnect_max_s, reconnect_s), poll_s
        self.max_frame_bytes = int(max_frame_bytes)
        self.rejected: dict[str, int] = {}
        self.state = "connecting"
        self.last_error = ""
        self.cause = ""  # what last_error is, in a word or two (one status warning per cause)
        self._sock = None
        self._split = None
        self._failures = 0
        self._t_retry = 0.0
        self._t_data = 0.0
        self._t_logged = -1e9
        self.connections = 0
        self.reconnects = 0
        self.connect_failures = 0
        self.finished = False
        if self.network:
            host, _, port = source[len("tcp://"):].rpartition(":")
            if not host or not port.isdigit() or not 0 < int(port) < 65536:
                raise ConfigError(f"g3-bridge: source {source!r}: expected tcp://HOST:PORT")
            self._addr = (host.strip("[]"), int(port))
        else:
            import itertools

            from mntes_stream.g3.files import expand_inputs
            from mntes_stream.g3.wire import iter_file_frames

            files = expand_inputs(source)
            self._frames = itertools.chain.from_iterable(
                iter_file_frames(f, self.max_frame_bytes, self.rejected) for f in files)

    def _count(self, reason: str) -> None:
        self.rejected[reason] = self.rejected.get(reason, 0) + 1

    def _open(self) -> None:
        import socket

        from mntes_stream.g3.wire import FrameSplitter

        now = time.monotonic()
        if now < self._t_retry:
            return
        try:
            sock = socket.create_connection(self._addr, timeout=min(self.timeout_s, 5.0))
        except OSError as exc:
            self._failures += 1
            self.connect_failures += 1
            delay = min(self.reconnect_s * 2 ** min(self._failures - 1, 30), self.reconnect_max_s)
            self._t_retry = now + delay
            self.state = "connecting"
            self.last_error = f"cannot connect: {exc.strerror or exc}"
            self.cause = "cannot connect"
            if self.max_reconnects and self._failures > self.max_reconnects:
                raise ConfigError(f"g3-bridge: {self.source}: {self.last_error} ({self._failures} attempts)") from None
            if now - self._t_logged >= 60 or self._failures == 1:  # one line a minute while the DAQ is away
                self._t_logged = now
                log.warning("g3-bridge: %s: %s (%d attempts); retrying, every %g s at most", self.source,
                            self.last_error, self._failures, delay)
            return
        sock.settimeout(self.poll_s)
        self._sock, self._split = sock, FrameSplitter(self.max_frame_bytes)
        self._t_data = now
        self.connections += 1
        self.reconnects += self.connections > 1
        self._failures = 0
        self.state, self.cause = "connected", ""
        log.info("g3-bridge: connected to %s", self.source)

    def _drop(self, why: str, cause: str) -> None:
        if self._sock is not None:
            self._sock.close()
        self._sock = self._split = None
        self.state = "connecting"
        self.last_error, self.cause = why, cause
        self._t_retry = time.monotonic() + self.reconnect_s
        log.warning("g3-bridge: %s: %s; reconnecting", self.source, why)

    def next(self):
        if not self.network:
            return self._next_file()
        if self._sock is None:
            self._open()
            if self._sock is None:
                return None
        from mntes_stream.g3.wire import BadFrame, decode_frame

        try:
            data = self._sock.recv(1 << 20)
        except TimeoutError:
            if time.monotonic() - self._t_data > self.timeout_s:
                self._drop(f"no data for {self.timeout_s:g} s", "silent")
                return None
            return []
        except OSError as exc:
            self._drop(f"connection lost ({exc.strerror or exc})", "connection lost")
            return None
        if not data:
            if self._split.pending():
                self._count("truncated")
                self._drop(f"closed by the sender in the middle of a frame ({self._split.pending()} bytes)",
                           "truncated")
            else:
                self._drop("closed by the sender", "")  # a DAQ stopping is no fault: reconnect quietly
            return None
        self._t_data = time.monotonic()
        self._split.feed(data)
        frames = []
        while True:
            try:
                raw = self._split.next()
            except BadFrame as exc:
                self._count(exc.reason)
                self._drop(f"{exc} ({exc.reason}): the stream has lost its framing", exc.reason)
                return frames
            if raw is None:
                return frames
            try:
                frames.append(decode_frame(raw))
            except BadFrame as exc:
                self._count(exc.reason)
                log.warning("g3-bridge: %s: %s; frame skipped", self.source, exc)

    def _next_file(self):
        frames = []
        for frame in self._frames:
            frames.append(frame)
            if len(frames) >= 64:
                return frames
        self.finished = True
        self.state = "finished"
        return frames

    def close(self) -> None:
        if self.network and self._sock is not None:
            self._sock.close()
        self._sock = None


class _OcsBath:
    """``hk``: the OCS thermometer's readings as t_bath messages, handed out as the data's time passes them."""

    def __init__(self, b: BridgeSettings):
        from mntes_stream.g3.ocs_hk import OcsFields, hk_from_files

        if not b.t_bath_field:
            raise ConfigError("g3-bridge: hk needs t_bath_field (the thermometer's full OCS field name)")
        self.key = keys.hk_key(b.setup, "t_bath")
        self._msgs = hk_from_files(b.hk, OcsFields(t_bath_field=b.t_bath_field), b.setup)
        self._next = 0

    def up_to(self, t_ns: int | None) -> list[tuple[str, bytes]]:
        """The readings not yet handed out up to ``t_ns`` and the first one after it (so samples are bracketed)."""
        if t_ns is None:
            return []
        out, msgs = [], self._msgs
        while self._next < len(msgs):
            t = msgs[self._next][0]
            if t > t_ns and self._next and msgs[self._next - 1][0] > t_ns:
                break  # the reading beyond t_ns went out already
            out.append(msgs[self._next])
            self._next += 1
            if t > t_ns:
                break
        return [(key, payload) for _, key, payload in out]


class G3BridgeService(Service):
    """SPT-3G readout (G3 frames) -> counts, bias and housekeeping messages on zenoh."""

    name = "g3-bridge"
    Config = G3BridgeConfig
    summary = "SPT-3G DfMux readout (G3 over TCP or a file) published as counts + housekeeping"

    def owns(self) -> dict:
        return {"source": self.config.bridge.source, "boards": list(self.config.bridge.boards) or "all"}

    def duration_s(self) -> float:
        return self.config.bridge.duration_s

    def setup(self, ctx) -> None:
        from mntes_stream.g3.translate import FrameTranslator

        b = self.config.bridge
        self._said: set = set()
        gref = None
        if b.params:
            from mntes_stream.io.paramfile import load_params

            gref = {d: abs(p.gain_a_per_count) for d, p in load_params(b.params).items()}
        self._tr = FrameTranslator(b.setup, self.config.g3, b.chunk_samples, b.boards, gain_reference=gref,
                                   max_held=b.max_held_frames)
        self._src = G3Source(b.source, b.timeout_s, b.reconnect_s, b.max_reconnects,
                             max_frame_bytes=int(b.max_frame_mb * 2**20), reconnect_max_s=b.reconnect_max_s)
        self._hk = _OcsBath(b) if b.hk else None
        self._first_data_ns = None
        self._waited = False

    def step(self, ctx) -> bool:
        b, tr, src, hk, pubs = self.config.bridge, self._tr, self._src, self._hk, ctx.publishers
        frames = src.next()
        if frames is None:  # (re)connecting: what the last connection gave goes out now
            for key, payload in tr.flush():
                pubs.put(key, payload)
            ctx.stop.wait(min(0.05, b.reconnect_s))
            self._beat(tr, src, pubs)
            return True
        if not frames and src.finished:
            return False
        out = []
        for frame in frames:
            out += tr.accept(frame)
        counts = [k for k, _ in out if keys.kind_of(k) == "counts"]
        if hk is not None:  # the bath from OCS HK files, up to the data's time (and one beyond)
            out = hk.up_to(tr._t_last_ns if counts else None) + [m for m in out if m[0] != hk.key]
        if counts and hk is None:
            t_last = tr._t_last_ns
            self._first_data_ns = self._first_data_ns or t_last
            if not len(tr.bath):
                if self.config.g3.t_bath_default_k is not None:
                    out = tr.default_bath(t_last) + out
                elif t_last - self._first_data_ns > b.bath_wait_s * 1e9:
                    tr.bath.require()  # the one-line error naming the thermometer setting
        if out and not self._waited and b.wait_subscribers_s > 0:
            self._waited = True
            pubs.wait_matching([k for k, _ in out], b.wait_subscribers_s, ctx.stop)
        for key, payload in out:
            pubs.put(key, payload)
        while tr.gain_changed_at:
            self.heartbeat.warn(f"DfMux gain changed at {tr.gain_changed_at.pop(0)} ns: the converter "
                                "keeps the gain of its parameters")
        self._beat(tr, src, pubs)
        return True

    def finish(self, ctx) -> dict:
        tr, src, pubs = self._tr, self._src, ctx.publishers
        try:
            for key, payload in tr.flush():
                pubs.put(key, payload)
            tr.drop_held()
        finally:
            src.close()
        result = self._beat(tr, src, pubs)
        log.info("g3-bridge stopped: %s", result)
        return result

    def _beat(self, tr, src, pubs) -> dict:
        c = tr.counters
        rejected = dict(src.rejected)
        for reason, n in c.rejected.items():
            rejected[reason] = rejected.get(reason, 0) + n
        led = bridge_ledger(tr.published(), c.stream_gaps, rejected, self.config.bridge.chunk_samples)
        # The status says so too: each cause once (the DAQ away, a kind of bad frame), not every time.
        causes = [(f"daq:{src.cause}", f"DAQ {src.source}: {src.last_error}")] if src.cause else []
        causes += [(f"frame:{r}", f"G3 frames rejected ({r}): {tr.last_error.get(r, 'see the log')}")
                   for r in rejected]
        for key, text in causes:
            if key not in self._said:
                self._said.add(key)
                self.heartbeat.warn(text)
        counters = {"frames": c.frames, "timepoints": c.timepoints, "scans": c.scans, "samples": c.samples,
                    "invalid_samples": c.invalid_samples, "gap_samples": c.gap_samples,
                    "housekeeping": c.housekeeping, "gain_changes": c.gain_changes, "bias_changes": c.bias_changes,
                    "bath_readings": c.bath_readings,
                    "messages": pubs.messages, "bytes": pubs.bytes, "connections": src.connections,
                    "reconnects": src.reconnects, "connect_failures": src.connect_failures,
                    "source_state": src.state, "source_error": src.last_error,
                    "rejected_frames": sum(rejected.values()), "rejected": rejected, "held_frames": tr.held,
                    "published": dict(sorted(tr.published().items())), "stream_gaps": dict(c.stream_gaps),
                    "ledger": led.as_dict(), "lost": led.lost}
        self.heartbeat.beat(**counters)
        return counters


def bridge_ledger(published: dict, stream_gaps: dict, rejected: dict, chunk_samples: int):
    """The bridge's :class:`~mntes_stream.core.ledger.Ledger` (verb ``published``).

    Per stream (``board/module``): the counts chunks published, and as never
    received the samples the DfMux clock says never arrived, in chunks of
    ``chunk_samples`` (rounded up). A rejected G3 frame cannot be told to a
    stream: each is a rejected chunk of the stream ``other``, by reason, so
    ``lost`` counts it.
    """
    from mntes_stream.core.ledger import OTHER, Ledger

    led = Ledger("published")
    for stream, n in published.items():
        led.received(stream, n)
        led.done(stream, n)
    for stream, n in stream_gaps.items():
        led.set_missing(stream, -(-int(n) // max(int(chunk_samples), 1)))
    for reason, n in rejected.items():
        if n:
            led.received(OTHER, n)
            led.rejected(OTHER, reason, n)
    return led


def ledger_line(result: dict) -> str:
    """The bridge's ledger in one line, from its result (or heartbeat): chunks published, never received,
    frames rejected by reason, lost; samples never received; connections. Nothing missed is left out."""
    from mntes_stream.core.ledger import Ledger

    led = Ledger.from_dict(result.get("ledger", {}), "published")
    text = f"g3-bridge done: {led.line()}"
    if result.get("rejected_frames"):
        text += " (rejected: G3 frames, in stream 'other')"
    text += f"; {result.get('gap_samples', 0)} samples never received"
    if result.get("connections") or result.get("connect_failures"):
        text += f"; {result.get('connections', 0)} connections, {result.get('connect_failures', 0)} failed attempts"
    return text
