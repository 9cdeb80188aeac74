"""Who is alive on a setup: a zenoh liveliness token and a heartbeat queryable per service.

While a service runs, the session its lifecycle opens
(:meth:`Service.start <mntes_stream.service.base.Service.start>` passes its
:class:`Presence` to :func:`~mntes_stream.io.transport.open_session`, explicitly) declares

- a liveliness token ``mntes/<setup>/alive/<service>/<name>``: zenoh removes
  it when the session closes or the process dies, so a reader sees a service
  go within the transport's lease, with no heartbeat protocol of our own;
- a queryable on the same key answering the service's heartbeat (msgpack map:
  state, uptime, counters, what it owns, host, pid, zenoh id, warnings).

It also watches the session's ``connect`` endpoints: one that has no link
for ``dead_after_s`` is logged once and put in the heartbeat's warnings.
``mntes-stream ps`` reads tokens and heartbeats (:func:`list_services`).
"""

from __future__ import annotations

import contextlib
import logging
import os
import socket
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import msgpack

from mntes_stream.io import keys

__all__ = ["Presence", "announce", "join_watchers", "list_services", "DEAD_AFTER_S"]

log = logging.getLogger(__name__)

#: A connect endpoint with no link for this long is reported (once).
DEAD_AFTER_S = 5.0
_POLL_S = 0.25
_WATCHERS: list[tuple[threading.Thread, object]] = []  # (watch thread, its session)

@dataclass(frozen=True)
class Presence:
    """What a running service says about itself on zenoh.

    Parameters
    ----------
    setup, service, name : str
        The token is ``mntes/<setup>/alive/<service>/<name>``.
    snapshot : callable
        Returns the heartbeat (a dict of plain values); called per query.
    warn : callable
        Takes a warning (str) to keep in the heartbeat.
    dead_after_s : float
        How long a connect endpoint may stay without a link before it is reported.
    """

    setup: str
    service: str
    name: str
    snapshot: Callable[[], dict]
    warn: Callable[[str], None] = field(default=lambda _: None)
    dead_after_s: float = DEAD_AFTER_S

    @property
    def key(self) -> str:
        return keys.alive_key(self.setup, self.service, self.name)


def announce(session, connect: tuple[str, ...] = (), p: Presence | None = None) -> None:
    """Declare ``p`` (None: nothing) on ``session``; watch ``connect`` endpoints.

    Called by ``open_session``; everything declared here ends with the session.
    """
    if p is None:
        return
    zid = str(session.zid())
    me = {"host": socket.gethostname(), "pid": os.getpid(), "zid": zid}

    def on_query(query) -> None:
        try:
            body = {**p.snapshot(), **me, "t_ns": time.time_ns()}
            query.reply(p.key, msgpack.packb(body, default=str))
        except Exception:  # a querier that went away, or a snapshot that failed: nothing to answer
            pass

    try:
        queryable = session.declare_queryable(p.key, on_query)
        token = session.liveliness().declare_token(p.key)
    except Exception as exc:  # presence is a courtesy: the service runs without it, and says so
        log.warning("%s %s: cannot declare liveliness on %s: %s", p.service, p.name, p.key, exc)
        return
    # The token is undeclared when dropped: this thread holds it (and the queryable) as long as the session lives.
    watcher = threading.Thread(target=_watch, args=(session, p, connect, (token, queryable)),
                               name=f"presence-{p.service}", daemon=True)
    watcher.start()
    _WATCHERS.append((watcher, session))


def join_watchers(timeout_s: float = 2.0) -> None:
    """Wait for the watch threads of closed sessions to end (within ``timeout_s``).

    A daemon thread still inside a zenoh call when the interpreter exits is unwound by force, and the
    process aborts ("FATAL: exception not rethrown", exit -6) after a run that went well: a service
    (:meth:`Service.start <mntes_stream.service.base.Service.start>`) calls this once its session is closed.
    """
    deadline = time.monotonic() + timeout_s
    for watcher, session in list(_WATCHERS):
        try:
            closed = session.is_closed()
        except RuntimeError:  # being closed on another thread
            closed = True
        if not closed:
            continue
        watcher.join(max(0.0, deadline - time.monotonic()))
        if not watcher.is_alive():
            _WATCHERS.remove((watcher, session))


def _watch(session, p: Presence, connect: tuple[str, ...], _held) -> None:
    """Until the session closes (holding ``_held``): report once per outage each connect endpoint
    that has had no link for ``dead_after_s``."""
    wanted = {_normalised(e) for e in connect if e.startswith(("tcp/", "udp/", "tls/", "quic/"))}
    last_linked = dict.fromkeys(wanted, time.monotonic())
    down: set[str] = set()
    while True:
        try:
            if session.is_closed():
                return
        except RuntimeError:  # the session is being closed on another thread right now ("already borrowed")
            return
        time.sleep(_POLL_S)
        if not wanted:
            continue
        try:
            linked = {str(link.dst) for link in session.info.links()}
        except Exception:  # the session is closing
            continue
        now = time.monotonic()
        for endpoint in wanted:
            if endpoint in linked:
                if endpoint in down:
                    log.info("%s %s: connect endpoint %s reachable again", p.service, p.name, endpoint)
                    down.discard(endpoint)
                last_linked[endpoint] = now
            elif endpoint not in down and now - last_linked[endpoint] >= p.dead_after_s:
                msg = f"connect endpoint {endpoint} unreachable for {p.dead_after_s:g} s"
                log.warning("%s %s: %s", p.service, p.name, msg)
                p.warn(msg)
                down.add(endpoint)


def _normalised(endpoint: str) -> str:
    """``tcp/localhost:7447`` as links name it, ``tcp/127.0.0.1:7447`` (names resolved; IPv6 kept as given)."""
    proto, _, addr = endpoint.split("#")[0].partition("/")
    host, _, port = addr.rpartition(":")
    if host and not host.startswith("["):
        with contextlib.suppress(OSError):
            host = socket.gethostbyname(host)
    return f"{proto}/{host}:{port}"


def list_services(session, setup: str, timeout_s: float = 2.0) -> list[dict]:
    """The live services of ``setup``: one dict per liveliness token, with its heartbeat where it answered.

    Each dict has ``key``, ``service``, ``name`` and, when the service answered
    the heartbeat query in time, its heartbeat fields (``state``, ``uptime_s``,
    counters, ``owns``, ``host``, ``pid``, ``zid``, ``t_ns``, ``warnings``).
    """
    selector = keys.alive_key(setup, "*", "*")
    alive = set()
    for reply in session.liveliness().get(selector, timeout=timeout_s):
        if reply.ok is not None:
            alive.add(str(reply.ok.key_expr))
    beats: dict[str, list[dict]] = {}
    if alive:
        import zenoh

        for reply in session.get(selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s):
            if reply.ok is None:
                continue
            try:
                body = msgpack.unpackb(reply.ok.payload.to_bytes(), raw=False)
            except Exception:  # a peer answering nonsense on our key: listed without a heartbeat
                continue
            if isinstance(body, dict):
                beats.setdefault(str(reply.ok.key_expr), []).append(body)
    out = []
    for key in sorted(alive):
        parts = key.split("/")
        base = {"key": key, "service": parts[3], "name": parts[4]}
        for beat in beats.get(key) or [{}]:
            out.append({**beat, **base})
    return out
