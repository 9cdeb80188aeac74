"""zenoh at the edge: the one session/config builder, BLOCK publishers, a bounded subscriber queue.

Facts this module encodes (``ARCHITECTURE.md``, measured on zenoh 1.x):

- Scouting (multicast and gossip) is off unless asked for: explicit
  ``tcp/<host>:<port>`` endpoints behave the same on every network and in tests.
- Publishers here use ``CongestionControl.BLOCK``: the default DROP loses
  data silently when a subscriber (the recorder) falls behind.
- Sessions are always closed (context manager): a callback subscriber on an
  unclosed session hangs interpreter exit. Never fork with a session open:
  child processes are started with the ``spawn`` method.
- ``put`` takes bytes; subscribers get ``ZBytes`` (``.to_bytes()``).
"""

from __future__ import annotations

import collections
import contextlib
import dataclasses
import json
import logging
import os
import queue
import socket
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, fields

from mntes_stream.core.settings import setting
from mntes_stream.errors import ConfigError, TransportError
from mntes_stream.io import history, reconnect
from mntes_stream.io.presence import announce
from mntes_stream.io.zenoh_file import named_paths as _named_paths
from mntes_stream.io.zenoh_file import names_listen_endpoints as _names_listen_endpoints

log = logging.getLogger("mntes_stream.transport")

__all__ = [
    "ZenohSettings",
    "zenoh_config",
    "describe_config",
    "open_session",
    "free_tcp_port",
    "loopback",
    "Publishers",
    "QueueSubscriber",
    "answer",
]

_MODES = ("peer", "client", "router")
# zenoh's own router port: a router named by nothing else listens here, on loopback.
ROUTER_PORT = 7447


@dataclass(frozen=True)
class ZenohSettings:
    """How to join the zenoh network: the ``[zenoh]`` table of a config, and the zenoh flags.

    Layers, lowest first: built-in defaults < the zenoh JSON5 file
    (``config_file``, else ``$ZENOH_CONFIG``) < the ``[zenoh]`` table < the
    command line. A layer sets only what it names: a field left ``None`` (or
    ``cfg`` empty) leaves the lower layers' value alone. Built-in defaults,
    each applied only where neither the file nor a setting names it: peer
    mode, multicast and gossip scouting off, and listening on loopback only
    (``tcp/127.0.0.1:0``; a router ``tcp/127.0.0.1:7447``; clients do not
    listen).
    """

    config_file: str | None = setting(None, "zenoh JSON5 config file, read first (default: $ZENOH_CONFIG)", path=True)
    mode: str | None = setting(None, "peer, client or router (default peer)", choices=_MODES)
    connect: tuple[str, ...] | None = setting(None, "endpoints to connect to, e.g. tcp/127.0.0.1:7447")
    listen: tuple[str, ...] | None = setting(None, "endpoints to listen on (default: loopback only)")
    multicast_scouting: bool | None = setting(None, "multicast scouting (default off)")
    gossip: bool | None = setting(
        None, "gossip scouting: peers learn of each other through the peers they are connected to (default off)")
    cfg: tuple[str, ...] = setting((), "zenoh config changes KEY:VALUE (VALUE in JSON5), applied last")
    history_s: float | None = setting(
        None, "sources keep this much of each counts and housekeeping key for subscribers that start late or miss "
              "samples (a recorder or router restarting; io/history.py); memory: about this times the data rate "
              "(default 10 s; 0: none)", unit="s", ge=0)
    history_mb: float | None = setting(
        None, "... and at most this much per key: the samples a key's cache keeps are this divided by the size of "
              "its first message, when that is fewer than history_s holds (default 16 MB; 0: no cap in bytes)",
        unit="MB", ge=0)
    # zenoh retries peers' and routers' connections itself; a client does not open without its router
    # (io/reconnect.py): a service waits for it with this backoff.
    reconnect_min_s: float | None = setting(
        None, "a service in client mode whose router is unreachable at start retries after this long, "
              "doubling (default 0.5 s)", unit="s", gt=0)
    reconnect_max_s: float | None = setting(None, "... never waiting longer than this between tries (default 4 s)",
                                            unit="s", gt=0)
    reconnect_give_up_s: float | None = setting(
        None, "... and gives up (exit code 2) after this long without a router (default 0: never)", unit="s", ge=0)

    def __post_init__(self):
        for item in self.cfg:
            key, sep, _ = item.partition(":")
            if not sep or not key:
                raise ConfigError(f"zenoh cfg {item!r}: expected KEY:VALUE, e.g. transport/unicast/max_links:2")

    def over(self, base: ZenohSettings) -> ZenohSettings:
        """This layer on top of ``base``: what this one names wins; ``cfg`` entries add up."""
        named = {f.name: getattr(self, f.name) for f in fields(self) if f.name != "cfg" and getattr(self, f.name) is not None}
        return dataclasses.replace(base, **named, cfg=base.cfg + self.cfg)

    @property
    def history_seconds(self) -> float:
        """``history_s`` in force (10 s unless named)."""
        return 10.0 if self.history_s is None else float(self.history_s)

    @property
    def history_bytes(self) -> int:
        """``history_mb`` in force, in bytes (16 MB unless named; 0: no cap)."""
        return int((16.0 if self.history_mb is None else float(self.history_mb)) * 1e6)

    @property
    def file(self) -> str | None:
        """The zenoh config file in force: ``config_file``, else ``$ZENOH_CONFIG``, else none."""
        return self.config_file or os.environ.get("ZENOH_CONFIG") or None


