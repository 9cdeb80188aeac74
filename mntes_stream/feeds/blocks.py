"""Time-ordered data blocks and the per-stream assembly of chunks into gap-explicit time series (pure numpy).

A *stream* is the power of one module: ``(setup, board, module)``. Its chunks
are assembled in sample-time order by :class:`StreamAssembler`, which makes
every irregularity explicit instead of silent:

- **gap** (missing chunk, or missing sequence numbers that left a hole in
  time): the hole is filled with NaN power and ``flags.GAP`` on the regular
  sample grid continued from the last sample (``t_last + round(k * period)``);
  a hole is a step larger than 1.5 sample periods. The fill is made lazily
  (:class:`GapFill`), in pieces of at most ``block_samples``: a long hole
  never costs more memory than a block;
- **segment break** (a step in time beyond ``max_gap_s``, forwards: a long
  pause or a corrupt far-future timestamp; or backwards: a clock reset, or
  the return after such a timestamp): not filled; the stream goes on from
  the new time and the break is reported (``StreamStats.segment_starts``).
  Sample times increase strictly *within* a segment;
- **absent detector** (a row of the stream that a chunk does not carry, or a
  selected detector that is not there): NaN and ``flags.UNKNOWN_CHANNEL``;
- **duplicate chunk** (same ``seq`` and first sample time as one already
  taken): dropped and counted;
- **overlap** (samples at or before the last sample already emitted, e.g. a
  late chunk whose span was already filled as a gap): dropped and counted.

Power values are copied, never recomputed: what comes out is bitwise what the
converter published.
"""

from __future__ import annotations

import bisect
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import NamedTuple

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core.sequence import StreamSequence, Verdict
from mntes_stream.errors import ConfigError

__all__ = ["TodBlock", "StreamId", "StreamStats", "StreamAssembler", "BlockBuffer", "GapFill", "Piece",
           "iter_pieces", "concat_blocks", "stream_name", "DEFAULT_BLOCK_SAMPLES", "DEFAULT_MAX_GAP_S"]

GAP_FACTOR = 1.5  # a step longer than this many sample periods is a hole
DEFAULT_BLOCK_SAMPLES = 8192
DEFAULT_MAX_GAP_S = 3600.0  # a longer step is a segment break, not a hole to fill
# Backstop for a hole within max_gap_s but of absurdly many samples (a corrupt sample rate).
MAX_FILL_SAMPLES = 1 << 24


@dataclass(frozen=True, order=True)
class StreamId:
    """One module's power stream."""

    setup: str
    board: int
    module: int

    @property
    def name(self) -> str:
        return stream_name(self.setup, self.board, self.module)


def stream_name(setup: str, board: int, module: int) -> str:
    """Observation name of a stream: ``<setup>_b<board>m<module>`` (HDF5 group name)."""
    return f"{setup}_b{int(board)}m{int(module)}"


def _readonly(a: np.ndarray) -> np.ndarray:
    a.flags.writeable = False
    return a


def _distinct(values: Iterable) -> tuple:
    """Distinct non-empty values in order of first appearance."""
    return tuple(dict.fromkeys(v for v in values if v))


