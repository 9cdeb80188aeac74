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

__all__ = ["PublisherSequences", "SeqRanges", "StreamSequence", "Verdict", "format_ranges"]

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

    def sent(self, seq: int, t_first_ns: int) -> bool:
        """Whether this chunk (number and first sample time) was booked recently."""
        return self._recent_t.get(int(seq)) == int(t_first_ns)

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


MAX_PUBLISHERS = 8  # publishers of one stream tracked apart at most (the least recent forgotten)
_RETURNS = 2  # a publisher that comes back this many times after another took over: they publish side by side


class PublisherSequences:
    """One stream's numbers when its chunks may come from more than one publisher (zenoh's source id of each).

    One publisher after another (a source restarted: a new zenoh session) is
    one stream that started over, as :class:`StreamSequence` books it. Two
    publishers side by side on one key (two bridges of one setup) number their
    chunks each their own way: booked as one, every switch between them would
    look like a jump (chunks lost) or a restart. So each publisher's numbers are
    tracked apart as well, from the first time a second one appears, and once
    a publisher comes back after another took over (``_RETURNS`` times) the
    stream is in *conflict*: from then on a chunk's verdict is its own
    publisher's, a chunk another publisher already sent (same number, same first
    sample time) is a duplicate, and ``lost`` is the sum of each publisher's.
    ``source`` None (no publisher identity: a recording, a plain publisher) is
    one publisher. Besides :meth:`observe` it reads as a :class:`StreamSequence`
    (``next``, ``newest_t_ns``, ``lost``, ``duplicated``, ``out_of_order``,
    ``resets``: the stream's, or in conflict the sums).

    >>> s = PublisherSequences()
    >>> [str(s.observe(n, 10 * n, "a")) for n in (0, 1, 2)]
    ['new', 'new', 'new']
    >>> [str(s.observe(n, 10 * n + 5, p)) for n, p in ((50, "b"), (3, "a"), (51, "b"), (4, "a"), (52, "b"))]
    ['new', 'late', 'new', 'new', 'new']
    >>> s.conflict, s.publishers, s.lost  # as one stream: 47 lost at the first switch
    (True, 2, 0)
    >>> str(s.observe(52, 525, "a")), s.duplicated  # b's chunk 52, sent by a too
    ('duplicate', 1)
    """

    __slots__ = ("_one", "_apart", "_current", "_returns", "conflict", "dup_across", "dup_known")

    def __init__(self):
        self._one = StreamSequence()  # the stream as one publisher's
        self._apart: dict = {}  # source -> its own StreamSequence, once a second source appeared
        self._current = None  # the source of the newest chunk
        self._returns = 0
        self.conflict = False
        self.dup_across = 0  # chunks another publisher had sent already
        self.dup_known = 0  # chunks dropped before observe: a restarted converter's checkpoint had them

    def observe(self, seq: int, t_first_ns: int, source=None) -> Verdict:
        """Book one chunk of ``source``; the verdict (``DUPLICATE``: drop it)."""
        apart = self._apart
        if source != self._current and self._current is not None:
            if not apart:
                apart[self._current] = _copy(self._one)  # its numbers so far, tracked apart from now on
            elif source in apart and not self.conflict:
                self._returns += 1
                self.conflict = self._returns >= _RETURNS
        if apart or (source != self._current and self._current is not None):
            own = apart.get(source)
            if own is None:
                if len(apart) >= MAX_PUBLISHERS:
                    del apart[next(iter(apart))]
                own = apart[source] = StreamSequence()
            else:
                apart[source] = apart.pop(source)  # the most recent last
            seq, t = int(seq), int(t_first_ns)
            if self.conflict and any(o.sent(seq, t) for k, o in apart.items() if k != source):
                self.dup_across += 1
                own.observe(seq, t)
                self._current = source
                return Verdict.DUPLICATE
            verdict = own.observe(seq, t)
            one = self._one.observe(seq, t)
            self._current = source
            if one is Verdict.DUPLICATE and verdict is not Verdict.DUPLICATE:
                self.dup_across += 1  # another publisher's copy: counted so once the stream is in conflict
            return verdict if self.conflict else one
        self._current = source
        return self._one.observe(seq, t_first_ns)

    def _each(self):
        return self._apart.values() if self.conflict else (self._one,)

    @property
    def publishers(self) -> int:
        """Publishers seen (1 until a second appears; at most ``MAX_PUBLISHERS`` remembered)."""
        return max(len(self._apart), 1)

    @property
    def next(self) -> int | None:
        return self._apart[self._current].next if self.conflict and self._current in self._apart else self._one.next

    @property
    def newest_t_ns(self) -> int | None:
        if self.conflict and self._current in self._apart:
            return self._apart[self._current].newest_t_ns
        return self._one.newest_t_ns

    @property
    def lost(self) -> int:
        return sum(s.lost for s in self._each())

    @property
    def duplicated(self) -> int:
        return sum(s.duplicated for s in self._each()) + self.dup_across + self.dup_known

    @property
    def out_of_order(self) -> int:
        return sum(s.out_of_order for s in self._each())

    @property
    def resets(self) -> int:
        return sum(s.resets for s in self._each())


def _copy(s: StreamSequence) -> StreamSequence:
    out = StreamSequence(s.max_recent, s.max_missing)
    out.next, out._last_t, out._period = s.next, s._last_t, s._period
    out._recent = collections.deque(s._recent)
    out._recent_t = dict(s._recent_t)
    out._missing = [list(r) for r in s._missing]
    out.lost, out.out_of_order, out.duplicated, out.resets = s.lost, s.out_of_order, s.duplicated, s.resets
    return out