def zenoh_config(settings: ZenohSettings):
    """The ``zenoh.Config`` for ``settings`` with every layer applied (see :class:`ZenohSettings`)."""
    import zenoh

    s = settings
    path = s.file
    named = _named_paths(path) if path else set()
    try:
        conf = zenoh.Config.from_file(path) if path else zenoh.Config()
        mode = s.mode or (json.loads(conf.get_json("mode")) if "mode" in named else None) or "peer"
        conf.insert_json5("mode", json.dumps(mode))
        if s.connect is not None:
            conf.insert_json5("connect/endpoints", json.dumps(list(s.connect)))
        if s.listen is not None:
            conf.insert_json5("listen/endpoints", json.dumps(list(s.listen)))
        for key, value in (("scouting/multicast/enabled", s.multicast_scouting), ("scouting/gossip/enabled", s.gossip)):
            if value is not None or key not in named:
                conf.insert_json5(key, json.dumps(bool(value)))
        for item in s.cfg:
            key, _, value = item.partition(":")
            conf.insert_json5(key, value)
        listen_named = s.listen is not None or "listen/endpoints" in named or any(map(_names_listen_endpoints, s.cfg))
        mode = json.loads(conf.get_json("mode"))
        if not listen_named and mode != "client":
            # zenoh's default listens on every interface (tcp/[::]:0, a router tcp/[::]:7447).
            port = ROUTER_PORT if mode == "router" else 0
            conf.insert_json5("listen/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    except Exception as exc:  # zenoh raises ZError for unreadable files and bad keys or values
        raise ConfigError(f"zenoh config ({path or 'no file'}): {str(exc).splitlines()[0] if str(exc) else exc!r}") from None
    return conf


def describe_config(conf) -> dict:
    """The parts of a ``zenoh.Config`` a person checks first (``config show``, logs)."""
    out = {}
    for key in ("mode", "connect/endpoints", "listen/endpoints", "scouting/multicast/enabled", "scouting/gossip/enabled"):
        try:
            out[key] = json.loads(conf.get_json(key))
        except Exception:  # a key this zenoh version does not have
            continue
    return out


def open_session(settings: ZenohSettings, *, presence=None, retrying=None):
    """Open a session; use it as a context manager so it is always closed.

    ``presence`` (``io/presence.Presence``) is announced on it; with ``retrying``
    (``io/reconnect.Retrying``) a client whose router is unreachable waits for it.
    Both are passed explicitly by the ``Service`` lifecycle (``service/base.py``);
    None: not announced, and a client without its router fails at once.
    """
    import zenoh

    conf = zenoh_config(settings)
    named = describe_config(conf)
    try:
        session = reconnect.open_or_wait(zenoh.open, conf, named, settings, retrying)
    except TransportError:  # stopped while waiting for the router, or gave up
        raise
    except Exception as exc:  # e.g. a listen port already in use
        raise TransportError(
            f"cannot open zenoh session (mode {named.get('mode')}, listen {named.get('listen/endpoints')}, "
            f"connect {named.get('connect/endpoints')}): {str(exc).splitlines()[0] if str(exc) else exc!r}"
        ) from None
    # A running service is seen on every session it opens (liveliness token, heartbeat, dead endpoints).
    announce(session, tuple(named.get("connect/endpoints") or ()), presence)
    return session



def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` (for tests and ``up``)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def loopback(listen_port: int | None = None, connect_ports: Iterable[int] = ()) -> ZenohSettings:
    """Peer settings on 127.0.0.1: listen on one port, connect to others."""
    return ZenohSettings(
        mode="peer",
        listen=None if listen_port is None else (f"tcp/127.0.0.1:{int(listen_port)}",),
        connect=tuple(f"tcp/127.0.0.1:{int(p)}" for p in connect_ports),
    )


def answer(session, key: str, payload: bytes):
    """A queryable on ``key`` that replies ``payload`` (bytes, or a callable giving them) to every query.

    Returns the queryable (undeclared when the session closes)."""

    import zenoh

    from mntes_stream.io.describe import zenoh_encoding

    encoding = zenoh.Encoding(zenoh_encoding(key))

    def on_query(query) -> None:
        try:
            query.reply(key, payload() if callable(payload) else payload, encoding=encoding)
        except Exception:  # a querier that went away: nothing to answer
            pass

    try:
        return session.declare_queryable(key, on_query)
    except Exception as exc:
        raise TransportError(f"cannot declare queryable on {key!r}: {exc}") from None


class Publishers:
    """One BLOCK publisher per key, declared on first use.

    Each publisher sets the sample encoding ``application/msgpack;schema=<name>.v<version>``
    (``io/describe.py``): a subscriber knows what a payload is before decoding it.

    Parameters
    ----------
    session : zenoh.Session
    block : bool
        BLOCK congestion control (default): never drop, slow down instead.
    history_chunks : int
        Counts and housekeeping keys keep this many samples for late or recovering
        subscribers (``io/history.py``: zenoh's AdvancedPublisher); 0: plain publishers.
    history_bytes : int
        ... and at most this many bytes each: a key's cache keeps ``history_bytes`` / (its first message's
        size) samples when that is fewer (0: no cap in bytes).
    observer : callable, optional
        ``observer(key, payload)`` sees every message put (a service's metrics, passed by its lifecycle).
    """

    def __init__(self, session, block: bool = True, history_chunks: int = 0, observer=None, history_bytes: int = 0):
        import zenoh

        self._session = session
        self._cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._pubs: dict[str, object] = {}
        self._history = int(history_chunks)
        self._history_bytes = int(history_bytes)
        self._said_capped = False
        self.messages = 0
        self.bytes = 0
        self._observe = observer

    def publisher(self, key: str, size: int = 0):
        """The publisher on ``key``, declared now if new; ``size``: its messages' size (bytes), which bounds
        a history cache in bytes (0: not known, the cache is bounded in samples only)."""
        pub = self._pubs.get(key)
        if pub is None:
            import zenoh

            from mntes_stream.io.describe import zenoh_encoding

            try:
                if self._history and history.wants_history(key):
                    n = history.capped_chunks(self._history, self._history_bytes, size)
                    if n < self._history and not self._said_capped:  # once: every key of a source is alike
                        self._said_capped = True
                        log.info("history of %s: %d messages of %.2f MB kept, not %d: [zenoh] history_mb (%.0f MB "
                                 "per key) holds fewer than history_s", key, n, size / 1e6, self._history,
                                 self._history_bytes / 1e6)
                    pub = history.declare_history_publisher(
                        self._session, key, zenoh.Encoding(zenoh_encoding(key)), self._cc, n)
                else:
                    pub = self._session.declare_publisher(key, congestion_control=self._cc,
                                                          encoding=zenoh.Encoding(zenoh_encoding(key)))
            except Exception as exc:
                raise TransportError(f"cannot declare publisher on {key!r}: {exc}") from None
            self._pubs[key] = pub
        return pub

    def put(self, key: str, payload: bytes) -> None:
        self.publisher(key, len(payload)).put(payload)
        self.messages += 1
        self.bytes += len(payload)
        if self._observe is not None:
            self._observe(key, payload)

    def wait_matching(self, keys: Iterable[str], timeout_s: float, stop=None) -> bool:
        """Wait until every key has a matching subscriber (True) or the timeout passes."""
        # An AdvancedPublisher has no matching status, and one not yet declared waits for its first message (its
        # size bounds the cache): a plain publisher on its key asks for it.
        keys = list(keys)
        pubs = [self._pubs.get(k) or (None if self._history and history.wants_history(k) else self.publisher(k))
                for k in keys]
        probes = [self._session.declare_publisher(k) for k, p in zip(keys, pubs) if not hasattr(p, "matching_status")]
        pubs = [p for p in pubs if hasattr(p, "matching_status")] + probes
        deadline = time.monotonic() + timeout_s
        try:
            while True:
                # matching_status is a MatchingStatus object (always truthy): read .matching.
                if all(p.matching_status.matching for p in pubs):
                    return True
                if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                    return False
                time.sleep(0.005)
        finally:
            for p in probes:
                with contextlib.suppress(Exception):
                    p.undeclare()

    def close(self) -> None:
        for pub in self._pubs.values():
            with contextlib.suppress(Exception):
                pub.undeclare()
        self._pubs.clear()


def _item(sample) -> tuple[str, bytes, int]:
    return str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()


def _item_with_source(sample) -> tuple[str, bytes, int, str | None]:
    info = sample.source_info
    return (str(sample.key_expr), sample.payload.to_bytes(), time.time_ns(),
            str(info.source_id.zid) if info is not None else None)


class QueueSubscriber:
    """Subscribe to key expressions; samples come out as ``(key, bytes, t_recv_ns)``.

    Two ways, same interface:

    - ``mode="callback"`` (default): a zenoh callback (its own Python thread)
      stamps each sample and puts it on a bounded queue; ``t_recv_ns`` is the
      arrival time. When the queue is full the callback waits: back-pressure
      travels upstream to BLOCK publishers instead of losing samples. After
      :meth:`close` (or once ``stop`` is set) a waiting callback gives up and
      counts the sample in ``dropped_on_close``, so a session can always close.
      Each key expression's callback runs in a thread of its own (zenoh-python's
      indirect callbacks), so samples of one key expression keep their order but
      two key expressions' samples may interleave otherwise than they were sent
      (a status overtaking the power published just before it).
    - ``mode="channel"``: zenoh's own bounded FIFO channels, read from the
      caller's thread (no second Python thread competing for the GIL: lower
      latency in a busy converter); ``t_recv_ns`` is when the sample was
      taken. Key expressions are read in the order given, so a batch that put
      housekeeping before counts is read that way too. A full channel blocks
      zenoh's receive path: back-pressure as above.

    ``sources=True``: items are ``(key, bytes, t_recv_ns, source)``, ``source``
    the zenoh id of the session that published the sample (its source info,
    which zenoh's ``AdvancedPublisher`` sets: ``io/history.py``), None when the
    sample has none; two publishers on one key tell apart by it
    (``core.sequence.PublisherSequences``).
    """

    def __init__(self, session, key_exprs: Iterable[str], maxsize: int = 4096, stop=None, mode: str = "callback",
                 max_bytes: int = 0, recover: str = "", sources: bool = False):
        if mode not in ("callback", "channel"):
            raise ConfigError(f"QueueSubscriber mode must be 'callback' or 'channel', got {mode!r}")
        if max_bytes and mode != "callback":
            raise ConfigError("QueueSubscriber max_bytes needs mode='callback'")
        self.mode = mode
        self._item = _item_with_source if sources else _item
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)
        # Payload bytes queued, bounded by max_bytes (0: by count only): a queue of big messages
        # must not hold gigabytes. Full means the callback waits, as for a full count.
        self.max_bytes = int(max_bytes)
        self.queued_bytes = 0
        self.high_water_bytes = 0
        self._bytes_free = threading.Condition()
        self._closing = threading.Event()
        self._stop = stop
        self.received = 0
        self.dropped_on_close = 0
        self.high_water = 0
        self._subs = []
        self._leftover: collections.deque = collections.deque()
        if recover not in ("", "recovery", "history"):
            raise ConfigError(f"QueueSubscriber recover must be '', 'recovery' or 'history', got {recover!r}")
        # With history: a key whose history zenoh-ext dropped (a live sample came first) is asked of its
        # publisher's cache again as its first message is taken (callback mode: the replies join the queue).
        self._top_up = history.HistoryTopUp(session, self, time.time_ns()) \
            if recover == "history" and mode == "callback" else None
        for expr in key_exprs:
            try:
                import zenoh

                handler = self._on_sample if mode == "callback" else zenoh.handlers.FifoChannel(maxsize)
                if recover:  # samples missed (or, with history, published before we came) from the publishers' caches
                    self._subs.append(history.declare_recovering_subscriber(session, expr, handler, recover == "history"))
                else:
                    self._subs.append(session.declare_subscriber(expr, handler))
            except Exception as exc:
                raise TransportError(f"cannot subscribe to {expr!r}: {exc}") from None

    def _on_sample(self, sample) -> None:
        item = self._item(sample)
        if self.max_bytes and not self._reserve(len(item[1])):
            self.dropped_on_close += 1
            return
        while True:
            try:
                self._queue.put(item, timeout=0.05)
                self.received += 1
                return
            except queue.Full:
                if self._closing.is_set() or (self._stop is not None and self._stop.is_set()):
                    self.dropped_on_close += 1
                    if self.max_bytes:
                        with self._bytes_free:
                            self.queued_bytes -= len(item[1])
                    return

    def _reserve(self, n: int) -> bool:
        """Wait until ``n`` more bytes fit (one message always fits an empty queue); False once closing."""
        with self._bytes_free:
            while self.queued_bytes and self.queued_bytes + n > self.max_bytes:
                if self._closing.is_set() or (self._stop is not None and self._stop.is_set()):
                    return False
                self._bytes_free.wait(0.05)
            self.queued_bytes += n
            self.high_water_bytes = max(self.high_water_bytes, self.queued_bytes)
            return True

    def query(self, session, selector: str, timeout_s: float = 2.0, keep=None) -> None:
        """Ask the queryables under ``selector`` (e.g. a converter's provenance) once; their replies
        (those whose payload ``keep(payload)`` accepts, if given) join this queue as samples. Returns at
        once (callback mode only)."""
        import zenoh

        if self.mode != "callback":
            raise ConfigError("QueueSubscriber.query needs mode='callback'")

        def on_reply(reply) -> None:
            if reply.ok is not None and (keep is None or keep(reply.ok.payload.to_bytes())):
                self._on_sample(reply.ok)

        try:
            # Replies under any key: a publisher's cache answers on its samples' own keys, not the query's.
            session.get(selector, on_reply, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s,
                        accept_replies=zenoh.ReplyKeyExpr.ANY)
        except Exception as exc:
            raise TransportError(f"cannot query {selector!r}: {exc}") from None

    def _poll(self):
        if self._leftover:
            return self._leftover.popleft()
        for sub in self._subs:
            sample = sub.try_recv()
            if sample is not None:
                self.received += 1
                return self._item(sample)
        return None

    def get(self, timeout_s: float | None = None):
        """Next ``(key, payload, t_recv_ns)`` or None after ``timeout_s`` (None/0: do not wait)."""
        if self.mode == "channel":
            item = self._poll()
            if item is None and timeout_s:
                deadline = time.monotonic() + timeout_s
                while item is None and time.monotonic() < deadline:
                    time.sleep(0.0005)  # zenoh's channels have no timed receive
                    item = self._poll()
            return item
        try:
            item = self._queue.get(timeout=timeout_s) if timeout_s else self._queue.get_nowait()
        except queue.Empty:
            return None
        self.high_water = max(self.high_water, self._queue.qsize() + 1)
        if self.max_bytes:
            with self._bytes_free:
                self.queued_bytes -= len(item[1])
                self._bytes_free.notify()
        if self._top_up is not None and not self._closing.is_set() \
                and (said := self._top_up.first(item[0], item[1])) is not None:
            log.warning("%s", said)
        return item

    def drain(self, limit: int = 1 << 30, max_bytes: int = 0) -> Iterator[tuple[str, bytes, int]]:
        """What is queued now, without waiting (at most ``limit`` items; callback mode: and no more once
        ``max_bytes`` of payload are out, 0: no such cap).

        A batch taken out of a queue bounded in bytes frees room that the
        callback fills again at once: the caller holding the batch holds up to
        ``max_bytes`` more. In channel mode each key expression's channel is
        emptied in the order given (one pass over them, however many: a converter shard may hold
        hundreds), so housekeeping listed first still comes before counts.
        """
        if self.mode != "channel":
            out_bytes = 0
            for _ in range(limit):
                if max_bytes and out_bytes >= max_bytes:
                    return
                item = self.get()
                if item is None:
                    return
                out_bytes += len(item[1])
                yield item
            return
        n = 0
        while self._leftover and n < limit:
            n += 1
            yield self._leftover.popleft()
        for sub in self._subs:
            while n < limit:
                sample = sub.try_recv()
                if sample is None:
                    break
                n += 1
                self.received += 1
                yield self._item(sample)

    def qsize(self) -> int:
        return self._queue.qsize()

    def close(self) -> None:
        """Undeclare the subscribers; what was already received stays readable (:meth:`drain`)."""
        self._closing.set()
        for sub in self._subs:
            if self.mode == "channel":
                # Empty zenoh's channel first: a full one would hold up its receive thread.
                while (sample := sub.try_recv()) is not None:
                    self._leftover.append(self._item(sample))
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._subs.clear()
