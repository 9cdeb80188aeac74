"""Sequence numbers of one chunk stream: lost, late, duplicated, restarted.

One tracker per stream (a ``(board, module)`` counts stream, a recorded
topic). Every consumer of sequenced chunks (the converter, the recorder, the
feeds, the monitor) books its numbers here, so "lost" means the same
everywhere:

- a number above the next expected one: the skipped numbers are *lost*
  (and remembered as ranges, up to ``max_missing`` numbers, in case they turn
  up late), if the jump is plausible: when the chunks' first sample times
  are given, a jump must agree with the time that passed (a corrupt or forged
  number that claims thousands of chunks went by in one chunk's time is a
  *reset*, not a loss);
- a skipped number that turns up with older samples: no longer lost, *late*;
- a number seen recently (the last ``max_recent``) with the same first sample
  time: a *duplicate* (the caller drops it);
- a source that started over: a jump of more than ``max_missing`` either way,
  a recent number with other sample times, or an old number with samples
  newer than any seen: a *reset*; the tracker starts over from it.

Memory per stream is bounded: ``max_recent`` numbers and at most
``_MAX_RANGES`` missing ranges, whatever the numbers a sender chooses.

>>> s = StreamSequence()
>>> [str(s.observe(n, t_first_ns=10 * n)) for n in (0, 1, 3, 2, 2)]
['new', 'new', 'new', 'late', 'duplicate']
>>> s.lost, s.out_of_order, s.duplicated
(0, 1, 1)
>>> s.observe(100_000, t_first_ns=40) is Verdict.RESET, s.resets  # 99,996 chunks cannot fit in 10 ns
(True, 1)
"""

from __future__ import annotations

import bisect
import collections
import enum

__all__ = ["StreamSequence", "Verdict"]

MAX_RECENT = 256  # numbers remembered to spot duplicates
MAX_MISSING = 4096  # a longer jump is a restart; skipped numbers remembered (as ranges) for late arrivals
_MAX_RANGES = 64  # missing ranges kept; the oldest are forgotten first (they stay counted as lost)
_SLACK = 2  # chunks a jump may exceed what the elapsed time allows (jitter, a partial chunk)


class Verdict(enum.StrEnum):
    """What a chunk's number is to its stream; a ``str`` (``"new"``, ...) where text is wanted."""

    NEW = "new"
    LATE = "late"  # a number counted lost turned up: no longer lost
    DUPLICATE = "duplicate"  # seen already with the same first sample time: drop it
    RESET = "reset"  # the stream started over at this number: take it


class StreamSequence:
    """Book-keeping of one stream's sequence numbers (see the module docstring).

    Attributes
    ----------
    lost : int
        Numbers skipped and not seen since.
    out_of_order, duplicated, resets : int
        Chunks that came late, came twice, or restarted the stream.
    """

    __slots__ = ("next", "_recent", "_recent_t", "_missing", "max_recent", "max_missing", "_last_t", "_period",
                 "lost", "out_of_order", "duplicated", "resets")

    def __init__(self, max_recent: int = MAX_RECENT, max_missing: int = MAX_MISSING):
        self.max_recent = int(max_recent)
        self.max_missing = int(max_missing)
        self.next: int | None = None
        self._recent: collections.deque[int] = collections.deque()
        self._recent_t: dict[int, int] = {}  # seq -> first sample time: a duplicate has both equal
        self._missing: list[list[int]] = []  # sorted disjoint [lo, hi) ranges of skipped numbers
        self._last_t: int | None = None  # newest first-sample time seen
        self._period: int | None = None  # smallest positive first-sample step per number seen
        self.lost = self.out_of_order = self.duplicated = self.resets = 0

    @property
    def newest_t_ns(self) -> int | None:
        """The newest first-sample time booked (None before the first chunk): where the stream's pace is."""
        return self._last_t

    def observe(self, seq: int, t_first_ns: int) -> Verdict:
        """Book one chunk's number.

        Parameters
        ----------
        seq : int
        t_first_ns : int
            Time of the chunk's first sample (tells a duplicate from a restart,
            and a plausible gap from a forged number).

        Returns
        -------
        Verdict
            ``NEW``, ``LATE``, ``DUPLICATE`` (drop it) or ``RESET``
            (the stream restarted at this number; take it).
        """
        seq, t = int(seq), int(t_first_ns)
        seen = self._recent_t.get(seq)
        if seen == t:
            self.duplicated += 1
            return Verdict.DUPLICATE
        verdict = Verdict.NEW
        if self.next is not None and (seen is not None or self._restarted(seq, t)):
            self.resets += 1
            self._forget()
            verdict = Verdict.RESET
        if self.next is None or seq >= self.next:
            if self.next is not None and seq > self.next:
                self.lost += seq - self.next
                self._add_missing(self.next, seq)
            if self.next is not None and self._last_t is not None and t > self._last_t:
                step = (t - self._last_t) // (seq - self.next + 1)
                self._period = step if self._period is None else min(self._period, step)
            self.next = seq + 1
        else:
            if self._take_missing(seq):
                self.lost -= 1
            self.out_of_order += 1
            verdict = Verdict.LATE
        self._last_t = t if self._last_t is None else max(self._last_t, t)
        self._recent.append(seq)
        self._recent_t[seq] = t
        if len(self._recent) > self.max_recent:
            self._recent_t.pop(self._recent.popleft(), None)
        return verdict

    def _restarted(self, seq: int, t: int) -> bool:
        if abs(seq - self.next) > self.max_missing:
            return True
        if self._last_t is None:
            return False
        if seq < self.next:  # a late chunk carries older samples than the newest seen
            return t > self._last_t
        if seq > self.next and self._period:  # the jump must fit in the time that passed
            return (seq - self.next) > (t - self._last_t) // self._period + _SLACK
        return False

    def _add_missing(self, lo: int, hi: int) -> None:
        self._missing.append([max(lo, hi - self.max_missing), hi])
        if len(self._missing) > _MAX_RANGES:
            del self._missing[0]

    def _take_missing(self, seq: int) -> bool:
        i = bisect.bisect_right(self._missing, [seq, float("inf")]) - 1
        if i < 0 or not self._missing[i][0] <= seq < self._missing[i][1]:
            return False
        lo, hi = self._missing[i]
        pieces = [r for r in ([lo, seq], [seq + 1, hi]) if r[0] < r[1]]
        self._missing[i:i + 1] = pieces
        return True

    def _forget(self) -> None:
        self.next = None
        self._recent.clear()
        self._recent_t.clear()
        self._missing.clear()
        self._period = None
        self._last_t = None  # the new run's times may be anywhere relative to the old one's
