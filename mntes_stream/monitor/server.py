"""The monitor's web edge: an aiohttp server pushing updates to the page over a websocket.

Routes::

    GET /                   the page (static/index.html)
    GET /static/<file>      its script and style; plotly.min.js comes from the
                            installed ``plotly`` package (no CDN, works offline)
    GET /api/state          the latest shared update (JSON), for scripts and curl
    GET /api/view?ch=ID&ch=ID[&f_hwp=0.77|auto]   time streams + spectra (JSON)
    GET /ws                 websocket: the server sends ``update`` messages every
                            ``update_s``; the page sends ``select``, ``f_hwp``,
                            ``window``, ``focal`` and ``rendered`` (see static/monitor.js)

One ticker classifies the channels and builds the shared part of the update
once per period; each page then gets its own selected channels reduced on the
server (:meth:`Aggregator.view`), so what travels is what is drawn.

Locked down (:class:`WebGuard`): every request must name an allowed ``Host``
(loopback names, the bind address, ``allowed_hosts``: a DNS-rebinding page
names its own), a request with an ``Origin`` (every websocket a browser opens)
must come from the page's own origin, and a browser's cross-site request
(``Sec-Fetch-Site: cross-site``) is refused; responses forbid framing and
cross-origin reads. Each websocket client has a send queue of one update (a
slow client skips ticks, never piles them up) and is closed when one update
takes longer than ``send_timeout_s`` to go out.

Bounded (:mod:`~mntes_stream.monitor.web_limits`): a connection limit below
the descriptor limit (the oldest idle connection makes way for a new one), a
deadline for the first request (``header_timeout_s``), aiohttp's keep-alive
timeout (``idle_timeout_s``), and one log line per cause per interval.
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import math
import signal
import socket
import threading
import time
from importlib import resources
from pathlib import Path

from aiohttp import WSMsgType, web

from mntes_stream.errors import ConfigError
from mntes_stream.monitor.web_limits import ConnectionGuard, RateLog, WebLimits, descriptor_cap

__all__ = ["WebGuard", "is_loopback", "plotly_js_path", "make_app", "serve", "PageServer"]

log = logging.getLogger("mntes_stream.monitor")

STATIC = Path(__file__).resolve().parent / "static"
_STATIC_FILES = {"monitor.js": "text/javascript", "monitor.css": "text/css"}


def is_loopback(host: str) -> bool:
    """True for localhost, 127.0.0.0/8 and ::1."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


_LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")
_FOCAL_METRICS = ("state", "power_pw", "flag_pct", "noise_aw_rthz", "linear_nl_per_pw")
_WINDOWS_S = (30.0, 300.0, 3600.0)

# No framing, no cross-origin reads, nothing loaded from elsewhere (plotly is served from the wheel).
_SECURITY_HEADERS = {
    "Content-Security-Policy": ("default-src 'self'; style-src 'self' 'unsafe-inline'; img-src 'self' data: blob:; "
                                "connect-src 'self'; frame-ancestors 'none'; base-uri 'none'; form-action 'none'"),
    "X-Frame-Options": "DENY",
    "X-Content-Type-Options": "nosniff",
    "Cross-Origin-Resource-Policy": "same-origin",
    "Cross-Origin-Opener-Policy": "same-origin",
    "Referrer-Policy": "no-referrer",
}


def _split_host(value: str) -> tuple[str, str | None]:
    """``host[:port]`` or ``[v6][:port]`` -> (lower-case host without brackets, port or None)."""
    value = value.strip().lower()
    if value.startswith("["):
        host, _, rest = value[1:].partition("]")
        return host, rest[1:] if rest.startswith(":") else None
    if value.count(":") == 1:
        host, port = value.split(":")
        return host, port
    return value, None


