"""The converter pipeline's held chunks: set aside under overload, converted late or shed; the ledger's missing
column; the checkpoint's sequence state (a held chunk is not converted yet).

A mixin of :class:`~mntes_stream.service.pipeline.ConverterPipeline` (its
state: ``_aside``, ``_aside_bytes``, ``_aside_max``, ``_ready``, ``_streams``,
``_pending``, ``ledger``, ``counters``; its ``_environment``, ``_convert_ready``,
``_dropped``, ``_bad``, ``_guarded``), kept apart so each module stays one concern.

Shedding is the last resort: the live service sets ``overloaded`` only when it
has been behind without a break for ``overload_after_s`` (a real overload, not
a stall or a latency spike); then a chunk further behind its stream's pace
than ``max_lag_s`` is set aside, converted when the service has time (late
power, in order per stream) and shed only when the set-aside budget is full.
"""

from __future__ import annotations

import logging

from mntes_stream.core.ledger import Ledger

__all__ = ["Overload"]

log = logging.getLogger("mntes_stream.converter")


def _nbytes(p) -> int:
    """What a held chunk's counts take (I and Q)."""
    return p.chunk.counts_i.nbytes + p.chunk.counts_q.nbytes


class Overload:
    """Set-aside chunks and late conversion (see the module docstring)."""

    @property
    def set_aside(self) -> int:
        """Chunks set aside under overload, waiting for :meth:`convert_late`."""
        return len(self._aside)

    def convert_late(self, max_chunks: int) -> list[tuple[str, bytes]]:
        """Convert up to ``max_chunks`` set-aside chunks, oldest first (each stream's in order): late power."""
        out: list[tuple[str, bytes]] = []
        for _ in range(min(int(max_chunks), len(self._aside))):
            p = self._aside.popleft()
            self._aside_bytes -= _nbytes(p)
            try:
                self._ready.append(self._environment(p))
            except Exception as exc:
                self._dropped(p.chunk, exc)
        self._guarded(self._convert_ready, "late", out)
        return out

    def _set_aside(self, p, lag_ns: int, key: str) -> None:
        """Under overload: keep the chunk for later (the oldest set-aside chunks shed beyond the budget)."""
        p.late = True
        self._aside.append(p)
        self._aside_bytes += _nbytes(p)
        if len(self._aside) == 1 or len(self._aside) % 1000 == 0:
            log.warning("overload: %s seq %d %.3g s behind its stream set aside for late conversion (%d held)",
                        key, p.chunk.seq, lag_ns / 1e9, len(self._aside))
        while self._aside_bytes > self._aside_max and self._aside:
            old = self._aside.popleft()
            self._aside_bytes -= _nbytes(old)
            self.counters.chunks_shed += 1
            self.ledger.shed((old.chunk.board, old.chunk.module), "overload")
            self._bad("overload", f"chunk seq {old.chunk.seq} of {old.chunk.board}/{old.chunk.module} shed: the "
                      "set-aside budget is full (its counts are recorded: offline convert gives its power)", key)

    def ledger_now(self) -> Ledger:
        """The ledger with each stream's never-received count as its sequence tracker says now."""
        for (b, m), s in self._streams.items():
            self.ledger.set_missing((b, m), s.lost)
        return self.ledger

    def sequence_state(self) -> dict[tuple[int, int], tuple[int, int]]:
        """A checkpoint: ``(board, module) -> (newest sequence number converted, newest first-sample time ns)``.

        Chunks still held (waiting for housekeeping, set aside) are not converted yet: the number stops below
        the oldest of them, so a restart from here converts them again instead of taking them as done.
        """
        held: dict[tuple[int, int], int] = {}
        for p in (*self._pending, *self._aside):
            k = (p.chunk.board, p.chunk.module)
            held[k] = min(held.get(k, p.chunk.seq), p.chunk.seq)
        return {k: (min(s.next - 1, held.get(k, s.next) - 1), s.newest_t_ns) for k, s in self._streams.items()
                if s.next is not None and s.newest_t_ns is not None}
