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
import json
import queue
import socket
import threading
import time
from dataclasses import dataclass, fields
from typing import Iterable, Iterator

from mntes_stream.errors import ConfigError, TransportError

__all__ = [
    "ZenohSettings",
    "zenoh_config",
    "open_session",
    "free_tcp_port",
    "loopback",
    "Publishers",
    "QueueSubscriber",
]

_MODES = ("peer", "client", "router")


@dataclass(frozen=True)
class ZenohSettings:
    """How to join the zenoh network (the ``[zenoh]`` table of every service config).

    Attributes
    ----------
    mode : {"peer", "client", "router"}
    connect, listen : tuple of str
        Endpoints such as ``tcp/127.0.0.1:7447``. A peer given no ``listen``
        (and no config file) whose ``connect`` endpoints are all on loopback
        listens on ``tcp/127.0.0.1:0``, never on every interface.
    config_file : str
        zenoh JSON5 config read first (e.g. ``services/zenoh-lab.json5``);
        the fields above override it where given.
    scouting : bool
        Multicast and gossip scouting; off by default.
    gossip : bool
        Gossip scouting only (no multicast): peers learn each other's
        endpoints through the peers they are connected to and connect
        directly, so services that all connect to one peer form a full mesh.
        Without it (and without a router) a peer receives only from peers it
        is itself connected to: peers do not forward for each other.
    """

    mode: str = "peer"
    connect: tuple[str, ...] = ()
    listen: tuple[str, ...] = ()
    config_file: str = ""
    scouting: bool = False
    gossip: bool = False

    def __post_init__(self):
        if self.mode not in _MODES:
            raise ConfigError(f"zenoh mode must be one of {_MODES}, got {self.mode!r}")
        for name in ("connect", "listen"):
            value = getattr(self, name)
            if isinstance(value, str) or not all(isinstance(x, str) for x in value):
                raise ConfigError(f"zenoh {name} must be a list of endpoint strings, got {value!r}")
            object.__setattr__(self, name, tuple(value))

    @classmethod
    def from_dict(cls, d: dict, source: str = "[zenoh]", base_dir: str | None = None) -> "ZenohSettings":
        """From a config table; a relative ``config_file`` is resolved against ``base_dir``."""
        known = {f.name for f in fields(cls)}
        unknown = set(d) - known
        if unknown:
            raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)} (known: {sorted(known)})")
        d = dict(d)
        if d.get("config_file") and base_dir is not None:
            from pathlib import Path

            path = Path(d["config_file"])
            d["config_file"] = str(path if path.is_absolute() else Path(base_dir) / path)
        try:
            return cls(**d)
        except TypeError as exc:
            raise ConfigError(f"{source}: {exc}") from None


def zenoh_config(settings: ZenohSettings):
    """A ``zenoh.Config`` for ``settings`` (scouting off unless enabled)."""
    import zenoh

    try:
        conf = zenoh.Config.from_file(settings.config_file) if settings.config_file else zenoh.Config()
        conf.insert_json5("mode", json.dumps(settings.mode))
        if settings.connect:
            conf.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
        if settings.listen:
            conf.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
        elif settings.mode == "peer" and not settings.config_file and all(map(_is_loopback, settings.connect)):
            # zenoh's default would listen on every interface (tcp/[::]:0). A
            # peer must stay reachable for gossip, so: loopback, any free port.
            conf.insert_json5("listen/endpoints", json.dumps(["tcp/127.0.0.1:0"]))
        conf.insert_json5("scouting/multicast/enabled", json.dumps(bool(settings.scouting)))
        conf.insert_json5("scouting/gossip/enabled", json.dumps(bool(settings.scouting or settings.gossip)))
    except Exception as exc:  # zenoh raises ZError for unreadable files and bad values
        raise ConfigError(f"zenoh config ({settings}): {exc}") from None
    return conf


def _is_loopback(endpoint: str) -> bool:
    """Whether ``proto/host:port`` names this machine's loopback."""
    host = endpoint.split("/", 1)[-1].rsplit(":", 1)[0].strip("[]")
    return host in ("localhost", "::1") or host.startswith("127.")


def open_session(settings: ZenohSettings):
    """Open a session; use it as a context manager so it is always closed."""
    import zenoh

    conf = zenoh_config(settings)
    try:
        return zenoh.open(conf)
    except Exception as exc:  # e.g. a listen port already in use
        raise TransportError(
            f"cannot open zenoh session ({settings.mode}, listen={list(settings.listen)}, "
            f"connect={list(settings.connect)}): {exc}"
        ) from None



