"""The converter's stages up to conversion: decode, sequence, housekeeping and alignment, the release (no I/O).

Each stage is a callable over a batch of items (``pipeline.items``: what
flows, and :class:`~mntes_stream.pipeline.items.Stages`, the checked list),
declaring what it takes and gives. The stages are declared once, in order, by
:func:`~mntes_stream.pipeline.pipeline.converter_stages`; every path (the live
service, offline ``convert``, replay into a converter, the G3 ``OpticalPower``
module) runs that list through :class:`~mntes_stream.pipeline.pipeline.ConverterPipeline`.
Housekeeping and alignment are one stage because a chunk is aligned with the
history *as of its release*: a reading received after it must not change it,
or the power would depend on how the messages were batched.

Every stage books what it drops in the shared :class:`Books` (counters, the
ledger, bad messages by reason): nothing leaves the flow uncounted.
"""

from __future__ import annotations

import collections
import dataclasses
import logging
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mntes_stream.core.ledger import OTHER, Ledger
from mntes_stream.core.sequence import PublisherSequences, Verdict
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io import keys
from mntes_stream.io.lean import CountsDecoder
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk
from mntes_stream.pipeline.config import PipelineConfig
from mntes_stream.pipeline.housekeeping import DelayFloor, Housekeeping, ns
from mntes_stream.pipeline.items import Counts, End, Hk, Pending, Ready, Received, Tick

__all__ = ["Align", "Books", "Decode", "Environment", "PipelineCounters", "Sequence"]

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


class Interval:
    """Figures since the last status: power chunks and samples published, their latency (ms)."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        self.chunks, self.samples, self.latency_ms = 0, 0, []
        self.arrival_ms = []  # counts chunks received: due (source publication stamp) to receipt

    def add(self, samples: int, latency_ms: float) -> None:
        self.chunks += 1
        self.samples += samples
        self.latency_ms.append(latency_ms)


class Books:
    """What every stage books: counters, the ledger, bad messages by reason, the last error, the clock.

    Parameters
    ----------
    config : PipelineConfig
    clock : callable or None
        Publication time stamp of outputs (ns); None: the receive time of the newest message.
    """

    def __init__(self, config: PipelineConfig, clock: Callable[[], int] | None):
        self.config = config
        self.counters = PipelineCounters()
        self.ledger = Ledger("converted")
        self.bad_messages: collections.Counter = collections.Counter()
        self.flag_counts: collections.Counter = collections.Counter()
        self.last_error = ""
        self.interval = Interval()
        self.clock = clock
        self.t_first_ns: int | None = None
        self.now_ns: int | None = None  # the newest receive time handled

    def advance(self, t_ns: int) -> None:
        if self.t_first_ns is None:
            self.t_first_ns = t_ns
        self.now_ns = t_ns if self.now_ns is None else max(self.now_ns, t_ns)

    def stamp(self) -> int:
        return int(self.clock()) if self.clock is not None else int(self.now_ns)

    def bad(self, reason: str, detail: str, key: str) -> None:
        self.bad_messages[reason] += 1
        self.last_error = f"{reason} on {key}: {detail}"[:500]
        n = self.bad_messages[reason]
        if n <= 10 or n % 1000 == 0:  # log, but never flood the log
            log.warning("bad message #%d (%s) on %s: %s", n, reason, key, detail)

    def dropped(self, chunk: CountsChunk, exc: Exception) -> None:
        """A chunk that could not be carried on: counted, in its ledger, said; never re-published."""
        key = keys.counts_key(self.config.setup, chunk.board, chunk.module)
        self.counters.chunks_failed += 1
        self.ledger.rejected((chunk.board, chunk.module), "internal_error")
        self.bad("internal_error", f"chunk seq {chunk.seq} dropped: {type(exc).__name__}: {exc}", key)
        log.error("internal error converting %s seq %d; chunk dropped", key, chunk.seq, exc_info=exc)

    def internal(self, exc: Exception, where: str, key: str) -> None:
        """A stage's own bug on one item: counted and shown, the service goes on."""
        self.bad("internal_error", f"{type(exc).__name__}: {exc}", key)
        log.error("internal error (%s) handling %s", where, key, exc_info=exc)


