"""Long-running services: converter, recorder, replay (zenoh and MCAP at the edges).

- ``pipeline``: the converter's core, no zenoh (also used offline);
- ``converter``: the live converter service around it;
- ``source``: a minimal counts/housekeeping publisher from the physics model;
- ``recorder``, ``replay``: MCAP recording and re-publication;
- :class:`Services`: several of them as spawned processes (``up``, ``bench stream``).
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import sys
import threading
import time

__all__ = ["StopFlag", "stop_on_signals", "Services", "child_main", "run_recorder_doc", "dataclass_from_table"]


def split_config(doc: dict, tables: tuple[str, ...], source: str, base_dir=None):
    """A service config document as ``({table: dict}, ZenohSettings)``.

    Every service config is its own tables plus ``[zenoh]``; anything else,
    or a table that is not a table, is a ConfigError naming ``source``.
    """
    from mntes_stream.errors import ConfigError
    from mntes_stream.io.transport import ZenohSettings

    if not isinstance(doc, dict):
        raise ConfigError(f"{source}: expected a TOML document")
    unknown = set(doc) - {*tables, "zenoh"}
    if unknown:
        expected = ", ".join(f"[{t}]" for t in (*tables, "zenoh"))
        raise ConfigError(f"{source}: unknown table(s) {sorted(unknown)} (expected {expected})")
    for table in (*tables, "zenoh"):
        if not isinstance(doc.get(table, {}), dict):
            raise ConfigError(f"{source}: [{table}] must be a table")
    zenoh = ZenohSettings.from_dict(doc.get("zenoh", {}), f"{source} [zenoh]", base_dir=base_dir)
    return {t: dict(doc.get(t, {})) for t in tables}, zenoh


def dataclass_from_table(cls, table: dict, source: str, tuples: bool = False):
    """``cls(**table)`` for a config table; every problem is a ConfigError naming ``source``.

    Unknown keys, and values whose TOML type does not fit the field's annotation
    (a string for a number, a number for a string, a bool for an int, a scalar
    for an array), are named here; TypeError or ValueError from the constructor
    become ConfigError too. Ranges and finiteness are the class's own
    ``__post_init__`` checks. ``tuples`` turns TOML arrays into tuples (frozen
    dataclasses hold tuples).
    """
    from dataclasses import fields

    from mntes_stream.errors import ConfigError

    if not isinstance(table, dict):
        raise ConfigError(f"{source}: expected a table, got {type(table).__name__}")
    known = {f.name for f in fields(cls)}
    unknown = set(table) - known
    if unknown:
        raise ConfigError(f"{source}: unknown key(s) {sorted(unknown)} (known: {sorted(known)})")
    hints = _field_types(cls)
    for name, value in table.items():
        if name in hints and not _fits(value, hints[name]):
            raise ConfigError(f"{source}: {name} must be {_describe(hints[name])}, got {value!r}")
    if tuples:
        table = {k: tuple(v) if isinstance(v, list) else v for k, v in table.items()}
    try:
        return cls(**table)
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{source}: {exc}") from None


def _field_types(cls) -> dict:
    """Resolved field annotations of a dataclass ({} if they cannot be resolved: checks then fall to the class)."""
    import typing

    try:
        return typing.get_type_hints(cls)
    except Exception:  # a name only imported under TYPE_CHECKING
        return {}


def _fits(value, hint) -> bool:
    """Whether a TOML value can stand for ``hint`` (unknown kinds of hint: True, the class decides)."""
    import types
    import typing

    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return any(_fits(value, a) for a in args)
    if hint is type(None):
        return value is None
    if hint is bool:
        return isinstance(value, bool)
    if hint is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if hint is float:
        return isinstance(value, (int, float)) and not isinstance(value, bool)
    if hint is str:
        return isinstance(value, str)
    if origin is tuple:
        if not isinstance(value, (list, tuple)):
            return False
        if len(args) == 2 and args[1] is Ellipsis:
            return all(_fits(v, args[0]) for v in value)
        return not args or (len(value) == len(args) and all(_fits(v, a) for v, a in zip(value, args)))
    if isinstance(hint, type) and origin is None:
        return isinstance(value, hint)
    return True


def _describe(hint, plural: bool = False) -> str:
    import types
    import typing

    origin, args = typing.get_origin(hint), typing.get_args(hint)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_describe(a, plural) for a in args)
    if origin is tuple:
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {_describe(args[0], True)}"
        return f"a list of {len(args)} values ({', '.join(_describe(a) for a in args)})"
    one = {bool: "true or false", int: "an integer", float: "a number", str: "a string", type(None): "absent"}
    many = {bool: "booleans", int: "integers", float: "numbers", str: "strings"}
    return (many if plural else one).get(hint, getattr(hint, "__name__", str(hint)))


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


def child_main(name: str, target: str, cfg, stop, ready, results) -> None:
    """Entry of a spawned service process: ``target`` is ``"module:function"``.

    The function is called as ``function(cfg, stop, ready) -> dict``; its
    result (or its error) goes to the ``results`` queue as ``(name, "ok"|"error", value)``.
    """
    import importlib
    import multiprocessing

    from mntes_stream.service import StopFlag

    # Own process group: Ctrl-C in the terminal reaches only the parent, which
    # stops the children in order; the parent watch covers a parent killed hard.
    os.setpgrp()
    logging.basicConfig(level=logging.WARNING, format="%(asctime)s %(processName)s %(name)s: %(message)s")
    parent = multiprocessing.parent_process()

    class _Stop(StopFlag):
        def is_set(self) -> bool:
            return super().is_set() or (parent is not None and not parent.is_alive())

    if os.environ.get("RUST_LOG"):
        import zenoh

        zenoh.try_init_log_from_env()  # zenoh's own log, e.g. RUST_LOG=zenoh=warn
    module, func = target.split(":")
    wall0, cpu0 = time.monotonic(), time.process_time()
    try:
        result = getattr(importlib.import_module(module), func)(cfg, _Stop(stop), ready)
        if isinstance(result, dict):  # what the process cost, for benchmarks
            result = {**result, "process_cpu_s": time.process_time() - cpu0, "process_wall_s": time.monotonic() - wall0}
        results.put((name, "ok", result))
    except BaseException as exc:
        results.put((name, "error", f"{type(exc).__name__}: {exc}"))
        raise


def run_recorder_doc(doc: dict, stop=None, ready=None) -> dict:
    """The recorder from a config document, in the ``function(cfg, stop, ready)`` form."""
    from dataclasses import asdict

    from mntes_stream.service.recorder import RecorderConfig, run_recorder

    cfg = RecorderConfig.from_dict(doc, "recorder")
    return asdict(run_recorder(cfg, stop, ready))  # ready once subscribed, so sources start after it


class Services:
    """Spawned service processes, started in order (each waits until ready) and stopped in reverse dependency order."""

    def __init__(self):
        import multiprocessing as mp

        self._ctx = mp.get_context("spawn")  # never fork: a zenoh session may be open
        self.results = self._ctx.Queue()
        self.procs: dict = {}
        self._stops: dict = {}

    def start(self, name: str, target: str, cfg, timeout_s: float = 180.0, abort=None) -> None:
        from mntes_stream.errors import MntesError

        stop, ready = self._ctx.Event(), self._ctx.Event()
        proc = self._ctx.Process(target=child_main, name=name, args=(name, target, cfg, stop, ready, self.results))
        proc.start()
        self.procs[name], self._stops[name] = proc, stop
        deadline = time.monotonic() + timeout_s
        while not ready.wait(0.1):
            if not proc.is_alive() or time.monotonic() > deadline or (abort is not None and abort.is_set()):
                raise MntesError(f"{name} did not start (exit code {proc.exitcode})")

    def alive(self) -> bool:
        return all(p.is_alive() for p in self.procs.values())

    def stop(self, name: str, timeout_s: float = 30.0) -> bool:
        """Stop one service; False if it had to be terminated."""
        proc = self.procs.get(name)
        if proc is None:
            return True
        self._stops[name].set()
        proc.join(timeout_s)
        if proc.is_alive():
            print(f"{name} did not stop within {timeout_s:g} s; terminating it", file=sys.stderr)
            proc.terminate()
            proc.join(5)
            return False
        return proc.exitcode == 0

    def collect(self) -> tuple[dict, bool]:
        """Results by service name, and whether every service ended well."""
        out, ok = {}, True
        while True:
            try:
                name, state, value = self.results.get(timeout=0.5)
            except Exception:  # queue.Empty
                break
            out[name] = value
            ok &= state == "ok"
        return out, ok and len(out) == len(self.procs)
