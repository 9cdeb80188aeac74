"""The monitor's zenoh edge: power, housekeeping and status in, an :class:`Aggregator` fed.

The zenoh callback only stamps the receive time and queues the payload;
decoding and aggregation run on one ingest thread. The queue is bounded and
a full queue *drops* (counted, shown as "dropped" in the health panel)
instead of blocking: the converter publishes with BLOCK congestion control,
so a monitor that blocked its callback would slow the conversion it is
watching.
"""

from __future__ import annotations

import contextlib
import logging
import queue
import threading
import time

from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io import keys
from mntes_stream.io.messages import HousekeepingChunk, PowerChunk, Provenance, StatusMessage
from mntes_stream.io.transport import ZenohSettings, open_session
from mntes_stream.monitor.aggregate import Aggregator, MonitorConfig

__all__ = ["MonitorSubscriber"]

log = logging.getLogger("mntes_stream.monitor")

_DECODERS = {"power": PowerChunk, "hk": HousekeepingChunk, "status": StatusMessage, "provenance": Provenance}


class MonitorSubscriber:
    """Subscribe to ``mntes/<setup>/{power,hk,status,provenance}`` and keep an :class:`Aggregator` up to date.

    For the live leakage (``config.leakage_detectors`` > 0) it also subscribes to the counts of the
    measured detectors' modules only, once they are chosen, and runs the linear shadow
    (``monitor/shadow.py``) on them with the provenance's parameters (or ``params_path``).

    Use as a context manager (the zenoh session is always closed). All access
    to :attr:`aggregator` from other threads goes through :attr:`lock`.

    Parameters
    ----------
    setup : str
    zenoh : ZenohSettings
    config : MonitorConfig, optional
    queue_size : int
        Messages held between the zenoh callback and the ingest thread.
    queue_mb : float
        Bytes held there at most; a message beyond either bound is dropped (counted).
    max_message_mb : float
        A larger message is refused unread (counted as ``too_large``).
    positions : dict, optional
        Sky positions for the focal-plane view (:func:`~mntes_stream.monitor.service.load_positions`).
    params_path : str, optional
        Detector parameter TOML for the linear shadow instead of the converter's provenance.
    """

    def __init__(self, setup: str, zenoh: ZenohSettings, config: MonitorConfig | None = None, queue_size: int = 8192,
                 positions: dict | None = None, queue_mb: float = 64.0, max_message_mb: float = 16.0,
                 session=None, params_path: str | None = None):
        self.setup = setup
        self.key_exprs = (keys.power_key(setup), keys.hk_key(setup), keys.status_key(setup),
                          keys.provenance_key(setup))
        self.params_path = params_path
        self.shadow = None  # monitor.shadow.LinearShadow, once the measured detectors are chosen
        self._shadow_build = False  # parameters arrived: (re)build outside the lock
        self._counts_subs: dict = {}  # (board, module) -> subscriber of that module's counts
        self._provenance_texts: dict[str, str] = {}  # heard before the shadow exists
        self._measuring: threading.Thread | None = None  # the live leakage's fits, one at a time
        self.zenoh = zenoh
        self.aggregator = Aggregator(config, positions)
        self.lock = threading.Lock()
        self._queue: queue.Queue = queue.Queue(maxsize=queue_size)
        self._queue_max_bytes = int(queue_mb * 1e6)
        self._max_message_bytes = int(max_message_mb * 1e6)
        self._queued_bytes = 0  # approximate (updated by two threads without a lock): a bound, not a count
        self._too_large = 0
        self._stop = threading.Event()
        self._session = session  # given (a Service's): used, not closed; else opened at start
        self._own_session = session is None
        self._subs: list = []
        self._thread: threading.Thread | None = None
        self._dropped = 0

    # ------------------------------------------------------------------ lifecycle

    def __enter__(self) -> MonitorSubscriber:
        self.start()
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def start(self) -> None:
        if self._own_session:
            self._session = open_session(self.zenoh)
        try:
            for expr in self.key_exprs:
                self._subs.append(self._session.declare_subscriber(expr, self._on_sample))
        except Exception:
            self.close()
            raise
        self._thread = threading.Thread(target=self._ingest, name="monitor-ingest", daemon=True)
        self._thread.start()
        log.info("monitor subscribed to %s", ", ".join(self.key_exprs))

    def close(self) -> None:
        self._stop.set()
        for sub in [*self._subs, *self._counts_subs.values()]:
            with contextlib.suppress(Exception):
                sub.undeclare()
        self._subs.clear()
        self._counts_subs.clear()
        if self._session is not None and self._own_session:
            with contextlib.suppress(Exception):
                self._session.close()
        self._session = None
        if self._thread is not None:
            self._thread.join(timeout=5)
            self._thread = None
        if self._measuring is not None:
            self._measuring.join(timeout=5)
            self._measuring = None

    # ------------------------------------------------------------------ data path

    def _on_sample(self, sample) -> None:
        # zenoh thread: stamp and hand over, never block (see the module docstring).
        t_recv_ns = time.time_ns()
        size = len(sample.payload)
        if size > self._max_message_bytes:
            self._too_large += 1
            return
        if self._queued_bytes + size > self._queue_max_bytes:
            self._dropped += 1
            return
        try:
            self._queue.put_nowait((str(sample.key_expr), sample.payload.to_bytes(), t_recv_ns))
            self._queued_bytes += size
        except queue.Full:
            self._dropped += 1

    def _ingest(self) -> None:
        while not self._stop.is_set():
            try:
                self._leakage_upkeep()
            except Exception:  # a bug in the leakage must not stop the monitor: counted, shown, logged
                with self.lock:
                    self.aggregator.add_bad("internal_error")
                log.exception("monitor: live leakage failed")
            try:
                first = self._queue.get(timeout=0.1)
            except queue.Empty:
                continue
            batch = [first]
            # A bounded batch per lock hold, so ticks are never starved.
            with contextlib.suppress(queue.Empty):
                while len(batch) < 64:
                    batch.append(self._queue.get_nowait())
            self._queued_bytes -= sum(len(p) for _, p, _ in batch)
            with self.lock:
                if self._too_large:
                    self.aggregator.bad_messages["too_large"] = self._too_large
                for key, payload, t_recv_ns in batch:
                    try:
                        self.handle(key, payload, t_recv_ns)
                    except Exception:  # a bug must not stop the monitor: counted, shown, logged
                        self.aggregator.add_bad("internal_error")
                        log.exception("monitor failed on a message from %s", key)
                self.aggregator.dropped = self._dropped

    # ------------------------------------------------------------------ live leakage

    def _leakage_upkeep(self) -> None:
        """Start the linear shadow once the measured detectors are chosen, subscribe their modules' counts,
        (re)build it when parameters arrive (outside the lock: a first numba load takes seconds), let it tick."""
        leak = self.aggregator.leakage
        if not leak.chosen:
            return
        if self.shadow is None:
            from mntes_stream.monitor.shadow import LinearShadow

            shadow = LinearShadow(self.setup, leak.chosen)
            if self.params_path:
                from mntes_stream.io.paramfile import load_params

                try:
                    self._shadow_build = shadow.add_params(load_params(self.params_path))
                except ConfigError as exc:
                    shadow.state = f"parameters unreadable: {exc}"[:300]
            for text in self._provenance_texts.values():  # provenance heard before the detectors were chosen
                self._shadow_build |= shadow.add_params_toml(text, "converter provenance")
            self.shadow = shadow
            for board, module in leak.modules():
                try:
                    self._counts_subs[(board, module)] = self._session.declare_subscriber(
                        keys.counts_key(self.setup, board, module), self._on_sample)
                except Exception as exc:  # noqa: BLE001 - the rest of the monitor goes on
                    shadow.state = f"cannot subscribe to counts of b{board}m{module}: {exc}"[:300]
        if self._shadow_build:  # the ingest thread alone uses the shadow: only the leakage state needs the lock
            self._shadow_build = False
            try:
                self.shadow.build()
            except Exception as exc:  # noqa: BLE001 - bad parameters: said on the page, the monitor goes on
                self.shadow.pipeline, self.shadow.state = None, f"linear shadow not built: {exc}"[:300]
                log.warning("monitor: %s", self.shadow.state)
            with self.lock:
                leak.no_baseline = set(self.shadow.no_baseline)
        now = time.time_ns()
        with self.lock:
            for chunk in self.shadow.tick(now):
                self.aggregator.add_linear(chunk)
            leak.shadow_state = self.shadow.state
            leak.waiting(self.shadow.state)
            busy = self._measuring is not None and self._measuring.is_alive()
            pairs = leak.snapshot(now) if leak.due(now) and not busy else None
        if pairs is not None:
            # The fits (0.1-0.3 s at load; f_HWP's refinement once a minute) on a thread of their own, outside the
            # lock: neither the pages' ticks nor the ingest of power wait for them. One at a time.
            self._measuring = threading.Thread(target=self._measure, args=(leak, pairs, now),
                                               name="monitor-leakage", daemon=True)
            self._measuring.start()

    def _measure(self, leak, pairs: dict, now_ns: int) -> None:
        try:
            result = leak.measure(pairs, now_ns, self.aggregator.config.f_hwp_hz)
        except Exception:  # noqa: BLE001 - counted, shown, logged; the next period tries again
            with self.lock:
                self.aggregator.add_bad("internal_error")
            log.exception("monitor: live leakage measurement failed")
            return
        with self.lock:
            leak.last = result

    def handle(self, key: str, payload: bytes, t_recv_ns: int) -> None:
        """Decode one message and feed it to the aggregator (caller holds :attr:`lock`)."""
        agg = self.aggregator
        kind = keys.kind_of(key)
        if kind == "counts":  # only the measured detectors' modules are subscribed: the linear shadow's input
            if self.shadow is not None:
                for chunk in self.shadow.handle(key, payload, t_recv_ns):
                    agg.add_linear(chunk)
            return
        cls = _DECODERS.get(kind)
        if cls is None:
            agg.add_bad("wrong_key")
            return
        try:
            msg = cls.from_bytes(payload)
        except SchemaError as exc:
            agg.add_bad(exc.reason)
            log.debug("rejected %s: %s", key, exc)
            return
        if kind == "power":
            agg.add_power(msg, t_recv_ns)
        elif kind == "hk":
            agg.add_hk(msg, t_recv_ns)
            if self.shadow is not None:  # the linear shadow is fed as the converter is
                for chunk in self.shadow.handle(key, payload, t_recv_ns):
                    agg.add_linear(chunk)
        elif kind == "provenance":
            if self.params_path:
                return
            if self.shadow is not None:
                self._shadow_build |= self.shadow.add_params_toml(msg.params_toml, "converter provenance")
            elif len(self._provenance_texts) < 16:  # one per converter shard
                self._provenance_texts[msg.params_toml] = msg.params_toml
        else:
            agg.add_status(msg, t_recv_ns)

    # ------------------------------------------------------------------ convenience

    def view(self, selection, f_hwp_hz="config") -> dict:
        """:meth:`Aggregator.view` under the lock."""
        with self.lock:
            return self.aggregator.view(selection, f_hwp_hz)
