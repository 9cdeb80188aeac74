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

A gap in a stream's time stamps is lost data only if packets are missing:
with ``hold_gaps`` the gaps wait in :attr:`Assembler.pending_gaps` until
:meth:`Assembler.resolve_gaps` is given the collector's sequence-number
events (:mod:`.spt3glog`): a gap the sequence numbers account for (skipped,
or a board restart) is missing samples; the rest of it is the board's time
stamps jumping forward (its IRIG time), a ``jump`` event, never counted lost.
A V4 block missing from a sample leaves its channels at the int32 rail
(``2**31 - 1``, which every converter flags INVALID_INPUT), counted.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mntes_stream.core.ids import detector_id
from mntes_stream.dfmux.packets import SAMPLE_NS

__all__ = ["Assembler", "Event", "Gap", "RAIL", "utc"]

RAIL = int(np.iinfo(np.int32).max)


def utc(t_ns: int) -> str:
    """``t_ns`` as UTC to the millisecond (event text)."""
    return str(np.datetime64(int(t_ns), "ns").astype("datetime64[ms]")) + "Z"


@dataclass(frozen=True)
class Gap:
    """A stream's time stamps skipping ``missed`` samples before ``t_ns``, ``dt_ns`` after the last (not yet
    resolved)."""

    board: int
    module: int
    nblocks: int
    t_ns: int
    missed: int
    dt_ns: int
    t_seen_ns: int = 0


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
                 "jump_samples", "silent", "samples")

    def __init__(self, board: int, module: int, nblocks: int, width: int, chunk: int):
        self.board, self.module, self.nblocks, self.width = board, module, nblocks, width
        self.buf = np.empty((chunk, nblocks * width), dtype=np.int32)
        self.t = np.empty(chunk, dtype=np.int64)
        self.n = 0
        self.seq = 0
        self.last_t: int | None = None
        self.gap_samples = 0
        self.jump_samples = 0
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
    hold_gaps : bool
        Gaps wait for :meth:`resolve_gaps` (sequence numbers at hand); False: every gap is missing samples.
    """

    MATCH_NS = 250_000_000     # a sequence event read this long after its gap was seen still matches it
    STALE_NS = 10_000_000_000  # an unmatched sequence event this much older than a gap is given up

    def __init__(self, setup: str, chunk_samples: int = 16, late_s: float = 1.0, hold_gaps: bool = False):
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
        self.rejected: dict[str, int] = {}  # "board B: module out of range" -> module packets refused
        self.hold_gaps = bool(hold_gaps)
        self.pending_gaps: list[Gap] = []
        self.time_jumps: list[dict] = []    # {"board", "t_ns", "forward_s"}: one per board per jump
        self._seq: dict[tuple[int, int], list] = {}  # (board, collector's mod_id) -> its unmatched SeqEvents
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
                    if self.hold_gaps:
                        self.pending_gaps.append(Gap(board, module, nblocks, t_ns, missed, t_ns - s.last_t,
                                                     t_pub_ns))
                    else:
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
            self._gap_event(board, t_ns, items)
        return out

    def _gap_event(self, board: int, t_ns: int, items) -> None:
        mods = sorted(items)
        where = ", ".join(str(m) for m, _ in mods[:8]) + (" ..." if len(mods) > 8 else "")
        self._event("gap", board, None, t_ns, f"board {board}: up to {max(k for _, k in mods)} samples missing "
                    f"before {utc(t_ns)} on module(s) {where} (lost packets or a board restart)")

    def reject(self, board: int, reason: str, n: int = 1) -> None:
        """Count ``n`` module packets of ``board`` refused for ``reason`` (never put into a stream)."""
        key = f"{reason} (board {board})"
        if key not in self.rejected:
            self._event("rejected", board, None, self.t_newest_ns, f"board {board}: packets refused: {reason}")
        self.rejected[key] = self.rejected.get(key, 0) + int(n)

    def step_back(self, board: int, back_s: float) -> None:
        """The board's time stamps went back ``back_s`` (spt3g's builder drops its packets until they pass the
        last sample it sent out): a ``jump`` event and an entry of :attr:`time_jumps`."""
        self.time_jumps.append({"board": board, "t_ns": self.t_newest_ns, "forward_s": -round(back_s, 3)})
        self._event("jump", board, None, self.t_newest_ns, f"board {board}: time stamps stepped back {back_s:.3f} s: "
                    "spt3g's builder drops its packets until their time passes its last sample (counted)")

    def resolve_gaps(self, seq_events, upto: int | None = None) -> None:
        """Tell the held gaps (the first ``upto``; None: all) lost samples from time jumps.

        ``seq_events``: the collector's sequence events since the last call (:class:`.spt3glog.SeqEvent`). The
        collector writes one as it takes the packet after the skip, before the builder can send out its sample:
        a gap takes its module's first unmatched event read no later than ``MATCH_NS`` after the gap was seen
        (``t_pub_ns`` of :meth:`add`), events older than ``STALE_NS`` being dropped. A gap is missing samples as
        far as the event's sequence numbers skipped (the most of a V4 module's blocks), all of it after a
        restart (the sequence started again); what is left is a jump forward of the board's time stamps: a
        ``jump`` event per board and time, in :attr:`time_jumps`, not missing.
        """
        for ev in seq_events:
            self._seq.setdefault((ev.board, ev.mod_id), []).append(ev)
        n = len(self.pending_gaps) if upto is None else min(upto, len(self.pending_gaps))
        todo, self.pending_gaps = self.pending_gaps[:n], self.pending_gaps[n:]
        lost: dict[tuple[int, int], list] = {}
        jumped: dict[tuple[int, int], list] = {}
        for g in todo:
            s = self.streams[(g.board, g.module)]
            ids = [(g.board, g.module)] if g.nblocks == 1 else \
                [(g.board, g.module * g.nblocks + b) for b in range(g.nblocks)]
            matched = []
            for k in ids:
                evs = self._seq.get(k)
                while evs and evs[0].t_read_ns < g.t_seen_ns - self.STALE_NS:
                    evs.pop(0)  # a skip no gap came for (a packet lost at the stop, a restart without a gap)
                if evs and evs[0].t_read_ns <= g.t_seen_ns + self.MATCH_NS:
                    matched.append(evs.pop(0))
            if any(ev.got <= ev.expected for ev in matched):
                missing = g.missed  # the board restarted: its sequence started again
            else:
                missing = min(g.missed, max((ev.got - ev.expected for ev in matched), default=0))
            s.gap_samples += missing
            s.jump_samples += g.missed - missing
            if missing:
                lost.setdefault((g.board, g.t_ns), []).append((g.module, missing))
            if g.missed > missing:
                jumped.setdefault((g.board, g.t_ns), []).append((g.module, g.dt_ns - (missing + 1) * SAMPLE_NS))
        said = sorted([(t_ns, 0, board, items) for (board, t_ns), items in lost.items()] +
                      [(t_ns, 1, board, items) for (board, t_ns), items in jumped.items()])
        for t_ns, jump, board, items in said:
            if not jump:
                self._gap_event(board, t_ns, items)
                continue
            forward_s = max(k for _, k in items) / 1e9
            self.time_jumps.append({"board": board, "t_ns": t_ns, "forward_s": round(forward_s, 3)})
            self._event("jump", board, None, t_ns, f"board {board}: time stamps jumped forward {forward_s:.3f} s "
                        f"at {utc(t_ns)} with no packet missing (its IRIG time; nothing lost)")

    def _new(self, board, module, nblocks, size, t_ns, old):
        s = _Stream(board, module, nblocks, size, self.chunk)
        if old is not None:
            s.seq, s.last_t, s.gap_samples, s.samples = old.seq, old.last_t, old.gap_samples, old.samples
            s.jump_samples = old.jump_samples
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

    @property
    def jump_samples(self) -> int:
        """Samples the boards' time stamps jumped over (no packet missing): not lost."""
        return sum(s.jump_samples for s in self.streams.values())