def reject(books: Books, modules, info: dict, reason: str) -> None:
    """A counts message refused: in its stream's ledger when the stream is ours, else under OTHER (bounded)."""
    b, m = info.get("board", ""), info.get("module", "")
    stream = (int(b), int(m)) if b.isdigit() and m.isdigit() else None
    if stream is None or (modules is not None and stream not in modules):
        stream = OTHER
    books.ledger.received(stream)
    books.ledger.rejected(stream, reason)


class Decode:
    """Messages to :class:`Counts` and :class:`Hk`: the key parsed, the payload decoded and matched to it.

    A message that fails is counted by reason (a counts message also in its
    stream's ledger as received and rejected) and leaves a :class:`Tick`.
    """

    name = "decode"
    takes, gives = (Received,), (Counts, Hk, Tick)

    def __init__(self, books: Books, modules):
        self.books, self.modules = books, modules
        self._decoder = CountsDecoder()
        self._keys: dict[str, dict] = {}  # parsed keys (read-only): a stream's key repeats every chunk
        # Counts keys whose last chunk was taken (our setup, a known stream): key -> (info, board, module).
        # Their next chunk takes the short path; anything it does not take goes the whole way (``_one``).
        self._taken: dict[str, tuple] = {}

    def __call__(self, items: list) -> list:
        out, books, setup, taken = [], self.books, self.books.config.setup, self._taken
        decode, arrival, append = self._decoder.decode, books.interval.arrival_ms.append, out.append
        for item in items:
            if type(item) is not tuple:
                append(item)
                continue
            key, payload, t_recv_ns = item[:3]
            key, t_recv_ns = str(key), int(t_recv_ns)
            books.advance(t_recv_ns)
            hit = taken.get(key)
            if hit is not None:
                try:
                    chunk = payload if type(payload) is CountsChunk else decode(key, payload)
                except Exception:  # noqa: BLE001 - the whole way books it by reason
                    chunk = None
                if chunk is not None and chunk.board == hit[1] and chunk.module == hit[2] and chunk.setup == setup:
                    arrival((t_recv_ns - chunk.t_pub_ns) / 1e6)
                    append(Counts(hit[0], chunk, key, t_recv_ns, item[3] if len(item) > 3 else None))
                    continue
                del taken[key]
            try:
                decoded = self._one(key, payload, t_recv_ns, setup, item[3] if len(item) > 3 else None)
            except SchemaError as exc:
                books.bad(exc.reason, str(exc), key)
                decoded = None
            except Exception as exc:  # noqa: BLE001 - the service must survive its own bugs too
                books.internal(exc, self.name, key)
                decoded = None
            out.append(decoded if decoded is not None else Tick(t_recv_ns))
        return out

    def _one(self, key: str, payload: bytes, t_recv_ns: int, setup: str, source: str | None = None):
        books = self.books
        info = self._keys.get(key)
        if info is None:
            try:
                info = keys.parse_key(key)
            except ConfigError as exc:
                books.bad("wrong_key", str(exc), key)
                return None
            if len(self._keys) >= 4096:  # peer-chosen keys only evict, never grow it
                self._keys.clear()
            self._keys[key] = info
        if info["setup"] != setup:
            books.bad("wrong_key", f"setup {info['setup']!r} is not {setup!r}", key)
            return None
        kind = info["kind"]
        if kind == "counts":
            try:  # the typed entry (``ConverterPipeline(typed=True)``) hands the chunk itself
                chunk = payload if type(payload) is CountsChunk else self._decoder.decode(key, payload)
            except SchemaError as exc:  # the key names its stream: booked there as received and rejected
                reject(books, self.modules, info, exc.reason)
                raise
            if chunk.setup != setup or info["board"] != str(chunk.board) or info["module"] != str(chunk.module):
                reject(books, self.modules, info, "wrong_key")
                books.bad("wrong_key", f"payload is setup {chunk.setup} board {chunk.board} module {chunk.module}",
                          key)
                return None
            if self.modules is not None and (chunk.board, chunk.module) not in self.modules:
                reject(books, self.modules, info, "unknown_stream")
                books.bad("unknown_stream", f"board {chunk.board} module {chunk.module}: no detector of it in the "
                                            "parameters (given no state, not converted)", key)
                return None
            books.interval.arrival_ms.append((t_recv_ns - chunk.t_pub_ns) / 1e6)
            if len(self._taken) >= 4096:  # as ``_keys``: bounded whatever keys peers choose
                self._taken.clear()
            self._taken[key] = (info, chunk.board, chunk.module)
            return Counts(info, chunk, key, t_recv_ns, source)
        if kind == "hk":
            return Hk(info, HousekeepingChunk.from_bytes(payload), key, t_recv_ns)
        books.bad("wrong_key", f"the converter does not consume {kind!r} messages", key)
        return None


