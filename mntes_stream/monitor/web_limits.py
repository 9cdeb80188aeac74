"""Bounds on the monitor's sockets: how many, how long idle, and how much they may log.

aiohttp closes an idle keep-alive connection (``keepalive_timeout``) and
bounds request lines and headers (``max_line_size``, ``max_field_size``,
``max_headers``), but it has no limit on connections and no deadline for the
first request: a client that connects and sends nothing, or half a request
line, holds a descriptor for ``keepalive_timeout`` (an hour by default). With
1,100 such sockets under a 1,024-descriptor limit, ``accept`` failed with
EMFILE, ``/api/state`` timed out and asyncio logged a traceback per failed
accept (50,511 in 45 s). Here:

- :class:`ConnectionGuard` counts the connections. At ``max_connections``
  (capped below the process's descriptor limit) a new one evicts the oldest
  *idle* one (no request being handled: a page's websocket or a request in
  progress is never evicted), else it is closed at once; both counted. A
  connection that has not delivered a whole request within
  ``header_timeout_s`` is closed (counted).
- :class:`RateLog` logs one line per cause per interval (the first at once,
  then a count), never a traceback per connection; :meth:`RateLog.filter`
  does the same for aiohttp's and asyncio's own error logging.
"""

from __future__ import annotations

import asyncio
import logging
import os
import resource
import time
import weakref
from dataclasses import dataclass

from mntes_stream.core.settings import Settings, setting

__all__ = ["WebLimits", "ConnectionGuard", "RateLog", "descriptor_cap"]

log = logging.getLogger("mntes_stream.monitor")

# Descriptors kept free for everything else the process opens (zenoh, files, the page's assets).
_FD_RESERVE = 64


@dataclass(frozen=True)
class WebLimits(Settings):
    """The page server's socket limits (keys of the ``[monitor]`` table)."""

    max_connections: int = setting(256, "HTTP connections held at once (pages, API calls, idle keep-alives); at the "
                                   "limit a new one evicts the oldest idle one, else is closed at once (counted); "
                                   "capped below the process's descriptor limit", ge=2, le=65536)
    header_timeout_s: float = setting(5.0, "a connection that has not sent a whole request this long after it "
                                      "opened is closed (counted)", unit="s", gt=0, le=600)
    idle_timeout_s: float = setting(15.0, "a keep-alive connection idle this long between requests is closed",
                                    unit="s", gt=0, le=3600)
    log_interval_s: float = setting(10.0, "repeated socket events (refused, timed out, errors) are logged once per "
                                    "cause per interval, with their count", unit="s", gt=0, le=3600)
    backlog: int = setting(64, "connections the kernel queues before the page server accepts them (and the most "
                           "it accepts at once)", ge=1, le=4096)


def descriptor_cap(limit: int, backlog: int = 128, reserve: int = _FD_RESERVE) -> tuple[int, int | None]:
    """``limit`` capped to what the descriptor limit leaves: open now, ``reserve`` kept free, and ``backlog``.

    asyncio accepts up to ``backlog`` sockets in one go, and a socket closed (evicted or refused) frees its
    descriptor only on the loop's next turn: so ``limit + backlog`` descriptors may be held at once.

    Returns
    -------
    (int, int or None)
        The connection limit to use, and the soft RLIMIT_NOFILE (None if unlimited or unknown).
    """
    try:
        soft, _ = resource.getrlimit(resource.RLIMIT_NOFILE)
    except (OSError, ValueError):
        return limit, None
    if soft == resource.RLIM_INFINITY:
        return limit, None
    try:
        open_now = len(os.listdir("/proc/self/fd"))
    except OSError:
        open_now = 32
    return max(min(limit, soft - open_now - reserve - backlog), 2), int(soft)


class RateLog:
    """One log line per cause per interval: the first event at once, later ones as a count.

    Parameters
    ----------
    logger : logging.Logger
    interval_s : float
    clock : callable
        Seconds, monotonic (tests pass their own).
    """

    def __init__(self, logger: logging.Logger, interval_s: float = 10.0, clock=time.monotonic):
        self.logger = logger
        self.interval_s = float(interval_s)
        self.clock = clock
        self.counts: dict[str, int] = {}  # cause -> events since the process started
        self._pending: dict[str, list] = {}  # cause -> [events not yet logged, time of the last line, text]
        self.lines = 0

    def note(self, cause: str, text: str, n: int = 1, level: int = logging.WARNING) -> None:
        """``n`` events of ``cause``; ``text`` says what one event is (e.g. "connection refused over the limit")."""
        self.counts[cause] = self.counts.get(cause, 0) + n
        now = self.clock()
        p = self._pending.get(cause)
        if p is None:
            self._pending[cause] = [0, now, text, level]
            self._emit(level, f"monitor: {text} (repeats are counted and logged every {self.interval_s:g} s)")
            return
        p[0] += n
        p[2], p[3] = text, level
        if now - p[1] >= self.interval_s:
            self.flush(cause)

    def flush(self, only: str | None = None) -> None:
        """Log the count of every cause whose interval has passed (or ``only`` that one)."""
        now = self.clock()
        for cause, p in self._pending.items():
            if (only is None or cause == only) and p[0] and now - p[1] >= self.interval_s:
                self._emit(p[3], f"monitor: {p[0]:,} x {p[2]} in the last {now - p[1]:.0f} s")
                p[0], p[1] = 0, now

    def _emit(self, level: int, line: str) -> None:
        self.lines += 1
        self.logger.log(level, line)

    def filter(self, record: logging.LogRecord) -> bool:
        """A :class:`logging.Filter` for other libraries' loggers: their records become counted causes.

        The record is replaced by a line of its own (no traceback), at most once per cause per interval.
        """
        exc = record.exc_info[1] if record.exc_info else None
        try:
            what = record.getMessage()
        except (TypeError, ValueError):
            what = str(record.msg)
        cause = f"{record.name}:{record.msg}:{type(exc).__name__ if exc else ''}"
        text = f"{record.name}: {what}" + (f" ({type(exc).__name__}: {exc})" if exc else "")
        self.note(cause, text[:300], level=max(record.levelno, logging.WARNING))
        return False

    def loop_exception(self, loop, context: dict) -> None:
        """An asyncio exception handler: one line per cause (its message and exception type) per interval."""
        exc = context.get("exception")
        msg = str(context.get("message", "error"))
        text = f"asyncio: {msg}" + (f" ({type(exc).__name__}: {exc})" if exc else "")
        self.note(f"asyncio:{msg}:{type(exc).__name__ if exc else ''}", text[:300], level=logging.ERROR)