class WebGuard:
    """Which ``Host`` and ``Origin`` headers the page answers (see the module docstring).

    Parameters
    ----------
    bind : str
        The listen address; allowed as a host name unless it is a wildcard.
    allowed_hosts : tuple of str
        Further names the page may be reached as (e.g. the machine's DNS
        name when ``bind`` is not loopback); loopback names always are.
    """

    def __init__(self, bind: str = "127.0.0.1", allowed_hosts: tuple[str, ...] = ()):
        hosts = set(_LOOPBACK_NAMES)
        if bind not in ("0.0.0.0", "::", ""):
            hosts.add(_split_host(bind)[0] if bind.startswith("[") else bind.lower())
        hosts.update(_split_host(h)[0] for h in allowed_hosts)
        self.hosts = frozenset(hosts)

    def refusal(self, headers) -> str | None:
        """Why a request with these headers is refused, or None."""
        host_header = headers.get("Host", "")
        host, _ = _split_host(host_header)
        if host not in self.hosts:
            return f"Host {host_header!r} is not allowed (allowed_hosts)"
        if headers.get("Sec-Fetch-Site", "") == "cross-site":
            return "cross-site request"
        origin = headers.get("Origin")
        if origin is not None:
            scheme, _, rest = origin.partition("://")
            if scheme not in ("http", "https") or rest.lower() != host_header.strip().lower():
                return f"Origin {origin!r} is not this page's"
        return None


def plotly_js_path() -> Path:
    """The plotly.js bundle shipped inside the ``plotly`` pip package."""
    try:
        path = Path(str(resources.files("plotly") / "package_data" / "plotly.min.js"))
    except ModuleNotFoundError:
        raise ConfigError("the monitor needs plotly: pip install 'mntes-stream[monitor]'") from None
    if not path.is_file():
        raise ConfigError(f"plotly is installed but {path} is missing")
    return path


def _dumps(obj) -> str:
    # allow_nan=False: a NaN that slipped through is a bug, not invalid JSON for the page.
    return json.dumps(obj, separators=(",", ":"), allow_nan=False)


class _Hub:
    """The ticker's latest shared update and a way to wait for the next one."""

    def __init__(self):
        self.seq = 0
        # (tick, layout): the shared update and the grid rows its state codes refer to, replaced as one.
        self.snapshot: tuple[dict, list] | None = None
        self._event = asyncio.Event()

    def publish(self, tick: dict, layout: list) -> None:
        self.seq += 1
        self.snapshot = (tick, layout)
        self._event.set()
        self._event = asyncio.Event()

    async def wait(self, seen: int) -> None:
        """Return once an update newer than ``seen`` exists."""
        while self.seq == seen:
            await self._event.wait()


_HUB = web.AppKey("hub", _Hub)
_TICKER = web.AppKey("ticker", asyncio.Task)


def _parse_f_hwp(value):
    """"auto" -> None (estimate), a positive number -> float, "config" stays; else ConfigError."""
    if value in ("config", None, ""):
        return "config"
    if value == "auto":
        return None
    try:
        f = float(value)
    except (TypeError, ValueError):
        f = math.nan
    if not (math.isfinite(f) and f > 0):
        raise ConfigError(f"f_HWP must be a positive number or 'auto', got {value!r}")
    return f


