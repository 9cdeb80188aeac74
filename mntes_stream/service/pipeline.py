"""The converter's core, free of zenoh: messages in, power/status messages out.

The live service (``service/converter.py``) feeds it what its subscriber
receives; offline re-conversion of a recording feeds it the recorded messages
in log-time order. Both get the same outputs from the same inputs because
every decision here depends only on the messages and their receive times.

What happens to a message (``handle``):

- counts chunk: decoded and validated, checked against its key, its sequence
  number booked per ``(board, module)`` stream (``core.sequence``: lost,
  late, duplicates dropped, a restarted stream resynchronised and counted as
  ``bad_messages["seq_reset"]``, not as lost). The chunk then waits until
  every *required* housekeeping sensor has a reading at or after its last
  sample (so housekeeping is interpolated, not extrapolated) or until it has
  waited ``hk_wait_s`` of receive time, whichever first;
- housekeeping (``service.housekeeping``): added to that sensor's history (``core.align.HkSeries``),
  except readings stamped more than ``hk_max_ahead_s`` ahead of the data clock
  or (bias excepted: a setting holds) more than ``hk_retention_s`` behind it,
  which are counted (``bad_messages["hk_time"]``) and dropped. The data clock
  is the receive clock minus the median delay (receive time minus ``t_pub_ns``)
  of the latest counts chunks, so a replayed old recording is judged by its own
  time. History is pruned relative to the data clock, never relative to the
  newest reading, which one bad time stamp could push anywhere;
- anything that fails to decode, or does not match its key, is counted by
  reason in the status and otherwise ignored: the service never stops on one.

A released chunk is converted with the housekeeping aligned to each sample
(``core.align``): flags HK_STALE / HK_MISSING / ENV_OUT_OF_RANGE come from
there; channels without detector parameters get UNKNOWN_CHANNEL and NaN; a
converter failure flags that chunk INVALID_INPUT and is counted, never raised.
Power is NaN wherever a flag in ``core.flags.UNUSABLE`` is set, and where
HK_STALE is (``hk_stale_power = "nan"``). Every counts chunk is booked in
``ledger`` (``core.ledger``); overload: ``service/pipeline_overload.py``.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mntes_stream.core.ledger import OTHER, Ledger
from mntes_stream.core.sequence import StreamSequence, Verdict
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io import keys
from mntes_stream.io.lean import CountsDecoder, PowerEncoder
from mntes_stream.io.messages import (
    CountsChunk,
    HousekeepingChunk,
)
from mntes_stream.service.housekeeping import DelayFloor, Housekeeping, known_modules, ns
from mntes_stream.service.pipeline_config import SCALAR_SENSORS, PipelineConfig
from mntes_stream.service.pipeline_convert import Conversion, _Ready
from mntes_stream.service.pipeline_overload import Overload
from mntes_stream.service.pipeline_status import Reporting

__all__ = ["PipelineConfig", "ConverterPipeline", "PipelineCounters", "SCALAR_SENSORS"]

log = logging.getLogger("mntes_stream.converter")

@dataclass
class PipelineCounters:
    """Cumulative counts since start (sequence counts are summed over the streams' trackers)."""

    chunks_received: int = 0
    chunks_converted: int = 0
    chunks_failed: int = 0
    samples_converted: int = 0
    chunks_shed: int = 0
    hk_received: int = 0
    hk_stale_samples: int = 0
    hk_missing_samples: int = 0
    unknown_channel_samples: int = 0
    chunks_missed_while_down: int = 0  # published between a checkpoint and this start (resume_sequences)

    def as_dict(self) -> dict[str, int]:
        return dataclasses.asdict(self)


@dataclass
class _Pending:
    chunk: CountsChunk
    t_recv_ns: int
    t_ns: np.ndarray
    t_last_ns: int | None
    late: bool = False  # set aside under overload: converted later, published as late power


class ConverterPipeline(Overload, Conversion, Reporting):
    """Counts + housekeeping in, power chunks + status out (no I/O).

    Parameters
    ----------
    converter
        Has ``kind``, ``identity``, ``detector_ids`` and
        ``convert(detector_ids, counts_i, counts_q, env) -> PowerBlock``
        (``core.convert.make_converter``).
    config : PipelineConfig
    params : dict or list of DetectorParams, optional
        The detector parameters (provenance and nominal bias); default
        ``converter.params`` when it has them.
    clock : callable or None
        Publication time stamp of outputs (ns); default ``time.time_ns``.
        None stamps outputs with the receive time of the message being handled,
        which makes offline re-conversion reproducible.
    owns : dict, optional
        The part of the focal plane a converter shard owns, for its provenance
        (``service.ownership.owns_summary``); None: the whole of it.
    threads : int
        Threads converting a large run of chunks side by side (1: the calling
        thread alone). The power is the same whatever the number.
    set_aside_bytes : int
        Counts held at most under overload for late conversion; beyond, the
        oldest set-aside chunk is shed (counted in the ledger).
    uncertainty : core.uncertainty.UncertaintySettings, optional
        Given: every power chunk carries each sample's sigma_P and LOW_RESPONSIVITY is
        flagged (``core.uncertainty.sigma_p_block``); None: neither (the power is the same).

    Attribute ``overloaded`` (False unless the live service sets it, so offline
    runs never shed): while True, a chunk further behind its stream's pace than
    ``max_lag_s`` is set aside, not converted now; :meth:`convert_late`
    converts set-aside chunks when the service has time. ``ledger``
    (``core.ledger.Ledger``) accounts for every chunk of every stream.

    Attribute ``owns_status`` (a callable returning a dict, or None) gives the
    status its ``owns``: what is owned, published and held back now.
    """

    def __init__(self, converter, config: PipelineConfig | None = None, params=None,
                 clock: Callable[[], int] | None = time.time_ns, owns: dict | None = None, threads: int = 1,
                 set_aside_bytes: int = 256 << 20, uncertainty=None):
        self.converter = converter
        self.ledger = Ledger("converted")
        self.overloaded = False
        self._aside: collections.deque[_Pending] = collections.deque()
        self._aside_bytes, self._aside_max = 0, int(set_aside_bytes)
        if not isinstance(threads, int) or threads < 1:
            raise ConfigError(f"threads must be an integer >= 1, got {threads!r}")
        self._threads, self._executor = threads, None
        self._owns = dict(owns or {})
        self.owns_status: Callable[[], dict] | None = None
        self.config = config or PipelineConfig()
        self._clock = clock
        if params is None:
            params = getattr(converter, "params", None)
        if isinstance(params, dict):
            params = list(params.values())
        self._params = list(params) if params is not None else []
        self._known = frozenset(converter.detector_ids)
        self._modules = known_modules(self._known)
        self._wait_ns = ns(self.config.hk_wait_s)
        self._status_ns = ns(self.config.status_interval_s)
        self._max_lag_ns = ns(self.config.max_lag_s)
        self.hk = Housekeeping(self.config, {p.detector_id: float(p.v_thev_v) for p in self._params}, self._modules)
        # Per-stream state exists only for the modules the parameters know: bounded by construction.
        self._streams: dict[tuple[int, int], StreamSequence] = {}
        self._pace: dict[tuple[int, int], DelayFloor] = {}
        self._pending: collections.deque[_Pending] = collections.deque()
        self._ready: list[_Ready] = []
        self._table_identity, self._kind = str(converter.identity), str(converter.kind)
        self._decoder = CountsDecoder()
        self._step_times: dict[tuple, np.ndarray] = {}
        self._encoder = PowerEncoder(self.config.setup, self._table_identity, self._kind)
        self._noise = None
        if uncertainty is not None:
            from mntes_stream.io.noisefile import noise_model_for  # reads the measured-noise file, if one is named

            self._noise = noise_model_for(list(converter.params), uncertainty)
        self._rows: dict[tuple, tuple] = {}
        # Streams continued from a checkpoint, until their first chunk: (next number, checkpoint sample time).
        self._resumed: dict[tuple[int, int], tuple[int, int]] = {}
        # ... and for good: older chunks (history from the sources' caches) were converted before the restart.
        self._floor: dict[tuple[int, int], tuple[int, int]] = {}
        self._provenance: bytes | None = None
        self._t_created_ns = time.time_ns()
        self._t_first_ns: int | None = None
        self._now_ns: int | None = None
        self._next_status_ns: int | None = None
        self._last_status_ns: int | None = None
        self._interval_latency_ms: list[float] = []
        self._interval_chunks = 0
        self._interval_samples = 0
        self.counters = PipelineCounters()
        self.bad_messages = collections.Counter()
        self.flag_counts = collections.Counter()
        self.last_error = ""
        self._unmatched = 0  # channel lists none of whose rows has parameters (said once per list)
        if self._modules is None and self._known:
            # Stream rows are always b<B>m<M>c<C>: an id of another form can never match one. Said now, once;
            # and only the modules of the other ids get state (else any peer-chosen module would).
            odd = sorted(d for d in self._known if known_modules([d]) is None)
            self.last_error = (f"parameters: {len(odd)} of {len(self._known)} detector ids (e.g. {odd[0]!r}) are not "
                               "of the form b<board>m<module>c<channel> and can match no stream row")[:500]
            log.warning("%s", self.last_error)
            self._modules = known_modules(self._known.difference(odd))
            self.hk = Housekeeping(self.config, {p.detector_id: float(p.v_thev_v) for p in self._params},
                                   self._modules)

    # ------------------------------------------------------------------ public API

    @property
    def pending(self) -> int:
        """Chunks held back waiting for housekeeping."""
        return len(self._pending)

    def handle(self, key: str, payload: bytes, t_recv_ns: int) -> list[tuple[str, bytes]]:
        """Process one received message; returns ``(key, payload)`` messages to publish."""
        return self.handle_many(((key, payload, t_recv_ns),))

    def handle_many(self, items) -> list[tuple[str, bytes]]:
        """Process received ``(key, payload, t_recv_ns)`` messages in order; returns the messages to publish.

        Each message is dispatched and the chunks it releases are aligned as
        :meth:`handle` would, message by message; the released chunks are then
        converted together (:meth:`_convert_ready`), so the power is the same
        as from :meth:`handle` called per message, for less work per chunk.
        """
        out: list[tuple[str, bytes]] = []
        for key, payload, t_recv_ns in items:
            self._advance(t_recv_ns)
            self._guarded(self._dispatch, key, str(key), payload, int(t_recv_ns))
            self._guarded(self._release, key, out)
        self._guarded(self._convert_ready, "convert", out)
        self._guarded(self._maybe_status, "status", out)
        return out

    def tick(self, t_now_ns: int) -> list[tuple[str, bytes]]:
        """Let time pass without a message: release chunks that waited long enough, status when due."""
        out: list[tuple[str, bytes]] = []
        self._advance(t_now_ns)
        self._guarded(self._release, "tick", out)
        self._guarded(self._convert_ready, "tick", out)
        self._guarded(self._maybe_status, "tick", out)
        return out

    def _guarded(self, step, key, *args) -> None:
        try:
            step(*args)
        except Exception as exc:  # the service must survive its own bugs too: counted and shown
            self._bad("internal_error", f"{type(exc).__name__}: {exc}", str(key))
            log.exception("internal error (%s) handling %s", getattr(step, "__name__", step), key)

    def flush(self) -> list[tuple[str, bytes]]:
        """Convert everything still held (with what housekeeping there is) and emit a final status."""
        out: list[tuple[str, bytes]] = []
        self._guarded(self._release, "flush", out, True)
        self._guarded(self._convert_ready, "flush", out)
        out += self.convert_late(len(self._aside))
        if self._now_ns is not None:
            self._guarded(lambda: out.append(self._emit_status()), "flush")
        return out

    def resume_sequences(self, state: dict) -> int:
        """Continue streams from a previous converter's :meth:`sequence_state` (before any chunk arrives).

        A stream's first chunk then tells what was published while no converter ran: counted in
        ``chunks_lost`` and ``chunks_missed_while_down``, and said once per stream (log, ``last_error``).
        A stream that restarted meanwhile is a ``seq_reset`` as usual. Returns the streams resumed.
        """
        for stream, (seq, t_ns) in state.items():
            stream = (int(stream[0]), int(stream[1]))
            if stream in self._streams or (self._modules is not None and stream not in self._modules):
                continue
            s = self._streams[stream] = StreamSequence()
            s.observe(int(seq), int(t_ns))
            self._resumed[stream] = self._floor[stream] = (s.next, int(t_ns))
        return len(self._resumed)

    # ------------------------------------------------------------------ internals

    def _advance(self, t_ns: int) -> None:
        t_ns = int(t_ns)
        if self._t_first_ns is None:
            self._t_first_ns = t_ns
            self._last_status_ns = t_ns
            self._next_status_ns = t_ns + self._status_ns
        self._now_ns = t_ns if self._now_ns is None else max(self._now_ns, t_ns)

    def _stamp(self) -> int:
        return int(self._clock()) if self._clock is not None else int(self._now_ns)

    def _bad(self, reason: str, detail: str, key: str) -> None:
        self.bad_messages[reason] += 1
        self.last_error = f"{reason} on {key}: {detail}"[:500]
        n = self.bad_messages[reason]
        if n <= 10 or n % 1000 == 0:  # log, but never flood the log
            log.warning("bad message #%d (%s) on %s: %s", n, reason, key, detail)

    def _dispatch(self, key: str, payload: bytes, t_recv_ns: int) -> None:
        try:
            info = keys.parse_key(key)
        except ConfigError as exc:
            self._bad("wrong_key", str(exc), key)
            return
        if info["setup"] != self.config.setup:
            self._bad("wrong_key", f"setup {info['setup']!r} is not {self.config.setup!r}", key)
            return
        kind = info["kind"]
        try:
            if kind == "counts":
                try:
                    chunk = self._decoder.decode(key, payload)
                except SchemaError as exc:  # the key names its stream: booked there as received and rejected
                    self._reject(info, exc.reason)
                    raise
                self._on_counts(info, chunk, key, t_recv_ns)
            elif kind == "hk":
                self._on_hk(info, HousekeepingChunk.from_bytes(payload), key, t_recv_ns)
            else:
                self._bad("wrong_key", f"the converter does not consume {kind!r} messages", key)
        except SchemaError as exc:
            self._bad(exc.reason, str(exc), key)

    def _reject(self, info: dict, reason: str) -> None:
        """A counts message refused: in its stream's ledger when the stream is ours, else under OTHER (bounded)."""
        b, m = info.get("board", ""), info.get("module", "")
        stream = (int(b), int(m)) if b.isdigit() and m.isdigit() else None
        if stream is None or (self._modules is not None and stream not in self._modules):
            stream = OTHER
        self.ledger.received(stream)
        self.ledger.rejected(stream, reason)

    def _on_counts(self, info: dict, chunk: CountsChunk, key: str, t_recv_ns: int) -> None:
        if chunk.setup != self.config.setup or info["board"] != str(chunk.board) or info["module"] != str(chunk.module):
            self._reject(info, "wrong_key")
            self._bad("wrong_key", f"payload is setup {chunk.setup} board {chunk.board} module {chunk.module}", key)
            return
        stream = (chunk.board, chunk.module)
        if self._modules is not None and stream not in self._modules:
            self._reject(info, "unknown_stream")
            self._bad("unknown_stream", f"board {chunk.board} module {chunk.module}: no detector of it in the "
                                        "parameters (given no state, not converted)", key)
            return
        self.counters.chunks_received += 1
        self.ledger.received(stream)
        t = self._times(chunk)
        t_first = int(t[0]) if t.size else chunk.t_pub_ns
        verdict = self._sequence(stream, chunk.seq, t_first, key)
        if verdict is Verdict.DUPLICATE:
            self.ledger.duplicate(stream)
            return
        delay = t_recv_ns - chunk.t_pub_ns
        pace = self._pace.get(stream)
        if pace is None or verdict is Verdict.RESET:
            pace = self._pace[stream] = DelayFloor()
        lag = delay - pace.add(t_first, delay)
        self.hk.note_delay(stream, delay)
        p = _Pending(chunk, t_recv_ns, t, int(t.max()) if t.size else None)
        if self.overloaded and lag > self._max_lag_ns and self.config.overload == "shed":
            # A real overload (the service says so), and behind its own stream's pace: converting it now
            # would make every later chunk later too. Kept for when there is time (late power).
            self._set_aside(p, lag, key)
            return
        self._pending.append(p)

    def _times(self, chunk: CountsChunk) -> np.ndarray:
        """A chunk's sample times, computed once per readout step (the modules of a step share them; read-only)."""
        if chunk.t_ns is not None:
            return chunk.t_ns
        key = (chunk.t0_ns, chunk.sample_rate_hz, chunk.counts_i.shape[1])
        t = self._step_times.get(key)
        if t is None:
            if len(self._step_times) >= 256:
                self._step_times.clear()
            t = self._step_times[key] = chunk.times_ns()
            t.setflags(write=False)
        return t

    def _sequence(self, stream_id: tuple[int, int], seq: int, t_first_ns: int, key: str) -> Verdict:
        """Book-keep a sequence number; the tracker's verdict (``DUPLICATE``: drop it)."""
        s = self._streams.get(stream_id)
        if s is None:
            s = self._streams[stream_id] = StreamSequence()
        expected = s.next
        floor = self._floor.get(stream_id) if self._floor else None
        if floor is not None and seq < floor[0] and t_first_ns <= floor[1]:
            s.duplicated += 1  # converted by the converter that ran before this restart (its checkpoint says so)
            return Verdict.DUPLICATE
        resumed = self._resumed.pop(stream_id, None) if self._resumed else None
        verdict = s.observe(seq, t_first_ns)
        if resumed is not None and seq > resumed[0] and t_first_ns > resumed[1]:  # newer data, later numbers
            missed = seq - resumed[0]  # (a gap too long for the tracker is a reset there, but missed all the same)
            self.counters.chunks_missed_while_down += missed
            self.last_error = f"restart: {key} missed {missed} chunks (seq {expected}..{seq - 1}) while no converter ran"
            log.warning("%s", self.last_error)
        if verdict is Verdict.RESET:
            # Counted as a reset, not as a jump of lost chunks or a run of late ones.
            self._bad("seq_reset", f"sequence number {seq}, expected {expected}: stream restarted", key)
        return verdict

    def _on_hk(self, info: dict, hk: HousekeepingChunk, key: str, t_recv_ns: int) -> None:
        sensor = info["sensor"]
        expected = keys.hk_sensor(hk.sensor, hk.board, hk.module)
        if hk.setup != self.config.setup or sensor != expected:
            self._bad("wrong_key", f"payload is setup {hk.setup} sensor {expected}", key)
            return
        self.counters.hk_received += 1
        for reason, detail in self.hk.add(hk, t_recv_ns):
            self._bad(reason, detail, key)

    def _release(self, out: list, force: bool = False) -> None:
        """Chunks whose housekeeping is there (or that waited long enough) leave the queue, with their
        environment aligned now; they are converted together by :meth:`_convert_ready`."""
        if not self._pending:
            return
        now = self._now_ns
        keep: collections.deque[_Pending] = collections.deque()
        overflow = len(self._pending) - self.config.max_pending
        try:
            # Each chunk leaves the queue before it is converted: one that cannot be
            # converted is counted and dropped, never re-published nor left blocking the rest.
            for i in range(len(self._pending)):
                p = self._pending.popleft()
                try:
                    if force or i < overflow or self.hk.bracketed(p.t_last_ns) or now - p.t_recv_ns >= self._wait_ns:
                        self._ready.append(self._environment(p))
                    else:
                        keep.append(p)
                except Exception as exc:
                    self._dropped(p.chunk, exc)
        finally:
            keep.extend(self._pending)
            self._pending = keep

    def _dropped(self, chunk: CountsChunk, exc: Exception) -> None:
        key = keys.counts_key(self.config.setup, chunk.board, chunk.module)
        self.counters.chunks_failed += 1
        self.ledger.rejected((chunk.board, chunk.module), "internal_error")
        self._bad("internal_error", f"chunk seq {chunk.seq} dropped: {type(exc).__name__}: {exc}", key)
        log.error("internal error converting %s seq %d; chunk dropped", key, chunk.seq, exc_info=exc)