@dataclass(frozen=True, eq=False)
class TodBlock:
    """Time-ordered data: the power of one module stream over consecutive samples.

    Attributes
    ----------
    setup : str
    board, module : int
    detectors : tuple of str, length n_det
        Detector ids of the rows.
    channels : ndarray of int32, shape (n_det,)
    t_ns : ndarray of int64, shape (n_samp,)
        Sample times, ns since the Unix epoch, strictly increasing within a
        segment (see ``StreamStats.segment_starts``).
    p_opt_w : ndarray of float64, shape (n_det, n_samp)
        Optical power (W); NaN wherever no usable power (see ``flags``).
    flags : ndarray of uint16, shape (n_det, n_samp)
        ``core.flags`` bits; ``GAP`` in missing chunks, ``UNKNOWN_CHANNEL`` where
        a detector is absent.
    first_sample : int
        Index of ``t_ns[0]`` in the assembled stream (0 for a whole stream).
    table_identities : tuple of str
        Identities of the response tables (``PowerChunk.table_identity``) that
        produced the power in this block, in order of first appearance;
        empty for a block of gap fill only.
    sigma_p_w : ndarray of float32, shape (n_det, n_samp), or None
        Per-sample power uncertainty (``PowerChunk.sigma_p_w``) where the
        converter gave it, NaN elsewhere; None when no chunk of the block had it.

    Arrays are read-only; ``np.array(block.p_opt_w)`` gives a writable copy.
    """

    setup: str
    board: int
    module: int
    detectors: tuple
    channels: np.ndarray
    t_ns: np.ndarray
    p_opt_w: np.ndarray
    flags: np.ndarray
    first_sample: int = 0
    table_identities: tuple = ()
    sigma_p_w: np.ndarray | None = None

    def __post_init__(self) -> None:
        dets = tuple(str(d) for d in self.detectors)
        ch = np.asarray(self.channels, dtype=np.int32)
        t = np.asarray(self.t_ns, dtype=np.int64)
        p = np.asarray(self.p_opt_w, dtype=np.float64)
        f = np.asarray(self.flags, dtype=fl.FLAG_DTYPE)
        shape = (len(dets), t.size)
        if ch.shape != (len(dets),) or t.ndim != 1 or p.shape != shape or f.shape != shape:
            raise ConfigError(
                f"TodBlock: {len(dets)} detectors, channels {ch.shape}, t_ns {t.shape}, "
                f"p_opt_w {p.shape}, flags {f.shape} are inconsistent (want (n_det, n_samp) = {shape})"
            )
        for name, value in (("detectors", dets), ("channels", ch), ("t_ns", t), ("p_opt_w", p), ("flags", f)):
            object.__setattr__(self, name, value if name == "detectors" else _readonly(value))
        if self.sigma_p_w is not None:
            sp = np.asarray(self.sigma_p_w, dtype=np.float32)
            if sp.shape != shape:
                raise ConfigError(f"TodBlock: sigma_p_w {sp.shape} is not (n_det, n_samp) = {shape}")
            object.__setattr__(self, "sigma_p_w", _readonly(sp))
        object.__setattr__(self, "table_identities", tuple(str(s) for s in self.table_identities))

    @property
    def stream(self) -> StreamId:
        return StreamId(self.setup, self.board, self.module)

    @property
    def name(self) -> str:
        """Observation name (``<setup>_b<board>m<module>``)."""
        return stream_name(self.setup, self.board, self.module)

    @property
    def n_detectors(self) -> int:
        return len(self.detectors)

    @property
    def n_samples(self) -> int:
        return int(self.t_ns.size)

    @property
    def t_s(self) -> np.ndarray:
        """Sample times in float64 seconds since the epoch (sub-microsecond resolution)."""
        return self.t_ns / 1e9

    def select(self, detectors: Iterable[str]) -> TodBlock:
        """The rows of ``detectors`` (in that order); ConfigError for an id not here."""
        row = {d: r for r, d in enumerate(self.detectors)}
        want = list(detectors)
        missing = [d for d in want if d not in row]
        if missing:
            raise ConfigError(f"{self.name}: no detector(s) {missing}")
        idx = np.array([row[d] for d in want], dtype=np.intp)
        return TodBlock(self.setup, self.board, self.module, tuple(want), self.channels[idx], self.t_ns,
                        self.p_opt_w[idx], self.flags[idx], self.first_sample, self.table_identities,
                        None if self.sigma_p_w is None else self.sigma_p_w[idx])


def concat_blocks(blocks: list[TodBlock]) -> TodBlock:
    """Consecutive blocks of one stream (same rows) as one block."""
    if not blocks:
        raise ConfigError("no blocks to concatenate")
    b0 = blocks[0]
    if len(blocks) == 1:
        return b0
    for b in blocks[1:]:
        if b.stream != b0.stream or b.detectors != b0.detectors:
            raise ConfigError("concat_blocks: blocks of different streams or rows")
    return TodBlock(b0.setup, b0.board, b0.module, b0.detectors, b0.channels,
                    np.concatenate([b.t_ns for b in blocks]), np.concatenate([b.p_opt_w for b in blocks], axis=1),
                    np.concatenate([b.flags for b in blocks], axis=1), b0.first_sample,
                    _distinct(s for b in blocks for s in b.table_identities),
                    _sigma_concat([b.sigma_p_w for b in blocks], [b.p_opt_w.shape for b in blocks]))


def _sigma_concat(parts: list, shapes: list) -> np.ndarray | None:
    """Per-sample sigma_P of consecutive parts side by side; NaN for parts without; None if none has it."""
    if all(x is None for x in parts):
        return None
    return np.concatenate([np.full(sh, np.nan, dtype=np.float32) if x is None else np.asarray(x, np.float32)
                           for x, sh in zip(parts, shapes)], axis=1)