def free_tcp_port(host: str = "127.0.0.1") -> int:
    """A TCP port free right now on ``host`` (for tests and ``up``)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind((host, 0))
        return int(s.getsockname()[1])


def loopback(listen_port: int | None = None, connect_ports: Iterable[int] = ()) -> ZenohSettings:
    """Peer settings on 127.0.0.1: listen on one port, connect to others."""
    return ZenohSettings(
        mode="peer",
        listen=() if listen_port is None else (f"tcp/127.0.0.1:{int(listen_port)}",),
        connect=tuple(f"tcp/127.0.0.1:{int(p)}" for p in connect_ports),
    )


class Publishers:
    """One BLOCK publisher per key, declared on first use.

    Parameters
    ----------
    session : zenoh.Session
    block : bool
        BLOCK congestion control (default): never drop, slow down instead.
    """

    def __init__(self, session, block: bool = True):
        import zenoh

        self._session = session
        self._cc = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
        self._pubs: dict[str, object] = {}
        self.messages = 0
        self.bytes = 0

    def publisher(self, key: str):
        pub = self._pubs.get(key)
        if pub is None:
            try:
                pub = self._session.declare_publisher(key, congestion_control=self._cc)
            except Exception as exc:
                raise TransportError(f"cannot declare publisher on {key!r}: {exc}") from None
            self._pubs[key] = pub
        return pub

    def put(self, key: str, payload: bytes) -> None:
        self.publisher(key).put(payload)
        self.messages += 1
        self.bytes += len(payload)

    def wait_matching(self, keys: Iterable[str], timeout_s: float, stop=None) -> bool:
        """Wait until every key has a matching subscriber (True) or the timeout passes."""
        pubs = [self.publisher(k) for k in keys]
        deadline = time.monotonic() + timeout_s
        while True:
            # matching_status is a MatchingStatus object (always truthy): read .matching.
            if all(p.matching_status.matching for p in pubs):
                return True
            if time.monotonic() >= deadline or (stop is not None and stop.is_set()):
                return False
            time.sleep(0.005)

    def close(self) -> None:
        for pub in self._pubs.values():
            with contextlib.suppress(Exception):
                pub.undeclare()
        self._pubs.clear()


class QueueSubscriber:
    """Subscribe to key expressions; samples come out as ``(key, bytes, t_recv_ns)``.

    Two ways, same interface:

    - ``mode="callback"`` (default): a zenoh callback (its own Python thread)
      stamps each sample and puts it on a bounded queue; ``t_recv_ns`` is the
      arrival time. When the queue is full the callback waits: back-pressure
      travels upstream to BLOCK publishers instead of losing samples. After
      :meth:`close` (or once ``stop`` is set) a waiting callback gives up and
      counts the sample in ``dropped_on_close``, so a session can always close.
    - ``mode="channel"``: zenoh's own bounded FIFO channels, read from the
      caller's thread (no second Python thread competing for the GIL: lower
      latency in a busy converter); ``t_recv_ns`` is when the sample was
      taken. Key expressions are read in the order given, so a batch that put
      housekeeping before counts is read that way too. A full channel blocks
      zenoh's receive path: back-pressure as above.
    """

    def __init__(self, session, key_exprs: Iterable[str], maxsize: int = 4096, stop=None, mode: str = "callback"):
        if mode not in ("callback", "channel"):
            raise ConfigError(f"QueueSubscriber mode must be 'callback' or 'channel', got {mode!r}")
        self.mode = mode
        self._queue: queue.Queue = queue.Queue(maxsize=maxsize)
        self._closing = threading.Event()
        self._stop = stop
        self.received = 0
        self.dropped_on_close = 0
        self.high_water = 0
        self._subs = []
        self._leftover: collections.deque = collections.deque()
        for expr in key_exprs:
            try:
                if mode == "callback":
                    self._subs.append(session.declare_subscriber(expr, self._on_sample))
                else:
                    import zenoh

                    self._subs.append(session.declare_subscriber(expr, zenoh.handlers.FifoChannel(maxsize)))
            except Exception as exc:
                raise TransportError(f"cannot subscribe to {expr!r}: {exc}") from None

    def _on_sample(self, sample) -> None:
        item = (str(sample.key_expr), sample.payload.to_bytes(), time.time_ns())
        while True:
            try:
                self._queue.put(item, timeout=0.05)
                self.received += 1
                return
            except queue.Full:
                if self._closing.is_set() or (self._stop is not None and self._stop.is_set()):
                    self.dropped_on_close += 1
                    return

    def _poll(self):
        if self._leftover:
            return self._leftover.popleft()
        for sub in self._subs:
            sample = sub.try_recv()
            if sample is not None:
                self.received += 1
                return str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()
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
        return item

    def drain(self, limit: int = 1 << 30) -> Iterator[tuple[str, bytes, int]]:
        """What is queued now, without waiting (at most ``limit`` items)."""
        for _ in range(limit):
            item = self._poll() if self.mode == "channel" else self.get()
            if item is None:
                return
            yield item

    def qsize(self) -> int:
        return self._queue.qsize()

    def close(self) -> None:
        """Undeclare the subscribers; what was already received stays readable (:meth:`drain`)."""
        self._closing.set()
        for sub in self._subs:
            if self.mode == "channel":
                # Empty zenoh's channel first: a full one would hold up its receive thread.
                while (sample := sub.try_recv()) is not None:
                    self._leftover.append((str(sample.key_expr), sample.payload.to_bytes(), time.time_ns()))
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._subs.clear()
