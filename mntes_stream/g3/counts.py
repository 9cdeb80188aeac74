"""Counts of wired bolometers from G3 frames: collated Scan frames and raw Timepoint frames.

Both give a :class:`ScanBlock` (times from G3 ticks x 10 ns, I and Q as
float64 with NaN where a sample is missing), so everything downstream is the
same for either layout.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mntes_stream.core.timing import G3_TICK_NS
from mntes_stream.g3.mapping import Wiring, g3_time_ns

__all__ = ["ScanBlock", "scan_block", "TimepointBuffer"]


@dataclass(frozen=True)
class ScanBlock:
    """Counts of wired bolometers over a span of samples.

    Attributes
    ----------
    t_ns : ndarray of int64, shape (n_samp,)
    rows : ndarray of int64, shape (n_det,)
        Wiring rows of the bolometers present.
    counts_i, counts_q : ndarray of float64, shape (n_det, n_samp)
        NaN where a sample is missing.
    """

    t_ns: np.ndarray
    rows: np.ndarray
    counts_i: np.ndarray
    counts_q: np.ndarray

    @property
    def n_samples(self) -> int:
        return int(self.t_ns.size)


def _times_of(frame, tsmap) -> np.ndarray:
    if "DetectorSampleTimes" in frame:
        return np.array([t.time for t in frame["DetectorSampleTimes"]], dtype=np.int64) * G3_TICK_NS
    n = int(tsmap.n_samples)
    start, stop = int(tsmap.start.time), int(tsmap.stop.time)
    if n <= 1:
        return np.array([start] * n, dtype=np.int64) * G3_TICK_NS
    # G3 spans are inclusive of the last sample: stop = start + (n - 1) / rate.
    return (start + np.rint(np.arange(n) * ((stop - start) / (n - 1))).astype(np.int64)) * G3_TICK_NS


def scan_block(frame, wiring: Wiring, input_i: str = "RawTimestreams_I", input_q: str = "RawTimestreams_Q"):
    """Counts of a collated Scan frame, or None if it has no ``input_i``/``input_q`` maps."""
    if input_i not in frame or input_q not in frame:
        return None
    mi, mq = frame[input_i], frame[input_q]
    names = [n for n in mi.keys() if n in mq]
    rows = wiring.index_of_names(names)
    keep = np.flatnonzero(rows >= 0)
    order = keep[np.argsort(rows[keep], kind="stable")]
    t_ns = _times_of(frame, mi)
    n = t_ns.size
    ci = np.empty((order.size, n))
    cq = np.empty((order.size, n))
    for k, j in enumerate(order):
        ci[k] = np.asarray(mi[names[j]], dtype=np.float64)
        cq[k] = np.asarray(mq[names[j]], dtype=np.float64)
    return ScanBlock(t_ns, rows[order], ci, cq)


class TimepointBuffer:
    """Raw Timepoint frames (``EventHeader``, ``DfMux``) collected into :class:`ScanBlock` s.

    A wired channel whose board or module is absent from a Timepoint is NaN
    there, as ``DfMuxCollator`` leaves it.
    """

    def __init__(self, wiring: Wiring):
        self.wiring = wiring
        boards: dict = {}
        for (b, m), rows in wiring.modules().items():
            ch = wiring.channel[rows]
            boards.setdefault(int(b), []).append((int(m), rows, 2 * ch, 2 * ch + 1, int(2 * ch.max() + 2)))
        self._boards = list(boards.items())
        self._sizes: list[int] | None = None  # module sample sizes of the fast path (set by the first full frame)
        self._gather_i = self._gather_q = self._rows_all = None
        self._t: list[int] = []
        self._i: list[np.ndarray] = []
        self._q: list[np.ndarray] = []

    def __len__(self) -> int:
        return len(self._t)

    @property
    def last_t_ns(self) -> int | None:
        return self._t[-1] if self._t else None

    def _fast(self, meta):
        """I, Q of every wired channel when every wired module is there as before (one gather), else None."""
        try:
            arrays = [np.asarray(board[m]) for b, modules in self._boards for board in (meta[b],) for m, *_ in modules]
        except KeyError:
            return None
        sizes = [a.size for a in arrays]
        if sizes != self._sizes:  # first frame, or the modules changed size: new gather indices
            mods = [mod for _, modules in self._boards for mod in modules]
            if any(size < mod[4] for size, mod in zip(sizes, mods)):
                return None
            offsets = np.concatenate([[0], np.cumsum(sizes)[:-1]]).astype(np.int64)
            self._gather_i = np.concatenate([o + mod[2] for o, mod in zip(offsets, mods)])
            self._gather_q = np.concatenate([o + mod[3] for o, mod in zip(offsets, mods)])
            self._rows_all = np.concatenate([mod[1] for mod in mods])
            self._sizes = sizes
        flat = np.concatenate(arrays)
        return flat[self._gather_i], flat[self._gather_q]

    def add(self, frame) -> None:
        n = len(self.wiring)
        meta = frame["DfMux"]
        fast = self._fast(meta)
        if fast is not None:
            ci, cq = np.empty(n), np.empty(n)
            ci[self._rows_all], cq[self._rows_all] = fast  # every wired row
            self._t.append(g3_time_ns(frame["EventHeader"]))
            self._i.append(ci)
            self._q.append(cq)
            return
        ci, cq = np.full(n, np.nan), np.full(n, np.nan)
        for b, modules in self._boards:
            try:
                board = meta[b]
            except KeyError:
                continue
            for m, rows, ii, iq, need in modules:
                try:
                    s = np.asarray(board[m])
                except KeyError:
                    continue
                if s.size >= need:
                    ci[rows] = s[ii]
                    cq[rows] = s[iq]
                else:  # a module sending fewer channels than wired: those stay NaN
                    ok = iq < s.size
                    ci[rows[ok]] = s[ii[ok]]
                    cq[rows[ok]] = s[iq[ok]]
        self._t.append(g3_time_ns(frame["EventHeader"]))
        self._i.append(ci)
        self._q.append(cq)

    def take(self) -> ScanBlock | None:
        """Everything collected so far (None if nothing), and start over."""
        if not self._t:
            return None
        blk = ScanBlock(np.array(self._t, dtype=np.int64), np.arange(len(self.wiring), dtype=np.int64),
                        np.stack(self._i, axis=1), np.stack(self._q, axis=1))
        self._t, self._i, self._q = [], [], []
        return blk
