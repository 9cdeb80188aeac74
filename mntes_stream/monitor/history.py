"""Bounded history for the monitor: rings that grow with the data received, never with what a sender claims.

A :class:`Ring` has a hard capacity in samples fixed by the monitor's
configuration (a window times ``max_rate_hz``); its storage starts small and
doubles as samples actually arrive, so a stream that *claims* 1 MHz but sends
20 samples costs 20 samples. :class:`SlowRing` keeps per-bin means of every
channel (the downsampled long history); pure numpy, no I/O.
"""

from __future__ import annotations

import numpy as np

__all__ = ["Ring", "SlowRing"]

_FIRST_ALLOC = 64


class Ring:
    """The newest ``capacity`` samples of ``n_rows`` rows, time-ordered.

    Parameters
    ----------
    n_rows : int
    capacity : int
        Hard limit in samples (from configuration only).
    dtype : numpy dtype
        Of the values: float32 for display, float64 where fW lines on a pW level are fitted.
    """

    def __init__(self, n_rows: int, capacity: int, dtype=np.float32):
        self.n_rows = int(n_rows)
        self.capacity = max(int(capacity), 2)
        self._t = np.zeros(0, dtype=np.int64)
        self._v = np.zeros((self.n_rows, 0), dtype=dtype)
        self._head = 0   # next write position once full; while growing, == count
        self.count = 0

    @property
    def nbytes(self) -> int:
        """Bytes held now."""
        return int(self._t.nbytes + self._v.nbytes)

    @staticmethod
    def max_nbytes(n_rows: int, capacity: int) -> int:
        """Bytes a full ring of this shape holds: what a budget reserves for it."""
        return int(max(capacity, 2)) * (8 + 4 * int(n_rows))

    def clear(self) -> None:
        self._t = self._t[:0].copy()
        self._v = np.zeros((self.n_rows, 0), dtype=self._v.dtype)
        self._head = self.count = 0

    def _grow(self, need: int) -> None:
        alloc = min(self.capacity, max(_FIRST_ALLOC, 2 * self._t.size, need))
        t = np.zeros(alloc, dtype=np.int64)
        v = np.full((self.n_rows, alloc), np.nan, dtype=self._v.dtype)
        t[: self.count] = self._t[: self.count]
        v[:, : self.count] = self._v[:, : self.count]
        self._t, self._v = t, v
        self._head = self.count

    def append(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        """Add samples: times (n,) int64, values (n_rows, n), newer than any held (the caller checks)."""
        n = int(t_ns.size)
        if n == 0:
            return
        if n >= self.capacity:
            t_ns, values, n = t_ns[-self.capacity:], values[:, -self.capacity:], self.capacity
        alloc = self._t.size
        if alloc < self.capacity and self.count + n > alloc:
            self._grow(self.count + n)
            alloc = self._t.size
        first = min(n, alloc - self._head)  # slices, not fancy indexing: this runs for every chunk
        self._t[self._head:self._head + first] = t_ns[:first]
        self._v[:, self._head:self._head + first] = values[:, :first]
        if first < n:
            self._t[: n - first] = t_ns[first:]
            self._v[:, : n - first] = values[:, first:]
        self._head = (self._head + n) % alloc
        self.count = min(self.count + n, alloc)

    def read(self, rows=None, since_ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Held samples, oldest first: times (m,) and values float64 (len(rows), m) (all rows when None)."""
        alloc = self._t.size
        if alloc == 0:
            n_rows = self.n_rows if rows is None else len(rows)
            return np.zeros(0, dtype=np.int64), np.zeros((n_rows, 0))
        start = (self._head - self.count) % alloc
        # Oldest first as (at most) two slices; the times are ordered, so `since_ns` is a binary search.
        parts = [(start, min(start + self.count, alloc))]
        if start + self.count > alloc:
            parts.append((0, start + self.count - alloc))
        if since_ns is not None:
            kept = []
            for a, b in parts:
                a = a + int(np.searchsorted(self._t[a:b], since_ns, side="left"))
                if a < b:
                    kept.append((a, b))
            parts = kept
        t = np.concatenate([self._t[a:b] for a, b in parts]) if parts else self._t[:0].copy()
        v = self._v if rows is None else self._v[np.asarray(rows)]
        vals = [v[:, a:b] for a, b in parts]
        return t, (np.concatenate(vals, axis=1) if vals else v[:, :0]).astype(np.float64)

    @property
    def newest_t_ns(self) -> int | None:
        if self.count == 0:
            return None
        return int(self._t[(self._head - 1) % self._t.size])


class SlowRing:
    """Per-bin means of every row over a long window: the downsampled history.

    Samples accumulate into the open bin (``bin_ns`` wide, on the data clock);
    a sample in a later bin closes it and its means go to a :class:`Ring`.

    Parameters
    ----------
    n_rows : int
    bin_s : float
    window_s : float
    """

    def __init__(self, n_rows: int, bin_s: float, window_s: float):
        self.bin_ns = max(int(bin_s * 1e9), 1)
        self.ring = Ring(n_rows, int(np.ceil(window_s / bin_s)))
        self._bin: int | None = None
        self._sum = np.zeros(n_rows)
        self._n = np.zeros(n_rows, dtype=np.int64)

    @staticmethod
    def max_nbytes(n_rows: int, bin_s: float, window_s: float) -> int:
        return Ring.max_nbytes(n_rows, int(np.ceil(window_s / bin_s))) + 16 * int(n_rows)

    @property
    def nbytes(self) -> int:
        return self.ring.nbytes + self._sum.nbytes + self._n.nbytes

    def clear(self) -> None:
        self.ring.clear()
        self._bin = None
        self._sum[:] = 0
        self._n[:] = 0

    def _close(self) -> None:
        if self._bin is not None:
            with np.errstate(invalid="ignore", divide="ignore"):
                mean = np.where(self._n > 0, self._sum / np.maximum(self._n, 1), np.nan)
            self.ring.append(np.array([self._bin * self.bin_ns + self.bin_ns // 2]), mean[:, None])
        self._sum[:] = 0
        self._n[:] = 0

    def add(self, t_ns: np.ndarray, values: np.ndarray) -> None:
        """Samples (n,) and (n_rows, n), time-ordered and newer than any added before."""
        if t_ns.size == 0:
            return
        bins = t_ns // self.bin_ns
        starts = np.concatenate(([0], np.flatnonzero(bins[1:] != bins[:-1]) + 1))
        finite = np.isfinite(values)
        v = np.where(finite, values, 0.0)
        sums = np.add.reduceat(v, starts, axis=1)
        counts = np.add.reduceat(finite.astype(np.int64), starts, axis=1)
        for j, s in enumerate(starts.tolist()):
            b = int(bins[s])
            if self._bin is not None and b != self._bin:
                self._close()
            self._bin = b
            self._sum += sums[:, j]
            self._n += counts[:, j]

    def read(self, rows=None, since_ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Closed bins' centre times (m,) and means (len(rows), m)."""
        return self.ring.read(rows, since_ns)