def _nbytes(p: Pending) -> int:
    """What a held chunk's counts take (I and Q)."""
    return p.chunk.counts_i.nbytes + p.chunk.counts_q.nbytes


class Sequence:
    """:class:`Counts` to :class:`Pending`: each chunk's sequence number booked per ``(board, module)`` stream.

    ``core.sequence``: lost, late and duplicates (dropped) counted, a restarted
    stream resynchronised (``bad_messages["seq_reset"]``, not lost); two
    publishers sending one stream side by side numbered apart and reported
    (``conflicts``, ``PublisherSequences``); a stream not taken from its first
    chunk nor from a checkpoint: the lowest number taken (``began``). Under a
    real overload (``overloaded``, set by the live service), a chunk further
    behind its own stream's pace than ``max_lag_s`` is set aside (``aside``)
    for late conversion, the oldest shed beyond ``set_aside_bytes``.
    """

    name = "sequence"
    takes, gives = (Counts,), (Pending, Tick)

    def __init__(self, books: Books, modules, set_aside_bytes: int):
        self.books, self.modules = books, modules
        self.streams: dict[tuple[int, int], PublisherSequences] = {}
        self.conflicts: dict[tuple[int, int], int] = {}  # streams two publishers send side by side -> publishers
        self.pace: dict[tuple[int, int], DelayFloor] = {}
        self.overloaded = False
        self.aside: collections.deque[Pending] = collections.deque()
        self._aside_bytes, self._aside_max = 0, int(set_aside_bytes)
        self._max_lag_ns = ns(books.config.max_lag_s)
        self._step_times: dict[tuple, np.ndarray] = {}
        # Streams continued from a checkpoint, until their first chunk: (next number, checkpoint sample time).
        self._resumed: dict[tuple[int, int], tuple[int, int]] = {}
        # ... and for good: older chunks (history from the sources' caches) were converted before the restart.
        self._floor: dict[tuple[int, int], tuple[int, int]] = {}
        # Between a checkpoint's floor and its newest number: converted before the restart, but perhaps never
        # sent (service/checkpoint.py): (first, last number, last's sample time, the numbers taken again).
        self._refill: dict[tuple[int, int], tuple[int, int, int, set]] = {}
        # Numbers a resumed stream's first chunk skipped (counted missed while down): one that turns up after
        # all (history asked again, io/history.HistoryTopUp) is no longer missed.
        self._missed: dict[tuple[int, int], tuple[int, int]] = {}
        # Streams not continued from a checkpoint: the lowest number this converter took (status ``began_at``).
        # A converter started after the sources' history moved past a stream's first chunks never sees those.
        self.began: dict[tuple[int, int], int] = {}

    def __call__(self, items: list) -> list:
        out = []
        for item in items:
            if type(item) is not Counts:
                out.append(item)
                continue
            try:
                p = self._one(item)
            except Exception as exc:  # noqa: BLE001
                self.books.internal(exc, self.name, item.key)
                p = None
            out.append(p if p is not None else Tick(item.t_recv_ns))
        return out

    def _one(self, item: Counts) -> Pending | None:
        books, chunk = self.books, item.chunk
        stream = (chunk.board, chunk.module)
        books.counters.chunks_received += 1
        books.ledger.received(stream)
        t, t_last = self._times(chunk)
        t_first = int(t[0]) if t.size else chunk.t_pub_ns
        verdict = self._sequence(stream, chunk.seq, t_first, item.key, item.source)
        if verdict is Verdict.DUPLICATE:
            books.ledger.duplicate(stream)
            return None
        delay = item.t_recv_ns - chunk.t_pub_ns
        pace = self.pace.get(stream)
        if pace is None or verdict is Verdict.RESET:
            pace = self.pace[stream] = DelayFloor()
        lag = delay - pace.add(t_first, delay)
        p = Pending(chunk, item.t_recv_ns, t, t_last)
        if self.overloaded and lag > self._max_lag_ns and books.config.overload == "shed":
            # A real overload (the service says so), and behind its own stream's pace: converting it now
            # would make every later chunk later too. Kept for when there is time (late power).
            self._set_aside(p, lag, item.key)
            return None
        return p

    def _times(self, chunk: CountsChunk) -> tuple[np.ndarray, int | None]:
        """A chunk's sample times and the latest of them (None: no samples), computed once per readout step
        (the modules of a step share them; read-only)."""
        if chunk.t_ns is not None:
            t = chunk.t_ns
            return t, int(t.max()) if t.size else None
        key = (chunk.t0_ns, chunk.sample_rate_hz, chunk.counts_i.shape[1])
        hit = self._step_times.get(key)
        if hit is None:
            if len(self._step_times) >= 256:
                self._step_times.clear()
            t = chunk.times_ns()
            t.setflags(write=False)
            hit = self._step_times[key] = (t, int(t.max()) if t.size else None)
        return hit

    def _sequence(self, stream_id: tuple[int, int], seq: int, t_first_ns: int, key: str,
                  source: str | None = None) -> Verdict:
        """Book-keep a sequence number of ``source`` (a publisher); the tracker's verdict (``DUPLICATE``: drop it)."""
        s = self.streams.get(stream_id)
        if s is None:
            s = self.streams[stream_id] = PublisherSequences()
            if stream_id not in self._resumed:
                self.began[stream_id] = seq
                if seq > 0:
                    log.info("%s: the first chunk this converter takes is seq %d (no checkpoint): what came before "
                             "is not converted here; a recorder that holds their counts says so, and offline "
                             "`convert` of its recording gives their power", key, seq)
        elif seq < self.began.get(stream_id, seq):  # history that reached this converter after a newer chunk
            self.began[stream_id] = seq
        expected = s.next
        floor = self._floor.get(stream_id) if self._floor else None
        if floor is not None and seq < floor[0] and t_first_ns <= floor[1]:
            s.dup_known += 1  # converted by the converter that ran before this restart (its checkpoint says so)
            return Verdict.DUPLICATE
        refill = self._refill.get(stream_id) if self._refill else None
        if refill is not None and refill[0] <= seq <= refill[1] and t_first_ns <= refill[2]:
            if seq in refill[3]:
                s.dup_known += 1
                return Verdict.DUPLICATE
            refill[3].add(seq)  # the tracker stands at the newest number already: this one is not news to it
            self.books.ledger.again(stream_id)  # converted before the restart too (core.ledger.merge_restarts)
            return Verdict.LATE
        resumed = self._resumed.get(stream_id) if self._resumed else None
        if resumed is not None and (seq >= resumed[0] or t_first_ns > resumed[1]):
            del self._resumed[stream_id]  # the first chunk past the checkpoint (history before it: still to come)
        else:
            resumed = None
        verdict = s.observe(seq, t_first_ns, source)
        if s.conflict and self.conflicts.get(stream_id) != s.publishers:
            self.conflicts[stream_id] = s.publishers
            self.books.last_error = (f"conflict: {s.publishers} publishers send {key} side by side (two sources or "
                                     "bridges on one setup?): each one's chunks are numbered apart, a chunk two "
                                     "send is a duplicate")
            log.warning("%s", self.books.last_error)
        if resumed is not None and seq > resumed[0] and t_first_ns > resumed[1]:  # newer data, later numbers
            missed = seq - resumed[0]  # (a gap too long for the tracker is a reset there, but missed all the same)
            self.books.counters.chunks_missed_while_down += missed
            self._missed[stream_id] = (expected, seq - 1)
            self.books.last_error = (f"restart: {key} missed {missed} chunks (seq {expected}..{seq - 1}) while no "
                                     "converter ran")
            log.warning("%s", self.books.last_error)
        elif verdict is Verdict.LATE and self._missed and (gap := self._missed.get(stream_id)) is not None \
                and gap[0] <= seq <= gap[1]:
            self.books.counters.chunks_missed_while_down -= 1
        if verdict is Verdict.RESET:
            # Counted as a reset, not as a jump of lost chunks or a run of late ones.
            self.books.bad("seq_reset", f"sequence number {seq}, expected {expected}: stream restarted", key)
        return verdict

    def resume(self, state: dict) -> int:
        """Continue streams from a checkpoint (``ConverterPipeline.resume_sequences``); returns the streams resumed.

        A value ``(seq, t_ns)``, or ``(seq, t_ns, floor_seq, floor_t_ns)`` (``service.checkpoint``): numbers
        and missed chunks count from ``seq``, while history at or below ``floor_seq`` (default ``seq``; -1:
        none) is what the previous converter had sent and is dropped as a duplicate; history above it is
        converted again (a number below the newest: late, not lost)."""
        for stream, value in state.items():
            stream = (int(stream[0]), int(stream[1]))
            if stream in self.streams or (self.modules is not None and stream not in self.modules):
                continue
            seq, t_ns = int(value[0]), int(value[1])
            floor_seq, floor_t = (int(value[2]), int(value[3])) if len(value) > 2 else (seq, t_ns)
            s = self.streams[stream] = PublisherSequences()
            s.observe(seq, t_ns)
            self._resumed[stream] = (s.next, t_ns)
            if floor_seq >= 0:
                self._floor[stream] = (floor_seq + 1, floor_t)
            if floor_seq < seq:  # converted, maybe never sent: taken again once each, past the tracker
                self._refill[stream] = (max(floor_seq + 1, 0), seq, t_ns, set())
        return len(self._resumed)

    def _set_aside(self, p: Pending, lag_ns: int, key: str) -> None:
        """Under overload: keep the chunk for later (the oldest set-aside chunks shed beyond the budget)."""
        books = self.books
        p.late = True
        self.aside.append(p)
        self._aside_bytes += _nbytes(p)
        if len(self.aside) == 1 or len(self.aside) % 1000 == 0:
            log.warning("overload: %s seq %d %.3g s behind its stream set aside for late conversion (%d held)",
                        key, p.chunk.seq, lag_ns / 1e9, len(self.aside))
        while self._aside_bytes > self._aside_max and self.aside:
            old = self.aside.popleft()
            self._aside_bytes -= _nbytes(old)
            books.counters.chunks_shed += 1
            books.ledger.shed((old.chunk.board, old.chunk.module), "overload")
            books.bad("overload", f"chunk seq {old.chunk.seq} of {old.chunk.board}/{old.chunk.module} shed: the "
                      "set-aside budget is full (its counts are recorded: offline convert gives its power)", key)

    def unconfirmed(self) -> dict[tuple[int, int], tuple[int, int, int]]:
        """Chunks the converter before a restart converted after its last status, not taken again here.

        ``(board, module) -> (first seq, last seq, how many)`` of the checkpoint's range above its floor (see
        :meth:`resume`) less the chunks the sources' history gave again. The previous process may have died
        before their power went out, and this one could not convert them again: whether they have power is
        unknown here (a recording of the counts and power says).
        """
        out = {}
        for stream, (lo, hi, _, taken) in self._refill.items():
            n = hi - lo + 1 - len(taken)
            if n > 0:
                out[stream] = (lo, hi, n)
        return out

    def ledger_now(self) -> Ledger:
        """The ledger with each stream's never-received count as its sequence tracker says now."""
        for (b, m), s in self.streams.items():
            self.books.ledger.set_missing((b, m), s.lost)
        return self.books.ledger

    def take_aside(self, n: int) -> list[Pending]:
        """Up to ``n`` set-aside chunks, oldest first (each stream's in order)."""
        out = []
        for _ in range(min(int(n), len(self.aside))):
            p = self.aside.popleft()
            self._aside_bytes -= _nbytes(p)
            out.append(p)
        return out


