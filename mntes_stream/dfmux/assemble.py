"""DfMux Timepoints -> counts chunks, one stream per (board serial, module), and what went missing.

:class:`Assembler` takes one sample of every board at a time (what spt3g's
``DfMuxBuilder`` puts in a Timepoint frame, already unpacked to numpy) and
returns counts chunks of ``chunk_samples`` samples per stream. Streams are
numbered as the G3 path numbers them (:mod:`mntes_stream.g3.mapping`):
board serial, 0-indexed module, channel; a V4 module's channel is
``block * 128 + channel in the block`` (spt3g's ``DfMuxCollator``), so a
detector id is the same whether its counts came through the DAQ or here.

What it notices (each an :class:`Event`, said once): samples missing from a
stream's clock (lost packets, a board restart), a stream that starts late,
a stream or a whole board gone silent, and back. None of them stops it.
A V4 block missing from a sample leaves its channels at the int32 rail
(``2**31 - 1``, which every converter flags INVALID_INPUT), counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mntes_stream.core.ids import detector_id
from mntes_stream.dfmux.packets import SAMPLE_NS

__all__ = ["Assembler", "Event", "RAIL", "utc"]

RAIL = int(np.iinfo(np.int32).max)


def utc(t_ns: int) -> str:
    """``t_ns`` as UTC to the millisecond (event text)."""
    return str(np.datetime64(int(t_ns), "ns").astype("datetime64[ms]")) + "Z"


@dataclass(frozen=True)
class Event:
    """Something about the boards worth one line: ``kind`` (gap, late, silent, back, channels), where, what."""

    kind: str
    board: int
    module: int | None
    t_ns: int
    text: str


class _Stream:
    __slots__ = ("board", "module", "nblocks", "width", "buf", "t", "n", "seq", "last_t", "gap_samples",
                 "silent", "samples")

    def __init__(self, board: int, module: int, nblocks: int, width: int, chunk: int):
        self.board, self.module, self.nblocks, self.width = board, module, nblocks, width
        self.buf = np.empty((chunk, nblocks * width), dtype=np.int32)
        self.t = np.empty(chunk, dtype=np.int64)
        self.n = 0
        self.seq = 0
        self.last_t: int | None = None
        self.gap_samples = 0
        self.samples = 0
        self.silent = False


class Assembler:
    """Samples in, counts chunks out (see the module's docstring).

    Parameters
    ----------
    setup : str
    chunk_samples : int
        Samples per counts chunk per stream.
    late_s : float
        A stream first seen this long after the first sample is reported as late.
    """

    def __init__(self, setup: str, chunk_samples: int = 16, late_s: float = 1.0):
        self.setup = setup
        self.chunk = int(chunk_samples)
        self.late_ns = int(late_s * 1e9)
        self.streams: dict[tuple[int, int], _Stream] = {}
        self.events: list[Event] = []
        self.t_first_ns: int | None = None
        self.t_newest_ns = 0
        self.timepoints = 0
        self.samples = 0            # detector samples put into chunks
        self.invalid_samples = 0    # of which at the rail (a V4 block missing)
        self.out_of_order = 0       # samples at or before their stream's last one (dropped)
        self.published: dict[str, int] = {}
        self._t_pub = 0
        # (board, module) -> {channel: detector id}: the boards' names (fixed by the bridge before any sample)
        self.names: dict[tuple[int, int], dict[int, str]] = {}
        self._row_ids: dict[tuple[int, int, int], tuple | None] = {}

    def add(self, t_ns: int, modules, t_pub_ns: int = 0) -> list:
        """One sample: ``modules`` is ``[(board, module, block, nblocks, I/Q int32 array), ...]``; returns the
        :class:`~mntes_stream.io.messages.CountsChunk` s completed by it (stamped ``t_pub_ns``)."""
        self._t_pub = t_pub_ns
        self.timepoints += 1
        if self.t_first_ns is None:
            self.t_first_ns = t_ns
        self.t_newest_ns = max(self.t_newest_ns, t_ns)
        touched = {}
        gaps: dict[int, list] = {}
        out = []
        for board, module, block, nblocks, iq in modules:
            key = (board, module)
            s = touched.get(key)
            if s is None:
                s = self.streams.get(key)
                if s is None or s.nblocks != nblocks or s.width != iq.size:
                    if s is not None:
                        out += self._flush(s)
                        self._event("channels", board, module, t_ns, f"module {board}/{module}: now "
                                    f"{nblocks * iq.size // 2} channels (was {s.nblocks * s.width // 2})")
                    s = self._new(board, module, nblocks, iq.size, t_ns, s)
                if s.last_t is not None and t_ns <= s.last_t:
                    self.out_of_order += 1
                    continue
                if s.last_t is not None and t_ns - s.last_t > SAMPLE_NS * 3 // 2:
                    missed = round((t_ns - s.last_t) / SAMPLE_NS) - 1
                    s.gap_samples += missed
                    gaps.setdefault(board, []).append((module, missed))
                if s.silent:
                    s.silent = False
                    self._event("back", board, module, t_ns, f"module {board}/{module} back")
                if nblocks > 1:
                    s.buf[s.n] = RAIL  # blocks that do not come stay at the rail
                s.t[s.n] = t_ns
                s.last_t = t_ns
                touched[key] = s
            s.buf[s.n, block * s.width:(block + 1) * s.width] = iq
        for s in touched.values():
            s.n += 1
            if s.n == self.chunk:
                out += self._flush(s)
        for board, items in gaps.items():
            mods = sorted(items)
            where = ", ".join(str(m) for m, _ in mods[:8]) + (" ..." if len(mods) > 8 else "")
            self._event("gap", board, None, t_ns, f"board {board}: up to {max(k for _, k in mods)} samples missing "
                        f"before {utc(t_ns)} on module(s) {where} (lost packets or a board restart)")
        return out

    def _new(self, board, module, nblocks, size, t_ns, old):
        s = _Stream(board, module, nblocks, size, self.chunk)
        if old is not None:
            s.seq, s.last_t, s.gap_samples, s.samples = old.seq, old.last_t, old.gap_samples, old.samples
        elif t_ns - self.t_first_ns > self.late_ns:
            self._event("late", board, module, t_ns, f"module {board}/{module} started late, at "
                        f"{(t_ns - self.t_first_ns) / 1e9:.1f} s")
        self.streams[(board, module)] = s
        return s

    def _event(self, kind, board, module, t_ns, text) -> None:
        self.events.append(Event(kind, board, module, t_ns, text))

    def _flush(self, s: _Stream) -> list:
        if not s.n:
            return []
        from mntes_stream.io.messages import CountsChunk

        n = s.n
        block = s.buf[:n]
        bad = block == RAIL
        if s.nblocks > 1 and bad.any():
            self.invalid_samples += int(bad[:, 0::2].sum())
        nch = block.shape[1] // 2
        msg = CountsChunk(setup=self.setup, board=s.board, module=s.module,
                          channels=np.arange(nch, dtype=np.int32), seq=s.seq, t0_ns=None, sample_rate_hz=None,
                          counts_i=np.ascontiguousarray(block[:, 0::2].T), counts_q=np.ascontiguousarray(block[:, 1::2].T),
                          t_pub_ns=self._t_pub, t_ns=s.t[:n].copy(), detector_ids=self._ids(s.board, s.module, nch))
        s.seq += 1
        s.samples += n * nch
        self.samples += n * nch
        s.n = 0
        name = f"{s.board}/{s.module}"
        self.published[name] = self.published.get(name, 0) + 1
        return [msg]

    def _ids(self, board: int, module: int, nch: int) -> tuple | None:
        """The rows' detector ids where the board names its channels (unnamed ones: b/m/c); None: none named."""
        key = (board, module, nch)
        if key not in self._row_ids:
            named = self.names.get((board, module))
            self._row_ids[key] = None if not named else \
                tuple(named.get(c, detector_id(board, module, c)) for c in range(nch))
        return self._row_ids[key]

    def flush(self, t_pub_ns: int = 0) -> list:
        """Every stream's partial chunk (at the end)."""
        self._t_pub = t_pub_ns
        out = []
        for s in self.streams.values():
            out += self._flush(s)
        return out

    def check_silent(self, silent_s: float) -> None:
        """Streams (and whole boards) with no sample for ``silent_s`` of the newest data time: one event each."""
        limit = self.t_newest_ns - int(silent_s * 1e9)
        newly: dict[int, list] = {}
        for s in self.streams.values():
            if not s.silent and s.last_t is not None and s.last_t < limit:
                s.silent = True
                newly.setdefault(s.board, []).append(s.module)
        for board, mods in newly.items():
            whole = all(s.silent for (b, _), s in self.streams.items() if b == board)
            if whole:
                self._event("silent", board, None, self.t_newest_ns, f"board {board} stopped sending "
                            f"(nothing for {silent_s:g} s of data time)")
            else:
                self._event("silent", board, mods[0], self.t_newest_ns, f"board {board} module(s) "
                            f"{', '.join(map(str, sorted(mods)))} silent for {silent_s:g} s")

    @property
    def stream_gaps(self) -> dict[str, int]:
        """``"board/module"`` -> samples missing from its clock."""
        return {f"{b}/{m}": s.gap_samples for (b, m), s in self.streams.items() if s.gap_samples}

    @property
    def gap_samples(self) -> int:
        return sum(s.gap_samples for s in self.streams.values())
