"""Services as spawned processes: started in order, each waited for, stopped in reverse order.

``multiprocessing`` *spawn* only: nothing ever forks with a zenoh session
open, and each service gets an interpreter (and a core) of its own. A child
knows its service by registry name (``service.registry``), never by an
import string.

Crash-only: a child that dies (killed, or failed) can be started again on
the same config (:meth:`Services.restart`), within a budget of restarts per
minute (:class:`RestartBudget`); its peers reconnect on their own (zenoh
peers re-dial their ``connect`` endpoints), so a restart is only a new process.
"""

from __future__ import annotations

import collections
import logging
import os
import queue
import signal
import sys
import time

from mntes_stream.errors import MntesError
from mntes_stream.service.base import StopFlag

__all__ = ["Services", "RestartBudget", "child_main", "exit_reason"]


def exit_reason(exitcode: int | None) -> str:
    """``killed by SIGKILL``, ``exit code 1``, ... for a process's exit code."""
    if exitcode is None:
        return "still running"
    if exitcode < 0:
        try:
            return f"killed by {signal.Signals(-exitcode).name}"
        except ValueError:
            return f"killed by signal {-exitcode}"
    return f"exit code {exitcode}"


class RestartBudget:
    """At most ``per_minute`` restarts of one service in any 60 s (0: none); :meth:`take` says whether one is left."""

    WINDOW_S = 60.0

    def __init__(self, per_minute: int):
        if per_minute < 0:
            raise MntesError(f"restarts per minute must be >= 0, got {per_minute}")
        self.per_minute = int(per_minute)
        self._times: dict[str, collections.deque] = {}

    def take(self, label: str, now_s: float | None = None) -> bool:
        now_s = time.monotonic() if now_s is None else now_s
        times = self._times.setdefault(label, collections.deque())
        while times and now_s - times[0] >= self.WINDOW_S:
            times.popleft()
        if len(times) >= self.per_minute:
            return False
        times.append(now_s)
        return True


class _ParentWatch(StopFlag):
    """Also set when the parent process is gone (killed hard: no stop event will ever come)."""

    def __init__(self, outer, parent):
        super().__init__(outer)
        self._parent = parent

    def is_set(self) -> bool:
        return super().is_set() or (self._parent is not None and not self._parent.is_alive())


class _ReadyReporting:
    """The child's ``ready``: the parent's Event, and progress before it is set sent on the results queue."""

    def __init__(self, label: str, ready, results):
        self._label, self._ready, self._results = label, ready, results

    def set(self) -> None:
        self._ready.set()

    def is_set(self) -> bool:
        return self._ready.is_set()

    def progress(self, text: str) -> None:
        self._results.put((self._label, "progress", text))