class Environment:
    """A released chunk's rows (detector ids, which have parameters) and housekeeping at every sample.

    Called by the housekeeping stage at a chunk's release (:class:`Align`): a chunk's release is this
    module and the histories of ``pipeline.housekeeping``.
    """

    def __init__(self, books: Books, hk, known: frozenset):
        self.books, self.hk, self._known = books, hk, known
        self._rows: dict[tuple, tuple] = {}
        self._unmatched = 0  # channel lists none of whose rows has parameters (said once per list)
        self._last_rows: dict[tuple, tuple] = {}  # (board, module) -> (channels, detector_ids, rows) last seen
        self._last_env: tuple | None = None  # (t_bath flags, b_field flags, their union) of the last step

    def rows_for(self, chunk: CountsChunk) -> tuple:
        """Detector ids of the rows and which the converter knows (cached per channel list)."""
        last = self._last_rows.get((chunk.board, chunk.module))
        # The decoder gives a stream's chunks one channels array while its header holds: no bytes to compare.
        if last is not None and last[0] is chunk.channels and last[1] is chunk.detector_ids:
            return last[2]
        rows = self._rows_by_list(chunk)
        if len(self._last_rows) > 4096:
            self._last_rows.clear()
        self._last_rows[(chunk.board, chunk.module)] = (chunk.channels, chunk.detector_ids, rows)
        return rows

    def _rows_by_list(self, chunk: CountsChunk) -> tuple:
        cache_key = (chunk.board, chunk.module, chunk.channels.tobytes(), chunk.detector_ids)
        rows = self._rows.get(cache_key)
        if rows is None:
            ids = chunk.row_ids()  # the source's names, or the b/m/c ids
            known = np.array([d in self._known for d in ids], dtype=bool)
            if len(self._rows) > 4096:
                self._rows.clear()
            rows = self._rows[cache_key] = (ids, known, int((~known).sum()))
            if ids and not known.any():  # every row NaN: loud, once per channel list, never silent
                self._unmatched += 1
                books = self.books
                books.last_error = (f"no_detector on {keys.counts_key(books.config.setup, chunk.board, chunk.module)}"
                                    f": none of its {len(ids)} channels ({ids[0]}...) has parameters; power NaN, "
                                    "flagged UNKNOWN_CHANNEL")[:500]
                if self._unmatched <= 10 or self._unmatched % 1000 == 0:
                    log.warning("%s", books.last_error)
        return rows

    def __call__(self, p: Pending) -> Ready:
        chunk, t = p.chunk, p.t_ns
        t_bath, f_tb = self.hk.scalar("t_bath", chunk, t)
        b_field, f_b = self.hk.scalar("b_field", chunk, t)
        last = self._last_env
        if last is not None and last[0] is f_tb and last[1] is f_b:
            env_flags_t = last[2]  # the modules of a step share their aligned flags (the same cached arrays)
        else:
            env_flags_t = f_tb | f_b
            env_flags_t.setflags(write=False)
            self._last_env = (f_tb, f_b, env_flags_t)
        ids, known, n_unknown = self.rows_for(chunk)
        v_bias, f_bias = self.hk.bias(chunk, t, ids)
        f_board = self.hk.readout_flags(chunk, t)
        if f_board is not None:  # the board's own flags (dfmux-bridge): per row, so the bias is per row too
            if v_bias is None:
                v_bias, f_bias = self.hk.nominal_bias(ids, t.size), f_board
            else:
                f_bias = f_bias | f_board
        env_flags = env_flags_t if f_bias is None else env_flags_t[None, :] | f_bias
        return Ready(chunk, ids, known, n_unknown, t_bath, b_field, v_bias, env_flags, env_flags_t, p.late)


