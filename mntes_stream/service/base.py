"""The service contract: every long-running service is one :class:`Service` subclass.

A service declares

- ``name``: its registry key, which is also the main table of its config
  document (``[converter]``, ``[recorder]``, ...);
- ``Config``: a settings dataclass (``core.settings``) for the whole document:
  its own settings from the main table, sub-tables such as ``[zenoh]`` as
  fields of their own;
- ``run(stop, ready)``: runs until ``stop`` is set (SIGINT/SIGTERM set it
  too when run in the main thread) or its own end, sets ``ready`` once it
  serves (subscribed, publishing), finishes cleanly (pending work done,
  files closed, session closed) and returns its final statistics as a dict;
- its :class:`Heartbeat`: state, uptime and counters, readable from any
  thread while it runs (:meth:`Service.status`).

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
from collections.abc import Mapping
from typing import Any, ClassVar

from mntes_stream.core.settings import build_document
from mntes_stream.io import keys, reconnect
from mntes_stream.io.presence import Presence, presence
from mntes_stream.service.metrics import metrics_for

__all__ = ["Service", "Heartbeat", "StopFlag", "stop_on_signals"]


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
        with reconnect.stopping_with(flag):  # a client waiting for its router stops too
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


class Service(abc.ABC):
    """Base of every long-running service (see the module docstring for the contract).

    Parameters
    ----------
    config : ``cls.Config``
    """

    name: ClassVar[str]
    Config: ClassVar[type]
    summary: ClassVar[str] = ""

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
        """:meth:`run` with the heartbeat's state kept and the service announced on every zenoh
        session it opens, where a client waits for its router (``io/reconnect.py``): what ``serve``
        and the supervisor call."""
        try:
            with presence(self.presence()), reconnect.retrying(stop, self.heartbeat.waiting), metrics_for(self):
                result = self.run(stop, _Ready(self.heartbeat, ready))
        except BaseException:
            self.heartbeat.set_state("failed")
            raise
        self.heartbeat.set_state("stopped")
        return dict(result or {})

    @abc.abstractmethod
    def run(self, stop=None, ready=None) -> Mapping[str, Any]:
        """Serve until stopped or done; set ``ready`` once serving; return the final statistics."""
