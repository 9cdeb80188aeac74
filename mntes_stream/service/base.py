"""The service contract: every long-running service is one :class:`Service` subclass.

A service declares

- ``name``: its registry key, which is also the main table of its config
  document (``[converter]``, ``[recorder]``, ...);
- ``Config``: a settings dataclass (``core.settings``) for the whole document:
  its own settings from the main table, sub-tables such as ``[zenoh]`` as
  fields of their own;
- its hooks, and nothing of the skeleton: :meth:`Service.setup` (open its
  inputs, declare what it serves), :meth:`Service.step` (one unit of work;
  False when done), :meth:`Service.finish` (flush, close, return the final
  statistics as a dict), :meth:`Service.counters` (what the heartbeat shows);
- its :class:`Heartbeat`: state, uptime and counters, readable from any
  thread while it runs (:meth:`Service.status`).

The lifecycle (:meth:`Service.run`, one signature everywhere:
``run(stop=None, ready=None)``, both Event-like) runs the skeleton: a stop
flag that SIGINT/SIGTERM (main thread), the caller's ``stop`` and
``duration_s`` set; the zenoh session (waiting for its router and announcing
the service's presence when started by :meth:`Service.start`); one
:class:`~mntes_stream.io.transport.Publishers` with the metrics observer; ready
(after setup, or when the service says so: ``ready_after_setup = False``, a
replay is ready when it first publishes); heartbeat beats; ``linger_s``; finish.
Everything reaches the hooks explicitly in a :class:`Context`, and presence,
router waiting and the metrics observer reach the session and publishers as
arguments: no ContextVar, no thread-local. ``run`` and ``start`` are the
lifecycle's: a subclass overriding them is refused when it is defined.

``mntes_stream.service.registry`` maps names to classes; ``serve``, ``up``
and :class:`~mntes_stream.service.supervise.Services` know services only
through it. A new service is one module and one registry entry.
"""

from __future__ import annotations

import abc
import contextlib
import signal
import threading
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any, ClassVar

from mntes_stream.core.settings import build_document
from mntes_stream.io import keys, reconnect
from mntes_stream.io.presence import Presence
from mntes_stream.service.metrics import metrics_for

__all__ = ["Service", "Context", "Heartbeat", "StopFlag", "stop_on_signals"]


class StopFlag:
    """Set by a signal or by :meth:`set`; also reports set when an outer event is."""

    def __init__(self, outer=None):
        self._event = threading.Event()
        self._outer = outer

    def set(self) -> None:
        self._event.set()

    def is_set(self) -> bool:
        return self._event.is_set() or (self._outer is not None and self._outer.is_set())

    def wait(self, timeout_s: float) -> bool:
        """Sleep up to ``timeout_s``, waking early when set; returns :meth:`is_set`."""
        step = 0.05
        remaining = timeout_s
        while remaining > 0 and not self.is_set():
            self._event.wait(min(step, remaining))
            remaining -= step
        return self.is_set()


@contextlib.contextmanager
def stop_on_signals(outer=None):
    """A :class:`StopFlag` that SIGINT and SIGTERM set while the block runs.

    Signal handlers are only installed in the main thread (elsewhere the flag
    follows ``outer`` alone); the previous handlers are restored on exit.
    """
    flag = StopFlag(outer)
    previous = {}
    if threading.current_thread() is threading.main_thread():
        for sig in (signal.SIGINT, signal.SIGTERM):
            previous[sig] = signal.signal(sig, lambda *_: flag.set())
    try:
        yield flag
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)


class Heartbeat:
    """What a running service says about itself; written by the service, read from any thread.

    States go ``starting`` -> ``running`` -> ``stopping`` -> ``stopped``
    (or ``failed``); ``waiting`` while a client waits for its router at start
    (:meth:`waiting`). ``beat(**counters)`` records progress and the time of it.
    """

    STATES = ("starting", "waiting", "running", "stopping", "stopped", "failed")
    MAX_WARNINGS = 8

    def __init__(self, service: str, name: str = ""):
        self.service = service
        self.name = name or service
        self._lock = threading.Lock()
        self._state = "starting"
        self._t_start = time.monotonic()
        self._t_beat = self._t_start
        self._counters: dict[str, Any] = {}
        self._warnings: tuple[str, ...] = ()

    def warn(self, message: str) -> None:
        """Keep ``message`` in the snapshot's ``warnings`` (the last few, oldest dropped)."""
        with self._lock:
            self._warnings = (self._warnings + (message,))[-self.MAX_WARNINGS:]

    def beat(self, **counters: Any) -> None:
        with self._lock:
            self._counters.update(counters)
            self._t_beat = time.monotonic()

    def set_state(self, state: str) -> None:
        if state not in self.STATES:
            raise ValueError(f"unknown service state {state!r}")
        with self._lock:
            self._state = state
            self._t_beat = time.monotonic()

    def waiting(self, text: str | None) -> None:
        """``text`` ("waiting for router ...") while the service waits to connect; None once connected."""
        with self._lock:
            if text is not None:
                self._state = "waiting"
                self._counters["connect_attempts"] = self._counters.get("connect_attempts", 0) + 1
            elif self._state == "waiting":
                self._state = "starting"
            self._counters["waiting_for"] = text or ""
            self._t_beat = time.monotonic()

    @property
    def state(self) -> str:
        return self._state

    def snapshot(self) -> dict[str, Any]:
        """``service``, ``name``, ``state``, ``uptime_s``, ``since_beat_s``, the counters and ``warnings``."""
        with self._lock:
            now = time.monotonic()
            return {"service": self.service, "name": self.name, "state": self._state,
                    "uptime_s": now - self._t_start, "since_beat_s": now - self._t_beat, **self._counters,
                    "warnings": list(self._warnings)}