@dataclass
class StreamStats:
    """What assembling one stream found (counts, cumulative).

    Attributes
    ----------
    chunks : int
        Chunks whose samples were used.
    samples : int
        Samples handed out per detector row (data and gap fill).
    duplicate_chunks : int
        Same ``seq`` and first sample time as a chunk already taken: dropped.
    overlap_samples : int
        Samples at or before the last one emitted (late chunks): dropped.
    gaps, gap_samples : int
        Holes in time and the samples filled with NaN + GAP.
    seq_gaps : int
        Sequence numbers skipped and not received since (``core.sequence``).
    absent_samples : int
        Detector-samples filled with NaN + UNKNOWN_CHANNEL (absent detectors).
    invalid_messages : int
        Payloads that did not decode as a power chunk (skipped).
    segment_starts : list of int
        Sample indices (in the stream) where a new segment starts after a
        step in time beyond ``max_gap_s`` (not filled); empty for one segment.
    table_identities, converter_kinds : list of str
        Distinct values of the chunks used, in order of first appearance.
    """

    chunks: int = 0
    samples: int = 0
    duplicate_chunks: int = 0
    overlap_samples: int = 0
    gaps: int = 0
    gap_samples: int = 0
    seq_gaps: int = 0
    absent_samples: int = 0
    invalid_messages: int = 0
    segment_starts: list = field(default_factory=list)
    table_identities: list = field(default_factory=list)
    converter_kinds: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return {k: (list(v) if isinstance(v, list) else v) for k, v in self.__dict__.items()}


class Piece(NamedTuple):
    """Samples handed out by the assembler (arrays of its rows at the time)."""

    t_ns: np.ndarray  # (n,) int64
    p_opt_w: np.ndarray  # (n_rows, n) float64
    flags: np.ndarray  # (n_rows, n) uint16
    table_identity: str | None  # None for gap fill
    sigma_p_w: np.ndarray | None = None  # (n_rows, n) float32, where the converter gave it


@dataclass(frozen=True)
class GapFill:
    """A hole's NaN + GAP samples, not yet made: times ``t_last_ns + round(k * period_ns)``, ``k_lo <= k < k_hi``."""

    t_last_ns: int
    period_ns: float
    k_lo: int
    k_hi: int
    n_rows: int

    @property
    def size(self) -> int:
        return self.k_hi - self.k_lo

    def take(self, start: int, stop: int) -> Piece:
        """Samples ``start:stop`` of the fill as a :class:`Piece`."""
        k = np.arange(self.k_lo + start, self.k_lo + stop, dtype=np.int64)
        t = self.t_last_ns + np.rint(k * self.period_ns).astype(np.int64)
        shape = (self.n_rows, t.size)
        return Piece(t, np.full(shape, np.nan), np.full(shape, fl.GAP, dtype=fl.FLAG_DTYPE), None)


def iter_pieces(pieces: Iterable, max_samples: int) -> Iterator[Piece]:
    """``pieces`` with each :class:`GapFill` made in pieces of at most ``max_samples``."""
    for piece in pieces:
        if isinstance(piece, GapFill):
            for a in range(0, piece.size, max_samples):
                yield piece.take(a, min(a + max_samples, piece.size))
        else:
            yield piece