class ConnectionGuard:
    """Counts the page server's connections and enforces :class:`WebLimits` on them.

    Parameters
    ----------
    limits : WebLimits
    rate_log : RateLog
    max_connections : int, optional
        The limit to enforce (default ``limits.max_connections``; :func:`descriptor_cap` lowers it).
    """

    def __init__(self, limits: WebLimits, rate_log: RateLog, max_connections: int | None = None):
        self.limits = limits
        self.rate_log = rate_log
        self.max_connections = int(max_connections or limits.max_connections)
        # handler -> [t_opened or idle since, requests in progress, header timer or None, connected]; weak: a
        # handler made for an accepted socket whose transport then failed never hears connection_made.
        self.open: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()
        self.counts = {"accepted": 0, "over_limit": 0, "evicted_idle": 0, "header_timeout": 0}
        self.peak = 0

    def snapshot(self) -> dict:
        """What /api/state shows: open, limit, peak and the counters."""
        return {"open": len(self.open), "max_connections": self.max_connections, "peak": self.peak,
                **self.counts}

    def factory(self, server, loop, **handler_args):
        """A protocol factory for ``loop.create_server``: aiohttp's handler for ``server``, bounded."""
        from aiohttp.web_protocol import RequestHandler  # here: the settings above load without aiohttp (--text)

        guard = self

        class _Handler(RequestHandler):
            def connection_made(self, transport):
                super().connection_made(transport)
                guard._opened(self, transport, loop)

            def connection_lost(self, exc):
                guard._closed(self)
                super().connection_lost(exc)

        def make():
            if len(self.open) >= self.max_connections and not self._evict_idle():
                self.counts["over_limit"] += 1
                self.rate_log.note("over_limit", f"connection refused: {len(self.open)} open, the limit "
                                   f"(max_connections {self.max_connections})")
                return _Refused()
            handler = _Handler(server, loop=loop, **handler_args)
            # Counted from now: the loop accepts a burst of sockets before any of them is connection_made.
            self.open[handler] = [time.monotonic(), 0, None, False]
            self.peak = max(self.peak, len(self.open))
            return handler

        return make

    def _evict_idle(self) -> bool:
        idle = [(v[0], h) for h, v in self.open.items() if v[1] == 0 and v[3]]
        if not idle:
            return False
        _, handler = min(idle, key=lambda x: x[0])
        self.counts["evicted_idle"] += 1
        self.rate_log.note("evicted_idle", f"idle connection closed for a new one: {len(self.open)} open "
                           f"(max_connections {self.max_connections})")
        self._drop(handler)
        return True

    def _opened(self, handler, transport, loop) -> None:
        timer = loop.call_later(self.limits.header_timeout_s, self._header_expired, handler)
        self.open[handler] = [time.monotonic(), 0, timer, True]
        self.counts["accepted"] += 1

    def _closed(self, handler) -> None:
        entry = self.open.pop(handler, None)
        if entry is not None and entry[2] is not None:
            entry[2].cancel()

    def _header_expired(self, handler) -> None:
        entry = self.open.get(handler)
        if entry is None or entry[1] > 0 or entry[2] is None:
            return
        self.counts["header_timeout"] += 1
        self.rate_log.note("header_timeout", f"connection closed: no whole request within "
                           f"{self.limits.header_timeout_s:g} s (header_timeout_s)", level=logging.INFO)
        self._drop(handler)

    def _drop(self, handler) -> None:
        self._closed(handler)
        transport = handler.transport
        if transport is not None:
            transport.abort()  # frees the descriptor now: no closing handshake with a peer that sends nothing

    def begin(self, handler) -> None:
        """A request of ``handler`` reached the application: busy (never evicted), header deadline met."""
        entry = self.open.get(handler)
        if entry is not None:
            entry[1] += 1
            if entry[2] is not None:
                entry[2].cancel()
                entry[2] = None

    def end(self, handler) -> None:
        entry = self.open.get(handler)
        if entry is not None:
            entry[1] = max(entry[1] - 1, 0)
            entry[0] = time.monotonic()  # idle from now: the oldest idle is evicted first


class _Refused(asyncio.Protocol):
    """A connection over the limit: closed as soon as it is made."""

    def connection_made(self, transport):
        transport.abort()