def make_app(subscriber, update_s: float = 0.5, guard: WebGuard | None = None, max_clients: int = 32,
             send_timeout_s: float = 10.0, connections: ConnectionGuard | None = None, rate_log: RateLog | None = None):
    """The aiohttp application serving ``subscriber`` (a :class:`MonitorSubscriber`).

    Parameters
    ----------
    subscriber : MonitorSubscriber
        Anything with ``view(selection, f_hwp)``, ``lock`` and ``aggregator``.
    update_s : float
        Update period of the page (the ticker's period).
    guard : WebGuard, optional
        Allowed hosts and origins (default: loopback only).
    max_clients : int
        Websocket clients served at once; more get HTTP 503.
    send_timeout_s : float
        A client that takes longer than this to accept one update is closed.
    connections : ConnectionGuard, optional
        Told when a request starts and ends (a connection handling one is never evicted); shown in /api/state.
    rate_log : RateLog, optional
        Where repeated refusals are logged (one line per cause per interval).
    """
    plotly_js = plotly_js_path()
    rate_log = rate_log or RateLog(log)

    def failed(cause: str, exc: BaseException) -> None:
        # The first of a cause with its traceback (a bug to report), the rest counted: a tick every 0.5 s or
        # an update per page must not flood the log.
        first = cause not in rate_log.counts
        rate_log.note(cause, f"{cause.replace('_', ' ')}: {type(exc).__name__}: {exc}"[:300], level=logging.ERROR)
        if first:
            log.error("monitor: %s, traceback of the first:", cause.replace("_", " "), exc_info=exc)
    guard = guard or WebGuard()
    clients: set = set()
    refused: dict[str, int] = {"host_or_origin": 0, "too_many_clients": 0, "slow_client": 0}

    @web.middleware
    async def lock_down(request, handler):
        why = guard.refusal(request.headers)
        if why is not None:
            refused["host_or_origin"] += 1
            rate_log.note("host_or_origin", f"refused {request.method} {request.path[:100]}: {why[:200]}")
            raise web.HTTPForbidden(text=why, headers=_SECURITY_HEADERS)
        if connections is not None:
            connections.begin(request.protocol)
        try:
            resp = await handler(request)
        except web.HTTPException as exc:
            exc.headers.update(_SECURITY_HEADERS)
            raise
        finally:
            if connections is not None:
                connections.end(request.protocol)
        if not resp.prepared:  # a websocket's handshake went out already
            resp.headers.update(_SECURITY_HEADERS)
        return resp

    def _tick():
        with subscriber.lock:
            return subscriber.aggregator.tick(time.time_ns()), subscriber.aggregator.layout()

    async def ticker(app):
        hub = app[_HUB]
        try:
            while True:
                t0 = time.monotonic()
                try:
                    hub.publish(*await asyncio.to_thread(_tick))
                except Exception as exc:  # keep ticking: one bad tick must not freeze every page
                    failed("tick_failed", exc)
                await asyncio.sleep(max(update_s - (time.monotonic() - t0), 0.01))
        except asyncio.CancelledError:
            pass

    async def on_startup(app):
        app[_HUB] = _Hub()
        app[_TICKER] = asyncio.create_task(ticker(app))

    async def on_shutdown(app):
        app[_TICKER].cancel()
        for ws in list(clients):
            await ws.close()

    async def index(request):
        return web.FileResponse(STATIC / "index.html", headers={"Cache-Control": "no-cache"})

    async def static(request):
        name = request.match_info["name"]
        if name == "plotly.min.js":
            return web.FileResponse(plotly_js, headers={"Cache-Control": "max-age=86400"})
        if name not in _STATIC_FILES:
            raise web.HTTPNotFound()
        return web.FileResponse(STATIC / name, headers={"Cache-Control": "no-cache", "Content-Type": _STATIC_FILES[name]})

    async def api_state(request):
        hub = request.app[_HUB]
        tick, layout = hub.snapshot or ({}, [])
        web_state = {"clients": len(clients), "refused": dict(refused)}
        if connections is not None:
            web_state["connections"] = connections.snapshot()
        body = {"seq": hub.seq, "layout": layout, **tick, "web": web_state}
        return web.Response(text=_dumps(body), content_type="application/json")

    async def api_view(request):
        try:
            f_hwp = _parse_f_hwp(request.query.get("f_hwp"))
        except ConfigError as exc:
            raise web.HTTPBadRequest(text=str(exc)) from None
        view = await asyncio.to_thread(subscriber.view, request.query.getall("ch", []), f_hwp)
        return web.Response(text=_dumps(view), content_type="application/json")

    async def ws_handler(request):
        if len(clients) >= max_clients:
            refused["too_many_clients"] += 1
            rate_log.note("too_many_clients", f"refused a page: {max_clients} already (max_clients)")
            raise web.HTTPServiceUnavailable(text=f"monitor: {max_clients} clients already (max_clients)")
        ws = web.WebSocketResponse(heartbeat=30.0, max_msg_size=1 << 16)
        await ws.prepare(request)
        clients.add(ws)
        hub = request.app[_HUB]
        client = {"selection": None, "f_hwp": "config", "window_s": None, "focal": "state", "layout_version": -1,
                  "wake": asyncio.Event()}

        async def send_loop():
            seen = 0
            while not ws.closed:
                # Wait for the next tick or a change of this page's selection, whichever first.
                wake = asyncio.create_task(client["wake"].wait())
                tick = asyncio.create_task(hub.wait(seen))
                try:
                    await asyncio.wait({wake, tick}, return_when=asyncio.FIRST_COMPLETED)
                finally:  # also when this loop is cancelled: no waiter left pending
                    for task in (wake, tick):
                        task.cancel()
                client["wake"].clear()
                if hub.snapshot is None:
                    continue
                seen = hub.seq
                try:
                    msg = await asyncio.to_thread(_update, hub, client)
                except Exception as exc:  # tell the page, keep serving it
                    failed("update_failed", exc)
                    msg = _dumps({"type": "error", "message": f"server: {type(exc).__name__}: {exc}"})
                try:
                    await asyncio.wait_for(ws.send_str(msg), send_timeout_s)
                except ConnectionError:  # the page went away (aiohttp's ClientConnectionResetError is one)
                    return
                except TimeoutError:
                    refused["slow_client"] += 1
                    rate_log.note("slow_client", f"closed a page that took over {send_timeout_s:g} s to take one update "
                                  "(send_timeout_s)")
                    # A peer that reads nothing never completes a closing handshake either: drop the transport.
                    if request.transport is not None:
                        request.transport.abort()
                    return

        def _update(hub, client) -> str:
            tick, layout = hub.snapshot
            with subscriber.lock:
                agg = subscriber.aggregator
                selection = client["selection"]
                if selection is None:
                    selection = agg.default_selection()
                    if agg.selection_settled(selection):
                        client["selection"] = selection
                agg.watch(selection)
                view = agg.view(selection, client["f_hwp"], client["window_s"])
                focal = client["focal"]
                shared = {k: v for k, v in tick.items() if k != "focal"}
                msg = {"type": "update", "seq": hub.seq, "t_server_ns": time.time_ns(), **shared, **view,
                       "window_s": client["window_s"] or agg.config.history_s, "update_s": update_s,
                       "focal": {"metric": focal, "values": tick["focal"].get(focal)}}
            if client["layout_version"] != tick["layout_version"]:  # the grid rows of this tick's codes
                msg["layout"] = layout
                client["layout_version"] = tick["layout_version"]
            return _dumps(msg)

        sender = asyncio.create_task(send_loop())
        try:
            async for raw in ws:
                if raw.type != WSMsgType.TEXT:
                    continue
                try:
                    try:
                        req = json.loads(raw.data)
                    except json.JSONDecodeError as exc:
                        raise ConfigError(f"not JSON: {exc}") from None
                    if not isinstance(req, dict):
                        raise ConfigError("a message must be a JSON object")
                    kind = req.get("type")
                    if kind == "select":
                        chans = req.get("channels")
                        if not isinstance(chans, list) or not all(isinstance(c, str) for c in chans):
                            raise ConfigError("channels must be a list of detector ids")
                        client["selection"] = chans
                        client["wake"].set()
                    elif kind == "f_hwp":
                        client["f_hwp"] = _parse_f_hwp(req.get("value"))
                        client["wake"].set()
                    elif kind == "window":
                        value = req.get("seconds")
                        if value not in _WINDOWS_S:
                            raise ConfigError(f"window must be one of {list(_WINDOWS_S)} s, got {value!r}")
                        client["window_s"] = float(value)
                        client["wake"].set()
                    elif kind == "focal":
                        if req.get("metric") not in _FOCAL_METRICS:
                            raise ConfigError(f"focal metric must be one of {list(_FOCAL_METRICS)}")
                        client["focal"] = req["metric"]
                        client["wake"].set()
                    elif kind == "rendered":
                        try:
                            t_pub, t_render = int(req["newest_t_pub_ns"]), int(req["t_render_ns"])
                        except (KeyError, TypeError, ValueError):
                            raise ConfigError("rendered needs integer newest_t_pub_ns and t_render_ns") from None
                        if t_pub > 0:
                            with subscriber.lock:
                                subscriber.aggregator.report_render(t_pub, t_render)
                    else:
                        raise ConfigError(f"unknown message type {kind!r}")
                except ConfigError as exc:  # tell the page; the connection stays
                    await ws.send_str(_dumps({"type": "error", "message": str(exc)}))
        finally:
            sender.cancel()
            clients.discard(ws)
        return ws

    app = web.Application(middlewares=[lock_down], client_max_size=1 << 16)
    app.on_startup.append(on_startup)
    app.on_shutdown.append(on_shutdown)
    app.router.add_get("/", index)
    app.router.add_get("/static/{name}", static)
    app.router.add_get("/api/state", api_state)
    app.router.add_get("/api/view", api_view)
    app.router.add_get("/ws", ws_handler)
    return app