MAX_SEQ_RANGES = 1024  # ranges a SeqRanges keeps; numbers that would open more are counted, not placed


class SeqRanges:
    """A set of sequence numbers, as sorted disjoint ``[lo, hi)`` ranges (bounded).

    What a recording holds of a stream (its counts chunks, its power chunks) is
    a few long runs of numbers: a number next to a range extends it in O(1) at
    the end (the usual case) and O(log n) elsewhere. At most ``max_ranges``
    ranges are kept; a number that would open one more is counted in
    ``untracked`` (so a fragmented or forged stream cannot grow memory) and the
    readers say so.

    >>> r = SeqRanges()
    >>> [r.add(n) for n in (0, 1, 2, 5, 6, 2)]
    [True, True, True, True, True, False]
    >>> r.ranges(), r.count
    ([(0, 3), (5, 7)], 5)
    >>> other = SeqRanges.from_list([[1, 2], [6, 9]])
    >>> r.minus(other)
    [(0, 1), (2, 3), (5, 6)]
    """

    __slots__ = ("_lo", "_hi", "count", "untracked", "max_ranges")

    def __init__(self, max_ranges: int = MAX_SEQ_RANGES):
        self._lo: list[int] = []
        self._hi: list[int] = []
        self.count = 0  # numbers held in the ranges
        self.untracked = 0  # numbers not placed: the range budget was spent
        self.max_ranges = int(max_ranges)

    def add(self, seq: int) -> bool:
        """Add one number; False if it was there already."""
        seq = int(seq)
        los, his = self._lo, self._hi
        if his and seq == his[-1]:  # the next number of a stream: the last range grows
            his[-1] += 1
            self.count += 1
            return True
        i = bisect.bisect_right(los, seq) - 1
        if i >= 0 and seq < his[i]:
            return False
        left = i >= 0 and his[i] == seq
        right = i + 1 < len(los) and los[i + 1] == seq + 1
        if left and right:
            his[i] = his[i + 1]
            del los[i + 1], his[i + 1]
        elif left:
            his[i] += 1
        elif right:
            los[i + 1] = seq
        elif len(los) >= self.max_ranges:
            self.untracked += 1
            return True
        else:
            los.insert(i + 1, seq)
            his.insert(i + 1, seq + 1)
        self.count += 1
        return True

    def _take(self, ranges) -> None:
        for lo, hi in ranges:
            if len(self._lo) >= self.max_ranges:
                self.untracked += hi - lo
                continue
            self._lo.append(lo)
            self._hi.append(hi)
            self.count += hi - lo

    def ranges(self) -> list[tuple[int, int]]:
        """The ``[lo, hi)`` ranges, in order."""
        return list(zip(self._lo, self._hi))

    @property
    def newest(self) -> int | None:
        """The highest number held (None when empty)."""
        return self._hi[-1] - 1 if self._hi else None

    def minus(self, other: SeqRanges, below: int | None = None) -> list[tuple[int, int]]:
        """The ``[lo, hi)`` ranges of numbers here and not in ``other`` (only those below ``below``, if given)."""
        out: list[tuple[int, int]] = []
        theirs = other.ranges()
        j = 0
        for lo, hi in self.ranges():
            if below is not None:
                hi = min(hi, below)
            while lo < hi:
                while j < len(theirs) and theirs[j][1] <= lo:
                    j += 1
                if j == len(theirs) or theirs[j][0] >= hi:
                    out.append((lo, hi))
                    break
                if theirs[j][0] > lo:
                    out.append((lo, theirs[j][0]))
                lo = theirs[j][1]
        return out

    def to_list(self) -> list[list[int]]:
        """``[[lo, hi], ...]`` (JSON)."""
        return [[lo, hi] for lo, hi in zip(self._lo, self._hi)]

    @classmethod
    def from_list(cls, ranges, untracked: int = 0, max_ranges: int = MAX_SEQ_RANGES) -> SeqRanges:
        """The set of :meth:`to_list` ranges (in any order, overlapping or not) and ``untracked`` numbers."""
        out = cls(max_ranges)
        out._take(_union([(int(lo), int(hi)) for lo, hi in ranges if int(hi) > int(lo)], []))
        out.untracked += int(untracked)
        return out

    def union(self, other: SeqRanges) -> SeqRanges:
        """A new set: the numbers of both (``untracked`` summed)."""
        out = SeqRanges(max(self.max_ranges, other.max_ranges))
        out._take(_union(self.ranges(), other.ranges()))
        out.untracked += self.untracked + other.untracked
        return out


def _union(a, b) -> list[tuple[int, int]]:
    """Sorted disjoint ``[lo, hi)`` ranges covering those of ``a`` and ``b`` (touching ranges joined)."""
    out: list[list[int]] = []
    for lo, hi in sorted([*a, *b]):
        if out and lo <= out[-1][1]:
            out[-1][1] = max(out[-1][1], hi)
        else:
            out.append([lo, hi])
    return [(lo, hi) for lo, hi in out]


def format_ranges(ranges, most: int = 8) -> str:
    """``[lo, hi)`` ranges as inclusive text, the first ``most`` of them: ``"seq 0-97, 120"`` (``"... and N more
    ranges"`` beyond).

    >>> format_ranges([(0, 98), (120, 121), (130, 140)], most=2)
    'seq 0-97, 120 and 1 more range'
    """
    ranges = list(ranges)
    text = ", ".join(f"{lo}-{hi - 1}" if hi - lo > 1 else f"{lo}" for lo, hi in ranges[:most])
    more = len(ranges) - most
    return f"seq {text}" + (f" and {more} more range{'s' if more > 1 else ''}" if more > 0 else "")
