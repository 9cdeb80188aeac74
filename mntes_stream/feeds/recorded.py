"""Recorded power as numpy: MCAP sessions (a file, rotated files, a directory) to power blocks.

Two passes over the session's ``mntes/<setup>/power/<board>/<module>`` messages:

1. **index** (at construction): every power chunk is decoded and validated;
   per stream the reader keeps its sequence number, first/last sample time,
   receive time and detector set (a few numbers per chunk, not the power).
   This fixes the output rows (union of the detectors seen, or the
   selection), the chunks to use (time range; duplicates counted and left
   out) and their order (sample time).
2. **read** (:meth:`RecordedPower.iter_blocks`): the chunks are read again,
   in receive order, held only until the chunks before them in sample time
   have come (a reorder buffer bounded by how far out of order they were
   recorded), assembled (:class:`~mntes_stream.feeds.blocks.StreamAssembler`:
   NaN + GAP in holes, NaN + UNKNOWN_CHANNEL for absent detectors, a segment
   break for a step beyond ``max_gap_s``) and cut into blocks of
   ``block_samples``. Memory is bounded by the blocks, not the session (nor
   the length of a hole).

Time selection is on *sample* time (``start_ns <= t < end_ns``); the second
pass only reads the receive-time span of the selected chunks. Holes are filled
only between chunks of a stream: each stream starts at its first selected
sample and ends at its last (``t_start_ns``/``t_end_ns`` show where).
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field

import numpy as np

from mntes_stream.core.ids import parse_detector_id
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.feeds.blocks import (
    DEFAULT_BLOCK_SAMPLES,
    DEFAULT_MAX_GAP_S,
    BlockBuffer,
    StreamAssembler,
    StreamId,
    StreamStats,
    TodBlock,
    concat_blocks,
)
from mntes_stream.io import keys

__all__ = ["RecordedPower", "StreamIndex", "read_power", "iter_power_blocks", "DEFAULT_BLOCK_SAMPLES"]


@dataclass
class StreamIndex:
    """What the index pass learned about one stream (no power values).

    Attributes
    ----------
    stream : StreamId
    detectors : tuple of str
        Output rows, sorted by channel (or the selection, in its order).
    channels : ndarray of int32, shape (n_det,)
    chunks : list of (t_first_ns, seq, log_time_ns)
        The chunks to read, in sample-time order (duplicates left out).
    duplicate_chunks : int
    invalid_messages : int
    sample_rate_hz : float or None
        Nominal rate of the chunks (the most common one; None if all give explicit times).
    t_first_ns, t_last_ns : int
        First and last sample time of the selected chunks.
    """

    stream: StreamId
    detectors: tuple = ()
    channels: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    chunks: list = field(default_factory=list)
    duplicate_chunks: int = 0
    invalid_messages: int = 0
    sample_rate_hz: float | None = None
    t_first_ns: int = 0
    t_last_ns: int = 0


def _power_topics(session, setup: str | None, detectors: tuple | None) -> list[str]:
    """Key expressions of the power to read: of ``setup``, or of every setup recorded in ``session``."""
    if setup is not None:
        setups = [setup]
    else:
        found = {t.split("/")[1] for t in session.message_counts() if keys.kind_of(t) == "power"}
        setups = sorted(s for s in found if keys.NAME_PATTERN.match(s))
    if detectors is None:
        return [keys.power_key(s) for s in setups]
    mods = sorted({parse_detector_id(d)[:2] for d in detectors})
    return [keys.power_key(s, b, m) for s in setups for b, m in mods]


class RecordedPower:
    """The power streams of a recorded session, indexed, ready to read as numpy.

    Parameters
    ----------
    source : path, directory, or iterable of paths
        One MCAP file, a directory of rotated files, or a list of files.
    setup : str, optional
        Only this setup's streams (default: every setup in the session).
    detectors : iterable of str, optional
        Only these detectors (output rows in this order); their modules are
        the streams. A detector that never appears is a ConfigError.
    start_ns, end_ns : int, optional
        Sample-time range ``[start_ns, end_ns)``.
    board, module : int, optional
        Only streams of this board / module.
    max_gap_s : float
        A step in sample time longer than this is a segment break
        (``stats[...].segment_starts``), not a hole filled with NaN + GAP.
    progress : bool
        tqdm progress bars for the two passes.

    Raises
    ------
    ConfigError
        Nothing matches the selection, or an unknown detector was asked for.
    TransportError
        A file is not MCAP or cannot be read.
    """

    def __init__(self, source, *, setup: str | None = None, detectors: Iterable[str] | None = None,
                 start_ns: int | None = None, end_ns: int | None = None, board: int | None = None,
                 module: int | None = None, max_gap_s: float = DEFAULT_MAX_GAP_S, progress: bool = False):
        from mntes_stream.io.mcap import Session

        if start_ns is not None and end_ns is not None and int(end_ns) <= int(start_ns):
            raise ConfigError(f"empty time range: end_ns {end_ns} <= start_ns {start_ns}")
        self.selection = {
            "setup": setup,
            "detectors": None if detectors is None else list(dict.fromkeys(str(d) for d in detectors)),
            "start_ns": None if start_ns is None else int(start_ns),
            "end_ns": None if end_ns is None else int(end_ns),
            "board": board,
            "module": module,
        }
        self._dets = None if detectors is None else tuple(self.selection["detectors"])
        if self._dets is not None and not self._dets:
            raise ConfigError("an empty detector selection selects nothing")
        if setup is not None:
            keys.power_key(setup)  # a bad name is a ConfigError before any file is opened
        if not max_gap_s > 0:
            raise ConfigError(f"max_gap_s must be > 0, got {max_gap_s!r}")
        self.max_gap_s = float(max_gap_s)
        self._progress = progress
        self.session = Session(source)
        self._topics = _power_topics(self.session, setup, self._dets)
        self.files = [fi.path for fi in self.session.files]
        self.streams: dict[StreamId, StreamIndex] = {}
        self.stats: dict[StreamId, StreamStats] = {}  # filled by iter_blocks
        self._build_index(board, module)

    # ------------------------------------------------------------------ index pass

    def _build_index(self, board, module) -> None:
        from mntes_stream.io.messages import PowerChunk

        lo, hi = self.selection["start_ns"], self.selection["end_ns"]
        want = None if self._dets is None else set(self._dets)
        entries: dict[StreamId, dict] = {}
        invalid: dict[str, int] = {}
        seen_dets: set[str] = set()
        for msg in self._progress_iter(self.session.iter_messages(self._topics), "index"):
            try:
                c = PowerChunk.from_bytes(msg.payload)
            except SchemaError:
                invalid[msg.topic] = invalid.get(msg.topic, 0) + 1
                continue
            if (board is not None and c.board != board) or (module is not None and c.module != module):
                continue
            if c.n_samples == 0:
                continue
            t = c.times_ns()
            t0, t1 = int(t[0]), int(t[-1])
            if (lo is not None and t1 < lo) or (hi is not None and t0 >= hi):
                continue
            if want is not None:
                here = want.intersection(c.detector_ids)
                seen_dets |= here
            sid = StreamId(c.setup, c.board, c.module)
            e = entries.setdefault(sid, {"chunks": {}, "dups": 0, "dets": {}, "rates": {}, "t": [t0, t1]})
            key = (t0, c.seq)
            if key in e["chunks"]:
                e["dups"] += 1  # same seq and first sample: the first received is kept
                continue
            e["chunks"][key] = msg.log_time_ns
            for ch, d in zip(c.channels.tolist(), c.detector_ids):
                e["dets"].setdefault(d, ch)
            rate = c.sample_rate_hz
            e["rates"][rate] = e["rates"].get(rate, 0) + 1
            e["t"][0], e["t"][1] = min(e["t"][0], t0), max(e["t"][1], t1)
        if want is not None:
            unknown = [d for d in self._dets if d not in seen_dets]
            if unknown:
                raise ConfigError(f"detector(s) {unknown} not in the power recorded in {self._where()} (within the time range)")
        for sid in sorted(entries):
            e = entries[sid]
            if want is None:
                dets = sorted(e["dets"].items(), key=lambda kv: (kv[1], kv[0]))
            else:
                dets = [(d, parse_detector_id(d)[2]) for d in self._dets if parse_detector_id(d)[:2] == (sid.board, sid.module)]
                if not dets:
                    continue
            rates = {r: n for r, n in e["rates"].items() if r is not None}
            self.streams[sid] = StreamIndex(
                stream=sid,
                detectors=tuple(d for d, _ in dets),
                channels=np.array([ch for _, ch in dets], dtype=np.int32),
                chunks=sorted((t0, seq, log) for (t0, seq), log in e["chunks"].items()),
                duplicate_chunks=e["dups"],
                invalid_messages=sum(n for topic, n in invalid.items() if topic == keys.power_key(sid.setup, sid.board, sid.module)),
                sample_rate_hz=max(rates, key=rates.get) if rates else None,
                t_first_ns=e["t"][0],
                t_last_ns=e["t"][1],
            )
        self.invalid_messages = sum(invalid.values())
        if not self.streams:
            raise ConfigError(f"no power chunks in {self._where()} match the selection {self._selection_text()}")

    def _where(self) -> str:
        return self.files[0] if len(self.files) == 1 else f"{len(self.files)} files"

    def _selection_text(self) -> str:
        return ", ".join(f"{k}={v}" for k, v in self.selection.items() if v is not None) or "(everything)"

    def _progress_iter(self, it, what: str):
        if not self._progress:
            return it
        from tqdm import tqdm

        total = self.session.count(self._topics) if what == "index" else sum(len(s.chunks) for s in self.streams.values())
        return tqdm(it, total=total, desc=what, unit="chunk", leave=False)

    # ------------------------------------------------------------------ read pass

    @property
    def names(self) -> list[str]:
        """Observation names (``<setup>_b<board>m<module>``) of the selected streams."""
        return [sid.name for sid in self.streams]

    def iter_blocks(self, block_samples: int = DEFAULT_BLOCK_SAMPLES) -> Iterator[TodBlock]:
        """Blocks of at most ``block_samples`` samples, streams interleaved as recorded.

        Each stream's blocks come in sample order with ``first_sample``
        counting from 0; a stream's last block may be shorter; no block is
        longer, however long a hole. After the iterator is exhausted,
        :attr:`stats` holds each stream's counts.
        """
        from mntes_stream.io.messages import PowerChunk

        lo, hi = self.selection["start_ns"], self.selection["end_ns"]
        state = {}
        log_lo, log_hi = None, None
        for sid, ix in self.streams.items():
            order = {(t0, seq): i for i, (t0, seq, _) in enumerate(ix.chunks)}
            asm = StreamAssembler(ix.detectors, ix.channels, lo, hi, self.max_gap_s)
            asm.stats.duplicate_chunks = ix.duplicate_chunks
            asm.stats.invalid_messages = ix.invalid_messages
            state[sid] = _ReadState(order, asm, BlockBuffer(sid, ix.detectors, ix.channels, block_samples))
            logs = [log for _, _, log in ix.chunks]
            log_lo = min(logs) if log_lo is None else min(log_lo, min(logs))
            log_hi = max(logs) if log_hi is None else max(log_hi, max(logs))
        self.stats = {sid: st.asm.stats for sid, st in state.items()}
        topics = [keys.power_key(s.setup, s.board, s.module) for s in self.streams]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # the index pass already warned about unfinished files
            messages = self.session.iter_messages(topics, log_lo, log_hi + 1)
            for msg in self._progress_iter(messages, "read"):
                try:
                    c = PowerChunk.from_bytes(msg.payload)
                except SchemaError:
                    continue  # counted by the index pass
                st = state.get(StreamId(c.setup, c.board, c.module))
                if st is None or c.n_samples == 0:
                    continue
                t = c.times_ns()
                i = st.order.get((int(t[0]), c.seq))
                if i is None or i < st.next or i in st.held:
                    continue  # outside the selection, or a duplicate
                st.held[i] = (c, t)
                while st.next in st.held:
                    yield from st.take(st.held.pop(st.next))
                    st.next += 1
        for st in state.values():
            if st.held:  # a chunk the index saw was not found again: assemble what there is
                warnings.warn(f"{st.buf.stream.name}: {len(st.order) - st.next - len(st.held)} indexed chunk(s) not re-read", stacklevel=2)
                for i in sorted(st.held):
                    yield from st.take(st.held.pop(i))
            yield from st.buf.flush()

    def read(self) -> dict[str, TodBlock]:
        """Every selected stream as one block, by observation name (small sessions)."""
        parts: dict[str, list[TodBlock]] = {}
        for b in self.iter_blocks(DEFAULT_BLOCK_SAMPLES * 16):
            parts.setdefault(b.name, []).append(b)
        out = {}
        for sid, ix in self.streams.items():
            blocks = parts.get(sid.name)
            if blocks:
                out[sid.name] = concat_blocks(blocks)
            else:  # every chunk fell outside the range after trimming
                n = len(ix.detectors)
                out[sid.name] = TodBlock(sid.setup, sid.board, sid.module, ix.detectors, ix.channels,
                                         np.zeros(0, np.int64), np.zeros((n, 0)), np.zeros((n, 0), np.uint16))
        return out

    def to_framework(self, framework: str, **kwargs) -> list:
        """Every selected stream as a mapmaking framework's objects, one per stream and segment (small sessions).

        Parameters
        ----------
        framework : {"toast", "sotodlib", "litebird_sim"}
            ``toast.Observation``, sotodlib ``AxisManager`` or ``litebird_sim.Observation``
            (:mod:`mntes_stream.feeds.frameworks`), with the streams' nominal sample rates.
        **kwargs
            Passed to the converter (``positions=``, ...).
        """
        from mntes_stream.feeds.frameworks import from_blocks

        rates = {sid.name: ix.sample_rate_hz for sid, ix in self.streams.items()}
        return from_blocks(self.read(), framework, sample_rates=rates, **kwargs)

    # ------------------------------------------------------------------ provenance

    def provenance(self) -> list:
        """Distinct ``Provenance`` records stored in the session, oldest first.

        Returns
        -------
        list of (Provenance, log_time_ns, path)
        """
        from mntes_stream.io.mcap import PROVENANCE_ATTACHMENT
        from mntes_stream.io.messages import Provenance

        seen, out = set(), []
        for a in sorted(self.session.attachments(), key=lambda a: a.log_time_ns):
            if a.name != PROVENANCE_ATTACHMENT or a.data in seen:
                continue
            seen.add(a.data)
            try:
                out.append((Provenance.from_bytes(a.data), a.log_time_ns, a.path))
            except SchemaError:
                continue
        return out

    def recording_metadata(self) -> list[dict]:
        """The ``mntes.recording`` metadata of each file (who wrote it, how)."""
        return [dict(m.data, path=m.path) for m in self.session.metadata() if m.name == "mntes.recording"]


class _ReadState:
    __slots__ = ("order", "asm", "buf", "held", "next")

    def __init__(self, order: dict, asm: StreamAssembler, buf: BlockBuffer):
        self.order, self.asm, self.buf = order, asm, buf
        self.held: dict[int, tuple] = {}
        self.next = 0

    def take(self, item) -> Iterator[TodBlock]:
        c, t = item
        pieces = self.asm.push(c.seq, t, c.sample_rate_hz, c.detector_ids, c.p_opt_w, c.flags,
                               c.table_identity, c.converter_kind, getattr(c, "sigma_p_w", None))
        yield from self.buf.add(pieces)


def iter_power_blocks(source, *, block_samples: int = DEFAULT_BLOCK_SAMPLES, **selection) -> Iterator[TodBlock]:
    """Stream a session's power in blocks (see :class:`RecordedPower` for ``selection``)."""
    return RecordedPower(source, **selection).iter_blocks(block_samples)


def read_power(source, **selection) -> TodBlock:
    """All selected power of ONE stream (module) as a single block.

    Parameters
    ----------
    source : path, directory, or iterable of paths
    **selection
        ``setup``, ``detectors``, ``start_ns``, ``end_ns``, ``board``, ``module``,
        ``max_gap_s`` (see :class:`RecordedPower`).

    Returns
    -------
    TodBlock
        ``p_opt_w`` (n_det, n_samp) W, ``t_ns`` (n_samp,), ``flags`` (n_det, n_samp).

    Raises
    ------
    ConfigError
        The selection covers several streams (use :meth:`RecordedPower.read` or
        select ``board``/``module``/``detectors``) or nothing.
    """
    rec = RecordedPower(source, **selection)
    if len(rec.streams) != 1:
        raise ConfigError(
            f"read_power returns one stream; the selection covers {len(rec.streams)}: {rec.names} "
            "(select board/module or detectors, or use RecordedPower(...).read())"
        )
    return next(iter(rec.read().values()))