class Align:
    """Housekeeping and alignment: :class:`Hk` into the histories; :class:`Pending` chunks held, released aligned.

    A chunk waits until every *required* sensor has a reading at or after its
    last sample (interpolated, not extrapolated) or until it has waited
    ``hk_wait_s`` of receive time, whichever first; at most ``max_pending``
    are held (beyond, the oldest is released at once). A released chunk
    leaves as :class:`~mntes_stream.pipeline.items.Ready`, aligned by ``environment`` (:class:`Environment`)
    with the histories as of its release. Readings are judged by
    ``pipeline.housekeeping`` (bad ones counted by reason).
    """

    name = "housekeeping"
    takes, gives = (Pending, Hk, Tick), (Ready,)

    def __init__(self, books: Books, hk: Housekeeping, environment: Callable[[Pending], Ready]):
        self.books, self.hk, self.environment = books, hk, environment
        self.pending: collections.deque[Pending] = collections.deque()
        self._wait_ns = ns(books.config.hk_wait_s)
        self._now_ns: int | None = None

    def __call__(self, items: list) -> list:
        out = []
        for item in items:
            kind = type(item)
            if kind is Pending:
                self._tick(item.t_recv_ns)
                self.hk.note_delay((item.chunk.board, item.chunk.module), item.t_recv_ns - item.chunk.t_pub_ns)
                if not self.pending and self.hk.bracketed(item.t_last_ns):
                    # Nothing held and its housekeeping there: released at once, as ``_release`` would.
                    try:
                        out.append(self.environment(item))
                    except Exception as exc:  # noqa: BLE001
                        self.books.dropped(item.chunk, exc)
                    continue
                self.pending.append(item)
            elif kind is Hk:
                self._tick(item.t_recv_ns)
                self._hk(item)
            elif kind is Tick:
                self._tick(item.t_recv_ns)
            elif kind is End:
                self._release(out, item.force)
                out.append(item)
                continue
            else:
                out.append(item)
                continue
            self._release(out)
        return out

    def _tick(self, t_ns: int) -> None:
        self._now_ns = t_ns if self._now_ns is None else max(self._now_ns, t_ns)

    def _hk(self, item: Hk) -> None:
        hk, books = item.hk, self.books
        expected = keys.hk_sensor(hk.sensor, hk.board, hk.module)
        if hk.setup != books.config.setup or item.info["sensor"] != expected:
            books.bad("wrong_key", f"payload is setup {hk.setup} sensor {expected}", item.key)
            return
        books.counters.hk_received += 1
        try:
            problems = self.hk.add(hk, item.t_recv_ns)
        except Exception as exc:  # noqa: BLE001
            books.internal(exc, self.name, item.key)
            return
        for reason, detail in problems:
            books.bad(reason, detail, item.key)

    def _release(self, out: list, force: bool = False) -> None:
        """Chunks whose housekeeping is there (or that waited long enough) leave the queue, aligned now."""
        if not self.pending:
            return
        now = self._now_ns if self._now_ns is not None else self.books.now_ns
        keep: collections.deque[Pending] = collections.deque()
        overflow = len(self.pending) - self.books.config.max_pending
        try:
            # Each chunk leaves the queue before it is aligned: one that cannot be is counted
            # and dropped, never re-published nor left blocking the rest.
            for i in range(len(self.pending)):
                p = self.pending.popleft()
                try:
                    if force or i < overflow or self.hk.bracketed(p.t_last_ns) or now - p.t_recv_ns >= self._wait_ns:
                        out.append(self.environment(p))
                    else:
                        keep.append(p)
                except Exception as exc:  # noqa: BLE001
                    self.books.dropped(p.chunk, exc)
        finally:
            keep.extend(self.pending)
            self.pending = keep

    def tick(self, t_ns: int) -> None:
        """Receive time passes with no message (``ConverterPipeline.tick``)."""
        self._tick(t_ns)
