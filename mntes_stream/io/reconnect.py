"""A zenoh client that cannot reach its router at start waits for it instead of exiting.

zenoh retries on its own everywhere but one place: a peer or a router whose
``connect`` endpoints are unreachable opens at once and keeps dialling in the
background (``connect/timeout_ms`` -1 and ``connect/exit_on_failure`` false
are zenoh's defaults for them, with ``connect/retry/*`` as the backoff), and
a connected client re-dials a router that went away. A *client* session,
though, does not open without a router: with ``connect/timeout_ms`` 0 (its
default) ``zenoh.open`` fails at once, with -1 it blocks in native code
where neither a stop flag nor Ctrl-C reaches it. So for a client, and only
while a service runs (:meth:`Service.start <mntes_stream.service.base.Service.start>`
passes a :class:`Retrying` to ``open_session``, explicitly), it tries again with bounded
exponential backoff, says so in the service's heartbeat and log, and gives
up only when the service is stopped (or after ``reconnect_give_up_s``).
Outside a service (a test, a benchmark's own session, ``up``'s monitoring
session) a client still fails at once with one line.
"""

from __future__ import annotations

import logging
import re
import time
from collections.abc import Callable
from dataclasses import dataclass, field

from mntes_stream.errors import TransportError

__all__ = ["Retrying", "Backoff", "open_or_wait", "open_with_retry", "is_unreachable"]

log = logging.getLogger(__name__)

#: zenoh's text when no connect endpoint answered (client mode, orchestrator.rs).
_UNREACHABLE = "Unable to connect to any of"
_AT_SOURCE = re.compile(r"\s+at /\S+\.rs:\d+\.?$")  # zenoh's own source location: noise in a log line


@dataclass(frozen=True)
class Retrying:
    """How ``open_session`` waits for an unreachable router (a running service's policy).

    Parameters
    ----------
    stop : object with ``is_set()``, or None
        Waiting ends (TransportError) once it is set.
    report : callable
        ``report(text)`` while waiting ("waiting for router ..."), ``report(None)`` once connected.
    """

    stop: object | None = None
    report: Callable[[str | None], None] = field(default=lambda _: None)


@dataclass
class Backoff:
    """Delays ``initial_s``, doubling, never above ``max_s``."""

    initial_s: float = 0.5
    max_s: float = 4.0
    attempts: int = 0

    def next_s(self) -> float:
        self.attempts += 1
        return min(self.max_s, self.initial_s * 2.0 ** min(self.attempts - 1, 60))


def is_unreachable(exc: BaseException) -> bool:
    """Whether zenoh refused to open because no connect endpoint answered (worth waiting for)."""
    return _UNREACHABLE in str(exc)


def _sleep(stop, seconds: float) -> bool:
    """Sleep up to ``seconds``, waking early once ``stop`` is set; True if it was."""
    t_end = time.monotonic() + seconds
    while (left := t_end - time.monotonic()) > 0:
        if stop is not None and stop.is_set():
            return True
        time.sleep(min(0.05, left))
    return stop is not None and stop.is_set()


def open_or_wait(open_fn: Callable, conf, named: dict, settings, policy: Retrying | None = None):
    """``open_fn(conf)``; for a client in a running service whose router is unreachable, wait for it.

    ``named`` is ``describe_config(conf)``; ``settings`` the ``ZenohSettings``
    (``reconnect_min_s``, ``reconnect_max_s``, ``reconnect_give_up_s``).
    ``policy`` is the service's waiting policy, passed in explicitly (``Service`` lifecycle);
    None: fail at once.
    Whatever else fails is raised as it is.
    """
    try:
        return open_fn(conf)
    except Exception as exc:  # zenoh's ZError
        if policy is None or named.get("mode") != "client" or not is_unreachable(exc):
            raise
        backoff = Backoff(settings.reconnect_min_s or 0.5, settings.reconnect_max_s or 4.0)
        return open_with_retry(lambda: open_fn(conf), ", ".join(named.get("connect/endpoints") or ()), policy,
                               backoff, settings.reconnect_give_up_s or 0.0, first_error=exc)


def open_with_retry(attempt: Callable[[], object], endpoints: str, policy: Retrying, backoff: Backoff,
                    give_up_s: float = 0.0, first_error: BaseException | None = None):
    """``attempt()`` until it returns a session; while the router is unreachable, wait ``backoff``.

    ``first_error`` is the failure of an attempt already made. Any other
    failure is raised at once. Logs the first failure, then at attempts 2, 4,
    8, ... (a bounded log however long the wait), and the connection.

    Raises
    ------
    TransportError
        Stopped while waiting, or ``give_up_s`` (> 0) passed without a router.
    """
    t0 = time.monotonic()
    exc = first_error
    reason = ""
    try:
        while True:
            if exc is not None:
                if not is_unreachable(exc):
                    raise exc
                delay = backoff.next_s()
                waited = time.monotonic() - t0
                n = backoff.attempts
                text = (f"waiting for router {endpoints}: unreachable ({n} attempt{'s' * (n > 1)} in {waited:.1f} s; "
                        f"next in {delay:g} s)")
                policy.report(text)
                why = _AT_SOURCE.sub("", str(exc).splitlines()[0]).strip()
                if why != reason or n & (n - 1) == 0:  # a new reason, or attempt 1, 2, 4, 8, ...
                    log.warning("%s: %s", text, why)
                    reason = why
                if give_up_s and waited + delay > give_up_s:
                    raise TransportError(f"no zenoh router at {endpoints} within {give_up_s:g} s "
                                         f"({n} attempts): {why}")
                if _sleep(policy.stop, delay):
                    raise TransportError(f"stopped while waiting for router {endpoints} "
                                         f"({n} attempts in {time.monotonic() - t0:.0f} s; never connected)")
            try:
                session = attempt()
            except Exception as err:  # zenoh's ZError: judged above (unreachable: wait; else raise)
                exc = err
                continue
            if backoff.attempts:
                log.warning("connected to router %s after %d failed attempts in %.1f s", endpoints,
                            backoff.attempts, time.monotonic() - t0)
            return session
    finally:
        policy.report(None)