def child_main(label: str, service, config, stop, ready, results) -> None:
    """Entry of a spawned service process: run ``service`` (a registry name or a Service class) on ``config``.

    Its final statistics (or its error, one line) go to ``results`` as
    ``(label, "ok"|"error", value)``, with the process's CPU and wall time.
    """
    import multiprocessing

    from mntes_stream.service.registry import service_class

    # Own process group: Ctrl-C in the terminal reaches only the parent, which
    # stops the children in order; the parent watch covers a parent killed hard.
    # SIGINT arrives blocked (Services.start): ignore what came before the new group, then unblock.
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    os.setpgrp()
    signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    signal.signal(signal.SIGINT, signal.default_int_handler)
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(processName)s %(name)s: %(message)s")
    if os.environ.get("RUST_LOG"):
        import zenoh

        zenoh.try_init_log_from_env()  # zenoh's own log, e.g. RUST_LOG=zenoh=warn
    from mntes_stream.service.heap import own_process

    own_process()  # a process of its own: its service's setup leaves the collector's sight (service.heap)
    wall0, cpu0 = time.monotonic(), time.process_time()
    try:
        svc = (service if isinstance(service, type) else service_class(service))(config)
        result = svc.start(_ParentWatch(stop, multiprocessing.parent_process()), _ReadyReporting(label, ready, results))
        import resource

        result = {**result, "process_cpu_s": time.process_time() - cpu0, "process_wall_s": time.monotonic() - wall0,
                  "process_max_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024}  # Linux: kB
        results.put((label, "ok", result))
    except KeyboardInterrupt:
        results.put((label, "error", "interrupted"))
    except BaseException as exc:
        results.put((label, "error", f"{type(exc).__name__}: {exc}"))
        if not isinstance(exc, MntesError):
            raise


class Services:
    """Spawned service processes, started in order (each waits until ready) and stopped in reverse dependency order."""

    def __init__(self):
        import multiprocessing as mp

        self._ctx = mp.get_context("spawn")  # never fork: a zenoh session may be open
        self.results = self._ctx.Queue()
        self.procs: dict = {}
        self._stops: dict = {}
        self._readies: dict = {}  # held while the child lives: a collected Event unlinks what the child still needs
        self._collected: dict = {}
        self._specs: dict = {}  # label -> (service, config, timeout_s): what a restart starts again
        self._stopped: set = set()  # stopped on purpose: not dead
        self.restarts: collections.Counter = collections.Counter()
        self.deaths: dict[str, list[str]] = {}  # label -> why each earlier process of it ended
        #: ``on_progress(label, text)``: what a starting service says it is doing (None: not shown)
        self.on_progress = None

    def start(self, label: str, service, config, timeout_s: float = 180.0, abort=None) -> None:
        """Start ``service`` (a registry name, or a Service class such as a benchmark's) on ``config`` as
        process ``label``; return once it is ready.

        Raises
        ------
        MntesError
            It exited, did not get ready within ``timeout_s``, or ``abort`` was set meanwhile;
            the message carries the child's own error when it sent one.
        """
        self._specs[label] = (service, config, timeout_s)
        self._stopped.discard(label)
        stop, ready = self._ctx.Event(), self._ctx.Event()
        proc = self._ctx.Process(target=child_main, name=label, args=(label, service, config, stop, ready, self.results))
        # The child starts with SIGINT blocked (the mask is inherited) until it has its own process
        # group: a Ctrl-C in the terminal meanwhile is the parent's alone, never a traceback in a child.
        old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
        try:
            proc.start()
        finally:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)
        self.procs[label], self._stops[label], self._readies[label] = proc, stop, ready
        deadline = time.monotonic() + timeout_s
        while not ready.wait(0.1):
            self._drain(0.0)  # the child's progress, as it comes
            if abort is not None and abort.is_set():
                raise MntesError(f"{label}: start interrupted")
            if not proc.is_alive() or time.monotonic() > deadline:
                proc.join(1.0)
                why = self._error_of(label) or (f"exit code {proc.exitcode}" if not proc.is_alive()
                                                else f"not ready within {timeout_s:g} s")
                raise MntesError(f"{label} did not start: {why}")

    def _error_of(self, label: str) -> str | None:
        self._drain(0.5)
        state, value = self._collected.get(label, (None, None))
        return value if state == "error" else None

    def _drain(self, timeout_s: float) -> None:
        while True:
            try:
                label, state, value = self.results.get(timeout=timeout_s)
            except queue.Empty:
                return
            if state == "progress":
                if self.on_progress is not None:
                    self.on_progress(label, value)
                continue
            self._collected[label] = (state, value)
            timeout_s = 0.05

    def alive(self) -> bool:
        return all(p.is_alive() for p in self.procs.values())

    def dead(self) -> list[str]:
        """Labels whose process ended without being stopped (in start order)."""
        return [label for label, p in self.procs.items() if label not in self._stopped and not p.is_alive()]

    def pid(self, label: str) -> int | None:
        proc = self.procs.get(label)
        return None if proc is None else proc.pid

    def restart(self, label: str, abort=None) -> str:
        """Start the dead service ``label`` again on its config; returns why the old process ended.

        Raises
        ------
        MntesError
            The new process did not start (as :meth:`start`).
        """
        old = self.procs[label]
        old.join(1.0)
        why = exit_reason(old.exitcode)
        error = self._error_of(label)
        if error:
            why += f": {error}"
        self._collected.pop(label, None)  # the new process reports for the label
        self.deaths.setdefault(label, []).append(why)
        self.restarts[label] += 1
        service, config, timeout_s = self._specs[label]
        self.start(label, service, config, timeout_s=timeout_s, abort=abort)
        return why

    def stop(self, label: str, timeout_s: float = 30.0) -> bool:
        """Stop one service; False if it had to be terminated or ended badly."""
        proc = self.procs.get(label)
        if proc is None:
            return True
        self._stopped.add(label)
        self._stops[label].set()
        proc.join(timeout_s)
        if proc.is_alive():
            print(f"{label} did not stop within {timeout_s:g} s; terminating it", file=sys.stderr)
            proc.terminate()
            proc.join(5)
            return False
        return proc.exitcode == 0

    def collect(self) -> tuple[dict, bool]:
        """Results by label, and whether every service ended well."""
        self._drain(0.5)
        out = {label: value for label, (state, value) in self._collected.items()}
        ok = all(state == "ok" for state, _ in self._collected.values())
        return out, ok and len(out) == len(self.procs)