class _Ready:
    """``ready`` as a service sees it: setting it also marks the heartbeat ``running``."""

    def __init__(self, heartbeat: Heartbeat, outer=None):
        self._heartbeat, self._outer = heartbeat, outer

    def set(self) -> None:
        self._heartbeat.set_state("running")
        if self._outer is not None:
            self._outer.set()

    def is_set(self) -> bool:
        return self._heartbeat.state == "running"

    def progress(self, text: str) -> None:
        """What the service is doing before it is ready, for whoever started it (``up`` prints it)."""
        self._heartbeat.beat(start_phase=text)
        tell = getattr(self._outer, "progress", None)  # a plain Event has none: nobody listens
        if tell is not None:
            tell(text)


@contextlib.contextmanager
def announced(progress: Callable[[str], None], text: str, after_s: float = 1.0):
    """Say ``text ...`` through ``progress`` once the block has taken ``after_s``, and how long it took.

    A start that is quick says nothing; a slow one (kernels compiling, tables
    building) says what it does while it does it, not after a silence.
    """
    t0 = time.monotonic()
    timer = threading.Timer(after_s, progress, (f"{text} ...",))
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        took_s = time.monotonic() - t0
        if took_s >= after_s:
            progress(f"{text}: done in {took_s:.1f} s")


@dataclass(frozen=True)
class Context:
    """What the lifecycle hands a service's hooks, explicitly.

    Attributes
    ----------
    stop : StopFlag
        Set by a signal, the caller's ``stop`` or the end of ``duration_s``.
    heartbeat : Heartbeat
    session : zenoh.Session or None
        None when the service joins no zenoh (``zenoh_settings()`` is None).
    publishers : Publishers or None
        BLOCK publishers on ``session``; every put is seen by the metrics.
    metrics : ServiceMetrics or None
        The service's Prometheus metrics, when ``[metrics] port`` is set.
    mark_ready : callable
        ``mark_ready()`` says the service serves (idempotent).
    progress : callable
        ``progress(text)`` says what a slow start is doing ("compiling kernels"), before it is ready.
    """

    stop: StopFlag
    heartbeat: Heartbeat
    session: Any
    publishers: Any
    metrics: Any
    mark_ready: Callable[[], None]
    progress: Callable[[str], None] = lambda text: None