def _listen_socket(bind: str, port: int, backlog: int = 128) -> socket.socket:
    family = socket.AF_INET6 if ":" in bind else socket.AF_INET
    sock = socket.socket(family, socket.SOCK_STREAM)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
    try:
        sock.bind((bind, port))
    except OSError as exc:
        sock.close()
        raise ConfigError(f"cannot listen on {bind}:{port}: {exc}") from None
    sock.listen(backlog)
    sock.setblocking(False)
    return sock


class _GuardedSite(web.SockSite):
    """aiohttp's SockSite, its connections made by a :class:`ConnectionGuard`'s protocol factory."""

    def __init__(self, runner, sock, factory, backlog: int):
        super().__init__(runner, sock, backlog=backlog)
        self._factory = factory

    async def start(self) -> None:
        await web.BaseSite.start(self)  # registers the site with its runner (cleanup closes it)
        loop = asyncio.get_running_loop()
        self._server = await loop.create_server(self._factory, sock=self._sock, backlog=self._backlog)


async def _flush_logs(rate_log: RateLog) -> None:
    with contextlib.suppress(asyncio.CancelledError):
        while True:
            await asyncio.sleep(min(rate_log.interval_s / 4, 1.0))
            rate_log.flush()


async def _serve(subscriber, bind: str, port: int, update_s: float, duration_s: float, on_ready, stop_event,
                 web_options: dict, limits: WebLimits) -> None:
    loop = asyncio.get_running_loop()
    rate_log = RateLog(log, limits.log_interval_s)
    max_connections, nofile = descriptor_cap(limits.max_connections, limits.backlog)
    if max_connections < limits.max_connections:
        log.warning("monitor: at most %d connections (max_connections %d, but the descriptor limit is %s, less "
                    "what is open, a reserve and the backlog of %d)", max_connections, limits.max_connections, nofile,
                    limits.backlog)
    connections = ConnectionGuard(limits, rate_log, max_connections)
    # aiohttp's and asyncio's own error logging (a failed accept, a broken request) goes through the rate
    # log too: one line per cause per interval, never a traceback per connection.
    http_log = logging.getLogger("mntes_stream.monitor.http")
    http_log.addFilter(rate_log.filter)
    loop.set_exception_handler(rate_log.loop_exception)
    app = make_app(subscriber, update_s, connections=connections, rate_log=rate_log, **web_options)
    runner = web.AppRunner(app, access_log=None)
    await runner.setup()
    sock = _listen_socket(bind, port, limits.backlog)
    factory = connections.factory(runner.server, loop, keepalive_timeout=limits.idle_timeout_s, logger=http_log,
                                  access_log=None)
    site = _GuardedSite(runner, sock, factory, limits.backlog)
    await site.start()
    flusher = asyncio.create_task(_flush_logs(rate_log))
    host, real_port = sock.getsockname()[:2]
    on_ready(host, real_port)
    stop = asyncio.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        with contextlib.suppress(NotImplementedError, RuntimeError, ValueError):  # not the main thread
            loop.add_signal_handler(sig, stop.set)
    t_end = time.monotonic() + duration_s if duration_s > 0 else math.inf
    try:
        while not stop.is_set() and time.monotonic() < t_end and not (stop_event is not None and stop_event.is_set()):
            with contextlib.suppress(asyncio.TimeoutError):
                await asyncio.wait_for(stop.wait(), min(0.1, max(t_end - time.monotonic(), 0.0)))
    finally:
        flusher.cancel()
        await runner.cleanup()
        rate_log.flush()
        http_log.removeFilter(rate_log.filter)


