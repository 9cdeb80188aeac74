"""Live power over zenoh as numpy blocks, for a selection of detectors.

:class:`LivePowerFeed` subscribes to ``mntes/<setup>/power/<board>/<module>``
(only the modules of the selected detectors, when a selection is given) and
yields one :class:`~mntes_stream.feeds.blocks.TodBlock` per received chunk,
assembled per stream exactly like a recording
(:class:`~mntes_stream.feeds.blocks.StreamAssembler`): a hole in time comes
as its own block(s) of NaN + GAP (at most ``gap_block_samples`` each) before
the chunk after it; a step beyond ``max_gap_s`` is a segment break, reported
in ``stats``, not filled; a chunk that arrives
after its span was already given out (late, or a duplicate) is dropped and
counted; an absent detector is NaN + UNKNOWN_CHANNEL. Without a selection the
rows are every detector seen so far on that stream (a block's ``detectors``
says which).

The feed is bounded: it stops after ``max_blocks`` blocks, ``duration_s``
seconds, or ``idle_timeout_s`` without a power chunk, whichever comes first,
and always closes its zenoh session (use it as a context manager, or let the
iteration finish).
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator

from mntes_stream.core.ids import parse_detector_id
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.feeds.blocks import (
    DEFAULT_BLOCK_SAMPLES,
    DEFAULT_MAX_GAP_S,
    StreamAssembler,
    StreamId,
    StreamStats,
    TodBlock,
    iter_pieces,
)
from mntes_stream.io import keys

__all__ = ["LivePowerFeed"]


class LivePowerFeed:
    """Iterate live power blocks.

    Parameters
    ----------
    zenoh : mntes_stream.io.transport.ZenohSettings
        How to join the network (e.g. ``transport.loopback(connect_ports=[port])``).
    setup : str
    detectors : iterable of str, optional
        Only these detectors (rows in this order, per module); default all.
    board, module : int, optional
        Streams to subscribe to when no detectors are given; None (default): any,
        as :class:`~mntes_stream.feeds.recorded.RecordedPower` takes them.
    max_blocks : int, optional
        Stop after this many blocks (gap blocks included).
    duration_s : float, optional
        Stop after this long.
    idle_timeout_s : float
        Stop after this long without a power chunk.
    queue_size : int
        Received chunks buffered; when full, BLOCK publishers wait (no loss).
    max_gap_s : float
        A step in time longer than this is a segment break, not a hole to fill.
    gap_block_samples : int
        A hole is given out in blocks of at most this many samples.

    Attributes
    ----------
    stats : dict of str to StreamStats
        Per observation name (``<setup>_b<board>m<module>``).
    invalid_messages : int
        Payloads that did not decode as power chunks (skipped).
    """

    def __init__(self, zenoh, setup: str, *, detectors: Iterable[str] | None = None, board: int | None = None,
                 module: int | None = None, max_blocks: int | None = None, duration_s: float | None = None,
                 idle_timeout_s: float = 10.0, queue_size: int = 1024, max_gap_s: float = DEFAULT_MAX_GAP_S,
                 gap_block_samples: int = DEFAULT_BLOCK_SAMPLES):
        self.settings = zenoh
        self.setup = setup
        self._dets = None if detectors is None else tuple(dict.fromkeys(str(d) for d in detectors))
        if self._dets is not None:
            if not self._dets:
                raise ConfigError("an empty detector selection selects nothing")
            mods = sorted({parse_detector_id(d)[:2] for d in self._dets})
            self.key_exprs = [keys.power_key(setup, b, m) for b, m in mods]
        else:
            for name, v in (("board", board), ("module", module)):
                if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
                    raise ConfigError(f"{name} {v!r}: expected a number >= 0, or None for any")
            self.key_exprs = [keys.power_key(setup, "*" if board is None else board, "*" if module is None else module)]
        for name, v in (("max_blocks", max_blocks), ("duration_s", duration_s), ("idle_timeout_s", idle_timeout_s),
                        ("max_gap_s", max_gap_s), ("gap_block_samples", gap_block_samples)):
            if v is not None and not v > 0:
                raise ConfigError(f"{name} must be > 0, got {v!r}")
        self.max_blocks = max_blocks
        self.duration_s = duration_s
        self.idle_timeout_s = float(idle_timeout_s)
        self.queue_size = int(queue_size)
        self.max_gap_s = float(max_gap_s)
        self.gap_block_samples = int(gap_block_samples)
        self._session = None
        self._sub = None
        self._asm: dict[StreamId, StreamAssembler] = {}
        self._emitted: dict[StreamId, int] = {}
        self.stats: dict[str, StreamStats] = {}
        self.invalid_messages = 0
        self.blocks = 0

    # ------------------------------------------------------------------ session

    def open(self) -> LivePowerFeed:
        """Open the zenoh session and subscribe (idempotent)."""
        from mntes_stream.io.transport import QueueSubscriber, open_session

        if self._session is None:
            self._session = open_session(self.settings)
            try:
                self._sub = QueueSubscriber(self._session, self.key_exprs, maxsize=self.queue_size)
            except BaseException:
                self.close()
                raise
        return self

    def close(self) -> None:
        """Undeclare the subscriber and close the session (idempotent)."""
        sub, session = self._sub, self._session
        self._sub = self._session = None
        try:
            if sub is not None:
                sub.close()
        finally:
            if session is not None:
                session.close()

    def __enter__(self) -> LivePowerFeed:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.close()

    # ------------------------------------------------------------------ blocks

    def _assembler(self, sid: StreamId, chunk) -> StreamAssembler | None:
        asm = self._asm.get(sid)
        if asm is None:
            if self._dets is None:
                asm = StreamAssembler((), (), max_gap_s=self.max_gap_s)
            else:
                mine = [d for d in self._dets if parse_detector_id(d)[:2] == (sid.board, sid.module)]
                if not mine:
                    return None
                asm = StreamAssembler(mine, [parse_detector_id(d)[2] for d in mine], max_gap_s=self.max_gap_s)
            self._asm[sid] = asm
            self._emitted[sid] = 0
            self.stats[sid.name] = asm.stats
        if self._dets is None:
            asm.add_rows(chunk.detector_ids, chunk.channels)
        return asm

    def _blocks_of(self, chunk) -> Iterator[TodBlock]:
        # A generator: a long hole is made one bounded block at a time, as the caller takes them.
        sid = StreamId(chunk.setup, chunk.board, chunk.module)
        asm = self._assembler(sid, chunk)
        if asm is None:
            return
        pieces = asm.push(chunk.seq, chunk.times_ns(), chunk.sample_rate_hz, chunk.detector_ids, chunk.p_opt_w,
                          chunk.flags, chunk.table_identity, chunk.converter_kind, getattr(chunk, "sigma_p_w", None))
        rows, channels = asm.detectors, asm.channels
        for t, p, f, ident, sig in iter_pieces(pieces, self.gap_block_samples):
            yield TodBlock(sid.setup, sid.board, sid.module, rows, channels, t, p, f, self._emitted[sid],
                           (ident,) if ident else (), sig)
            self._emitted[sid] += int(t.size)

    def collect(self) -> dict[str, TodBlock]:
        """Run the feed to its end (``duration_s``, ``max_blocks`` or idle) and return each stream as one block."""
        from mntes_stream.feeds.blocks import concat_blocks

        parts: dict[str, list[TodBlock]] = {}
        for block in self:
            parts.setdefault(block.name, []).append(block)
        out = {}
        for name, blocks in parts.items():
            # Rows grow while detectors appear (no selection): keep the spans of the final rows.
            last = blocks[-1]
            out[name] = concat_blocks([b if b.detectors == last.detectors else _widen(b, last) for b in blocks])
        return out

    def to_framework(self, framework: str, **kwargs) -> list:
        """Run the feed to its end and return a framework's objects, one per stream and segment.

        ``framework`` is ``toast``, ``sotodlib`` or ``litebird_sim``
        (:mod:`mntes_stream.feeds.frameworks`); ``kwargs`` go to the converter.
        """
        from mntes_stream.feeds.frameworks import from_blocks

        return from_blocks(self.collect(), framework, **kwargs)

    def __iter__(self) -> Iterator[TodBlock]:
        from mntes_stream.io.messages import PowerChunk

        self.open()
        t_start = last = time.monotonic()
        try:
            while True:
                now = time.monotonic()
                if self.duration_s is not None and now - t_start >= self.duration_s:
                    return
                if now - last >= self.idle_timeout_s:
                    return
                item = self._sub.get(timeout_s=0.05)
                if item is None:
                    continue
                last = time.monotonic()
                _, payload, _ = item
                try:
                    chunk = PowerChunk.from_bytes(payload)
                except SchemaError:
                    self.invalid_messages += 1
                    continue
                for block in self._blocks_of(chunk):
                    yield block
                    self.blocks += 1
                    if self.max_blocks is not None and self.blocks >= self.max_blocks:
                        return
        finally:
            self.close()


def _widen(block: TodBlock, last: TodBlock) -> TodBlock:
    """``block`` on the rows of ``last`` (a superset): rows it lacks are NaN + UNKNOWN_CHANNEL, as absent detectors."""
    import numpy as np

    from mntes_stream.core import flags as fl

    rows = last.detectors
    have = {d: r for r, d in enumerate(block.detectors)}
    p = np.full((len(rows), block.n_samples), np.nan)
    f = np.full((len(rows), block.n_samples), fl.UNKNOWN_CHANNEL, dtype=fl.FLAG_DTYPE)
    s = None if block.sigma_p_w is None else np.full((len(rows), block.n_samples), np.nan, dtype=np.float32)
    for i, d in enumerate(rows):
        if d in have:
            p[i], f[i] = block.p_opt_w[have[d]], block.flags[have[d]]
            if s is not None:
                s[i] = block.sigma_p_w[have[d]]
    return TodBlock(block.setup, block.board, block.module, rows, last.channels, block.t_ns, p, f,
                    block.first_sample, block.table_identities, s)