class StreamAssembler:
    """Chunks of one stream in, gap-explicit pieces on fixed detector rows out.

    Parameters
    ----------
    detectors : sequence of str
        The output rows (n_rows).
    channels : sequence of int, length n_rows
    start_ns, end_ns : int, optional
        Keep samples with ``start_ns <= t < end_ns`` (gap fill included).
    max_gap_s : float
        A step in time longer than this (either way) is a segment break, not a hole.
    """

    def __init__(self, detectors, channels, start_ns: int | None = None, end_ns: int | None = None,
                 max_gap_s: float = DEFAULT_MAX_GAP_S):
        if not max_gap_s > 0:
            raise ConfigError(f"max_gap_s must be > 0, got {max_gap_s!r}")
        self.detectors = tuple(detectors)
        self.channels = np.asarray(channels, dtype=np.int32)
        self._row = {d: r for r, d in enumerate(self.detectors)}
        self._lo = -(1 << 63) if start_ns is None else int(start_ns)
        self._hi = (1 << 63) - 1 if end_ns is None else int(end_ns)
        self.max_gap_ns = int(max_gap_s * 1e9)
        self.last_t_ns: int | None = None
        self.period_ns: float | None = None
        self.sequence = StreamSequence()
        self._maps: dict[tuple, tuple] = {}
        self.stats = StreamStats()

    def _map(self, ids: tuple) -> tuple[np.ndarray, np.ndarray, bool]:
        """(source rows, destination rows, same_rows) for a chunk's detector ids.

        ``same_rows``: the chunk's rows are exactly the output rows, in order (copied as they are).
        """
        m = self._maps.get(ids)
        if m is None:
            pairs = [(i, self._row[d]) for i, d in enumerate(ids) if d in self._row]
            src = np.array([i for i, _ in pairs], dtype=np.intp)
            dst = np.array([r for _, r in pairs], dtype=np.intp)
            m = self._maps[ids] = (src, dst, ids == self.detectors)
        return m

    def add_rows(self, detector_ids, channels) -> bool:
        """Extend the rows with detectors not yet there (kept sorted by channel); True if any."""
        new = [(int(c), d) for c, d in zip(np.asarray(channels).tolist(), detector_ids) if d not in self._row]
        if not new:
            return False
        rows = sorted(list(zip(self.channels.tolist(), self.detectors)) + new)
        self.channels = np.array([c for c, _ in rows], dtype=np.int32)
        self.detectors = tuple(d for _, d in rows)
        self._row = {d: r for r, d in enumerate(self.detectors)}
        self._maps.clear()
        return True

    def _fill(self, period_ns: float, n_fill: int, t_next_ns: int) -> GapFill:
        """The grid points ``1..n_fill`` after the last sample that lie before ``t_next_ns`` and in range."""
        last = self.last_t_ns
        ks = range(1, n_fill + 1)

        def t_of(k: int) -> int:
            return last + int(round(k * period_ns))  # round half to even, as np.rint in GapFill.take

        i_lo = bisect.bisect_left(ks, self._lo, key=t_of)
        i_hi = bisect.bisect_left(ks, min(t_next_ns, self._hi), key=t_of)
        return GapFill(last, period_ns, 1 + i_lo, 1 + max(i_lo, i_hi), len(self.detectors))

    def push(self, seq: int, t_ns: np.ndarray, sample_rate_hz: float | None, detector_ids: tuple,
             p_opt_w: np.ndarray, flags: np.ndarray, table_identity: str = "",
             converter_kind: str = "", sigma_p_w: np.ndarray | None = None) -> list:
        """Add the next chunk (in sample-time order); returns what to append, in order.

        Parameters
        ----------
        seq : int
        t_ns : ndarray of int64, shape (n,)
        sample_rate_hz : float or None
            None for chunks with explicit times (the period is then their median step).
        detector_ids : tuple of str, length n_ch
        p_opt_w : ndarray of float64, shape (n_ch, n)
        flags : ndarray of uint16, shape (n_ch, n)
        table_identity, converter_kind : str
            The chunk's, recorded in :attr:`stats` when its samples are used.
        sigma_p_w : ndarray of float32, shape (n_ch, n), optional
            The chunk's per-sample uncertainty, when it carries one.

        Returns
        -------
        list of Piece or GapFill
            A :class:`GapFill` is not made yet: pass the list through
            :func:`iter_pieces` to get bounded pieces.
        """
        st = self.stats
        n = int(t_ns.size)
        if n == 0:
            return []
        if self.sequence.observe(seq, int(t_ns[0])) is Verdict.DUPLICATE:
            st.duplicate_chunks += 1
            return []
        st.seq_gaps = max(self.sequence.lost, 0)
        if sample_rate_hz:
            period = 1e9 / float(sample_rate_hz)
        elif n >= 2:
            period = float(np.median(np.diff(t_ns)))
        else:
            period = self.period_ns
        out: list = []
        keep = slice(None)
        if self.last_t_ns is not None:
            if int(t_ns[0]) < self.last_t_ns - self.max_gap_ns:
                # Far back in time: a clock reset, or the stream back after a far-future timestamp.
                # Not a late chunk: a new segment (dropping it as overlap would drop the rest of the stream).
                st.segment_starts.append(st.samples)
            else:
                n_old = int(np.searchsorted(t_ns, self.last_t_ns, side="right"))
                if n_old:
                    st.overlap_samples += n_old
                    if n_old == n:
                        return []
                    keep = slice(n_old, None)
                t_next = int(t_ns[n_old])
                step = t_next - self.last_t_ns
                p_ref = period if period else self.period_ns
                n_fill = int(round(step / p_ref)) - 1 if p_ref and step > GAP_FACTOR * p_ref else 0
                if step > self.max_gap_ns or n_fill > MAX_FILL_SAMPLES:
                    st.segment_starts.append(st.samples)  # a pause, or a corrupt timestamp: not filled
                elif n_fill > 0:
                    fill = self._fill(p_ref, n_fill, t_next)
                    if fill.size:
                        st.gaps += 1
                        st.gap_samples += fill.size
                        st.samples += fill.size
                        out.append(fill)
        t = t_ns[keep]
        sel = (t >= self._lo) & (t < self._hi)
        if not sel.all():
            cols = np.flatnonzero(sel)
            t = t[cols]
        else:
            cols = None
        self.last_t_ns = int(t_ns[-1])
        if period:
            self.period_ns = period
        if t.size == 0:
            return out
        src, dst, same_rows = self._map(tuple(detector_ids))
        p = p_opt_w[:, keep]
        f = flags[:, keep]
        sp = None if sigma_p_w is None else sigma_p_w[:, keep]
        if cols is not None:
            p, f = p[:, cols], f[:, cols]
            sp = None if sp is None else sp[:, cols]
        s_out = None
        if same_rows:
            p_out, f_out = np.array(p, dtype=np.float64), np.array(f, dtype=fl.FLAG_DTYPE)
            if sp is not None:
                s_out = np.array(sp, dtype=np.float32)
        else:
            shape = (len(self.detectors), t.size)
            p_out = np.full(shape, np.nan)
            f_out = np.full(shape, fl.UNKNOWN_CHANNEL, dtype=fl.FLAG_DTYPE)
            p_out[dst] = p[src]
            f_out[dst] = f[src]
            if sp is not None:
                s_out = np.full(shape, np.nan, dtype=np.float32)
                s_out[dst] = sp[src]
            st.absent_samples += (len(self.detectors) - dst.size) * int(t.size)  # rows the chunk lacks
        st.chunks += 1
        st.samples += int(t.size)
        self._note(table_identity, converter_kind)
        out.append(Piece(np.array(t, dtype=np.int64), p_out, f_out, table_identity, s_out))
        return out

    def _note(self, table_identity: str, converter_kind: str) -> None:
        if table_identity and table_identity not in self.stats.table_identities:
            self.stats.table_identities.append(table_identity)
        if converter_kind and converter_kind not in self.stats.converter_kinds:
            self.stats.converter_kinds.append(converter_kind)