def serve(subscriber, bind: str = "127.0.0.1", port: int = 8050, update_s: float = 0.5,
          duration_s: float = 0.0, on_ready=None, stop_event=None, allowed_hosts: tuple[str, ...] = (),
          max_clients: int = 32, send_timeout_s: float = 10.0, limits: WebLimits | None = None) -> None:
    """Serve the page until SIGINT/SIGTERM, ``duration_s`` or ``stop_event``; returns after a clean shutdown.

    ``on_ready(host, port)`` is called once listening (``port=0`` picks a free port).
    ``stop_event`` (anything with ``is_set()``) lets another thread stop it. ``allowed_hosts``,
    ``max_clients`` and ``send_timeout_s``: see :class:`WebGuard` and :func:`make_app`; ``limits``: the
    socket bounds (:class:`~mntes_stream.monitor.web_limits.WebLimits`).
    """
    if not is_loopback(bind):
        log.warning("monitor listening on %s, beyond loopback: anyone who can reach it sees the stream "
                    "(there is no authentication)", bind)
        if bind in ("0.0.0.0", "::", "") and not allowed_hosts:
            log.warning("monitor: only loopback names are answered; list the names it is reached by in allowed_hosts")
    web_options = {"guard": WebGuard(bind, tuple(allowed_hosts)), "max_clients": max_clients,
                   "send_timeout_s": send_timeout_s}
    asyncio.run(_serve(subscriber, bind, port, update_s, duration_s, on_ready or (lambda h, p: None), stop_event,
                       web_options, limits or WebLimits()))