class Service(abc.ABC):
    """Base of every long-running service (see the module docstring for the contract).

    Parameters
    ----------
    config : ``cls.Config``
    """

    name: ClassVar[str]
    Config: ClassVar[type]
    summary: ClassVar[str] = ""
    #: ready once :meth:`setup` returns; False: the service calls ``ctx.mark_ready()`` itself
    ready_after_setup: ClassVar[bool] = True
    #: the lifecycle beats the heartbeat with :meth:`counters` this often
    beat_every_s: ClassVar[float] = 0.5

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        # A service that ran its own skeleton would skip what start() passes it (presence, router
        # waiting, metrics): the lifecycle is the base's alone.
        for name in ("run", "start", "_lifecycle"):
            if name in vars(cls):
                raise TypeError(f"{cls.__name__} overrides Service.{name}: a service writes hooks "
                                f"(setup, step, finish, counters), the lifecycle runs them")

    def __init__(self, config):
        if not isinstance(config, self.Config):
            raise TypeError(f"{type(self).__name__} takes a {self.Config.__name__}, got {type(config).__name__}")
        self.config = config
        self.heartbeat = Heartbeat(self.name, self.instance_name())

    def instance_name(self) -> str:
        """This instance's name among services of its kind (status keys, logs)."""
        return getattr(self.config, "name", "") or self.name

    @classmethod
    def config_from_document(cls, doc: Mapping, where: str = "", base_dir: str | None = None, **fixed: Any):
        """``cls.Config`` from a whole parsed config document (``[<name>]`` plus its sub-tables)."""
        return build_document(cls.Config, doc, cls.name, where, base_dir, **fixed)

    def status(self) -> dict[str, Any]:
        """The heartbeat snapshot (cheap; any thread)."""
        return self.heartbeat.snapshot()

    def owns(self) -> dict[str, Any]:
        """What part of the setup this instance serves (e.g. a converter's boards and modules); for ``ps``."""
        return {}

    def presence(self) -> Presence:
        """How this instance shows itself on zenoh while it runs (``io/presence.py``)."""
        return Presence(setup=getattr(self.config, "setup", None) or keys.DEFAULT_SETUP, service=self.name,
                        name=self.instance_name(), snapshot=lambda: {**self.status(), "owns": self.owns()},
                        warn=self.heartbeat.warn)

    def start(self, stop=None, ready=None) -> dict[str, Any]:
        """:meth:`run` with the heartbeat's state kept, the service announced on its zenoh session,
        a client waiting for its router (``io/reconnect.py``) and its metrics served: what ``serve``
        and the supervisor call."""
        from mntes_stream.io.presence import join_watchers

        try:
            with metrics_for(self) as metrics:
                result = self._lifecycle(stop, _Ready(self.heartbeat, ready), metrics, announce=True)
        except BaseException:
            self.heartbeat.set_state("failed")
            raise
        finally:
            join_watchers()  # the session is closed: its watch thread ends now, not inside zenoh at exit
        self.heartbeat.set_state("stopped")
        return dict(result or {})

    def run(self, stop=None, ready=None) -> Mapping[str, Any]:
        """Serve until stopped or done; set ``ready`` once serving; return the final statistics.

        The lifecycle without presence, router waiting or metrics (a bare run, e.g. a CLI
        command or a test); :meth:`start` adds them.
        """
        return self._lifecycle(stop, ready, None, announce=False)

    # ------------------------------------------------------------------ hooks

    def zenoh_settings(self):
        """The ``ZenohSettings`` of the session the lifecycle opens (None: no session)."""
        return getattr(self.config, "zenoh", None)

    def history_chunks(self) -> int:
        """Samples each counts/housekeeping key of ``ctx.publishers`` keeps for late subscribers."""
        return 0

    def duration_s(self) -> float:
        """Stop after this long (0: until stopped or :meth:`step` says done)."""
        return float(getattr(self.config, "duration_s", 0.0) or 0.0)

    def linger_s(self) -> float:
        """Keep the session open this long after the last step (queued is not yet delivered)."""
        return float(getattr(self.config, "linger_s", 0.0) or 0.0)

    def preflight(self) -> None:
        """Check what needs no session (an optional extra, a file) before the session opens: an error then
        leaves no zenoh threads to tear down at the process's exit (they can abort it)."""
        return None

    def setup(self, ctx: Context) -> None:
        """Open inputs, declare what the service serves; ready follows unless ``ready_after_setup`` is False."""
        return None

    def step(self, ctx: Context) -> bool:
        """One unit of work, returning within about ``beat_every_s``; False once there is nothing more."""
        raise NotImplementedError(f"{type(self).__name__} does not write step()")

    def finish(self, ctx: Context) -> Mapping[str, Any]:
        """Flush and close what :meth:`setup` opened (on stop, and after a failed step too); the final statistics.

        It may close ``ctx.session`` itself (to drain what arrived before it closed); the lifecycle closes it
        (again) after."""
        return {}

    def counters(self) -> dict[str, Any]:
        """The running counters the heartbeat shows."""
        return {}

    # ------------------------------------------------------------------ lifecycle

    def _lifecycle(self, stop, ready, metrics, announce: bool) -> Mapping[str, Any]:
        from mntes_stream.io.transport import Publishers, open_session
        from mntes_stream.service.heap import freeze_setup, pad_heap

        pad_heap()  # a payload per message: the heap grown in steps, not trimmed and faulted in per message

        def mark_ready() -> None:
            if ready is not None and not ready.is_set():
                ready.set()

        self.preflight()
        settings = self.zenoh_settings()
        with stop_on_signals(stop) as stopping, contextlib.ExitStack() as stack:
            session = pubs = None
            if settings is not None:
                session = stack.enter_context(open_session(
                    settings, presence=self.presence() if announce else None,
                    retrying=reconnect.Retrying(stopping, self.heartbeat.waiting) if announce else None))
                pubs = Publishers(session, history_chunks=self.history_chunks(), history_bytes=settings.history_bytes,
                                  observer=None if metrics is None else metrics.observe)
                stack.callback(pubs.close)
            ctx = Context(stopping, self.heartbeat, session, pubs, metrics, mark_ready,
                          getattr(ready, "progress", lambda text: None))
            self.setup(ctx)
            freeze_setup()  # in a process of its own: a full collection in the loop walks only what the loop made
            if self.ready_after_setup:
                mark_ready()
            duration = self.duration_s()
            t_end = time.monotonic() + duration if duration > 0 else None
            next_beat = 0.0
            try:
                while not stopping.is_set():
                    now = time.monotonic()
                    if now >= next_beat:
                        self.heartbeat.beat(**self.counters())
                        next_beat = now + self.beat_every_s
                    if t_end is not None and now >= t_end:
                        break
                    if not self.step(ctx):
                        break
                if self.heartbeat.state == "running":
                    self.heartbeat.set_state("stopping")
                stopping.wait(self.linger_s())
            finally:  # a failed step still has its files finished; its error is the one raised
                result = self.finish(ctx)
            self.heartbeat.beat(**self.counters())
        return result