class BlockBuffer:
    """Collects pieces of one stream and cuts them into blocks of ``block_samples``.

    Parameters
    ----------
    stream : StreamId
    detectors, channels
        The rows (as the assembler's).
    block_samples : int
        Samples per block (the last block may be shorter). Gap fill is made
        only as blocks are cut, so the buffer never holds much more than one
        block (plus one chunk).
    """

    def __init__(self, stream: StreamId, detectors, channels, block_samples: int):
        if int(block_samples) < 1:
            raise ConfigError(f"block_samples must be >= 1, got {block_samples}")
        self.stream = stream
        self.detectors = tuple(detectors)
        self.channels = np.asarray(channels, dtype=np.int32)
        self.block_samples = int(block_samples)
        self._pieces: list[Piece] = []
        self._n = 0
        self.emitted = 0

    def add(self, pieces: list) -> Iterator[TodBlock]:
        """Blocks completed by ``pieces`` (what :meth:`StreamAssembler.push` returned)."""
        for piece in iter_pieces(pieces, self.block_samples):
            self._pieces.append(piece)
            self._n += int(piece.t_ns.size)
            while self._n >= self.block_samples:
                yield self._cut(self.block_samples)

    def flush(self) -> Iterator[TodBlock]:
        if self._n:
            yield self._cut(self._n)

    def _cut(self, n: int) -> TodBlock:
        take, rest, got = [], [], 0
        for piece in self._pieces:
            if got >= n:
                rest.append(piece)
                continue
            t, p, f, ident, sp = piece
            k = min(n - got, t.size)
            take.append(Piece(t[:k], p[:, :k], f[:, :k], ident, None if sp is None else sp[:, :k]))
            if k < t.size:
                rest.append(Piece(t[k:], p[:, k:], f[:, k:], ident, None if sp is None else sp[:, k:]))
            got += k
        self._pieces = rest
        self._n -= n
        if len(take) == 1:
            t, p, f, _, sig = take[0]
        else:
            t = np.concatenate([x.t_ns for x in take])
            p = np.concatenate([x.p_opt_w for x in take], axis=1)
            f = np.concatenate([x.flags for x in take], axis=1)
            sig = _sigma_concat([x.sigma_p_w for x in take], [x.p_opt_w.shape for x in take])
        s = self.stream
        block = TodBlock(s.setup, s.board, s.module, self.detectors, self.channels, t, p, f, self.emitted,
                         _distinct(x.table_identity for x in take), sig)
        self.emitted += n
        return block