class PageServer:
    """:func:`serve` on a thread of its own, so a service's ``step`` returns while the page is served.

    :meth:`start` returns ``(host, port)`` once the page listens, None when stopped first, or raises
    what kept it from listening (a port in use: :class:`ConfigError`); :meth:`alive` while it serves;
    :meth:`stop` shuts it down and raises what the server died of, if it died. Arguments are
    :func:`serve`'s (no ``duration_s``: the owner stops it).
    """

    def __init__(self, subscriber, bind: str = "127.0.0.1", port: int = 8050, update_s: float = 0.5, **options):
        self._args = (subscriber, bind, port, update_s, 0.0)
        self._options = options
        self._stop = threading.Event()
        self._listening = threading.Event()
        self._address: tuple[str, int] | None = None
        self._error: BaseException | None = None
        self._thread = threading.Thread(target=self._run, name="monitor-page", daemon=True)

    def _on_ready(self, host: str, port: int) -> None:
        self._address = (host, port)
        self._listening.set()

    def _run(self) -> None:
        try:
            serve(*self._args, on_ready=self._on_ready, stop_event=self._stop, **self._options)
        except BaseException as exc:  # raised in the owner's thread by start() or stop()
            self._error = exc

    def start(self, stop=None) -> tuple[str, int] | None:
        """Start serving; ``(host, port)`` once listening, None if ``stop`` (Event-like) was set first."""
        self._thread.start()
        while not self._listening.wait(0.05):
            if not self._thread.is_alive() or (stop is not None and stop.is_set()):
                self.stop()  # raises what the server ended with
                if not (stop is not None and stop.is_set()):
                    raise ConfigError("the monitor page server ended before it listened")
                return None
        return self._address

    def alive(self) -> bool:
        return self._thread.is_alive()

    def stop(self, timeout_s: float = 10.0) -> None:
        """Stop serving (idempotent); raises the error the server ended with, once."""
        self._stop.set()
        if self._thread.ident is not None:
            self._thread.join(timeout_s)
            if self._thread.is_alive():
                log.warning("monitor: the page server did not stop within %.0f s", timeout_s)
        error, self._error = self._error, None
        if error is not None:
            raise error
