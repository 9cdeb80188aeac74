"""Long-running services: converter, recorder, replay (zenoh and MCAP at the edges).

- ``pipeline``: the converter's core, no zenoh (also used offline);
- ``converter``: the live converter service around it;
- ``source``: a minimal counts/housekeeping publisher from the physics model;
- ``recorder``, ``replay``: MCAP recording and re-publication;
- ``up``-style orchestration lives in ``cli/serve.py``.
"""

from __future__ import annotations

import contextlib
import signal
import threading

__all__ = ["StopFlag", "stop_on_signals"]


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
