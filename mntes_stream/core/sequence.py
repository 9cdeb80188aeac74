"""Sequence numbers of one chunk stream: lost, late, duplicated, restarted.

One tracker per stream (a ``(board, module)`` counts stream, a recorded
topic). Every consumer of sequenced chunks (the converter, the recorder, the
feeds, the monitor) books its numbers here, so "lost" means the same
everywhere:

- a number above the next expected one: the skipped numbers are *lost*
  (and remembered, up to ``max_missing``, in case they turn up late);
- a skipped number that turns up: no longer lost, *out of order*;
- a number seen recently (the last ``max_recent``) with the same first sample
  time: a *duplicate* (the caller drops it);
- a recent number with other sample times, or a jump of more than
  ``max_missing`` either way: the source *restarted*; the tracker starts over
  from it and counts a reset, not thousands of lost or late chunks.

Memory per stream is bounded by ``max_recent + max_missing`` entries.

>>> s = StreamSequence()
>>> [s.observe(n, t_first_ns=10 * n) for n in (0, 1, 3, 2, 2)]
['new', 'new', 'new', 'late', 'duplicate']
>>> s.lost, s.out_of_order, s.duplicated
(0, 1, 1)
>>> s.observe(100_000, t_first_ns=0), s.resets
('reset', 1)
"""

from __future__ import annotations

import collections

__all__ = ["StreamSequence"]

MAX_RECENT = 256  # numbers remembered to spot duplicates
MAX_MISSING = 4096  # skipped numbers remembered to spot late arrivals; a longer jump is a restart


class StreamSequence:
    """Book-keeping of one stream's sequence numbers (see the module docstring).

    Attributes
    ----------
    lost : int
        Numbers skipped and not (yet) seen since.
    out_of_order, duplicated, resets : int
        Chunks that came late, came twice, or restarted the stream.
    """

    __slots__ = ("next", "_recent", "_recent_t", "_missing", "max_recent", "max_missing",
                 "lost", "out_of_order", "duplicated", "resets")

    def __init__(self, max_recent: int = MAX_RECENT, max_missing: int = MAX_MISSING):
        self.max_recent = int(max_recent)
        self.max_missing = int(max_missing)
        self.next: int | None = None
        self._recent: collections.deque[int] = collections.deque()
        self._recent_t: dict[int, int] = {}  # seq -> first sample time: a duplicate has both equal
        self._missing: collections.OrderedDict[int, None] = collections.OrderedDict()
        self.lost = self.out_of_order = self.duplicated = self.resets = 0

    def observe(self, seq: int, t_first_ns: int) -> str:
        """Book one chunk's number.

        Parameters
        ----------
        seq : int
        t_first_ns : int
            Time of the chunk's first sample (tells a duplicate from a restart).

        Returns
        -------
        str
            ``"new"``, ``"late"`` (a skipped number turned up, or one older
            than anything remembered), ``"duplicate"`` (drop it) or ``"reset"``
            (the stream restarted at this number; take it).
        """
        seq = int(seq)
        seen = self._recent_t.get(seq)
        if seen == t_first_ns:
            self.duplicated += 1
            return "duplicate"
        verdict = "new"
        if seen is not None or (self.next is not None and abs(seq - self.next) > self.max_missing):
            self.resets += 1
            self._forget()
            verdict = "reset"
        if self.next is None or seq >= self.next:
            if self.next is not None and seq > self.next:
                self.lost += seq - self.next
                for missing in range(max(self.next, seq - self.max_missing), seq):
                    self._missing[missing] = None
                while len(self._missing) > self.max_missing:
                    self._missing.popitem(last=False)
            self.next = seq + 1
        else:
            if seq in self._missing:
                del self._missing[seq]
                self.lost -= 1
            self.out_of_order += 1
            verdict = "late"
        self._recent.append(seq)
        self._recent_t[seq] = int(t_first_ns)
        if len(self._recent) > self.max_recent:
            self._recent_t.pop(self._recent.popleft(), None)
        return verdict

    def _forget(self) -> None:
        self.next = None
        self._recent.clear()
        self._recent_t.clear()
        self._missing.clear()
