"""Housekeeping alignment: environment readings at every sample time (pure, no I/O).

Housekeeping (bath temperature, magnetic field, bias) arrives at its own
cadence with its own timestamps. For each sample time ``t``:

- where readings bracket ``t`` (one at or before, one at or after), the value
  is interpolated linearly between the two;
- after the newest reading, the newest value is held; before the oldest, the
  oldest value is used;
- the *age* of a sample's value is its distance to the nearest reading used
  (``min(t - t_prev, t_next - t)`` when bracketed). Age above the staleness
  limit sets ``HK_STALE`` (the value is still given here: the converter
  decides what its power is, see ``hk_stale_power``); with no usable reading
  at all the value is NaN and ``HK_MISSING`` is set. Before the oldest
  reading, only a reading within the staleness limit is used; otherwise the
  sample is ``HK_MISSING`` (nothing is known that early);
- readings outside the valid range (or non-finite ones, which are dropped
  first) flag ``ENV_OUT_OF_RANGE`` on every sample they contribute to.

Times are int64 ns; the arithmetic is done in int64 relative to the first
reading so ns timestamps near 2e18 keep full precision.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.errors import ConfigError

__all__ = ["Aligned", "align", "sample_times_ns", "last_sample_offset_ns", "HkSeries"]

_INT64_MIN, _INT64_MAX = -(1 << 63), (1 << 63) - 1


def last_sample_offset_ns(sample_rate_hz: float, n: int) -> int:
    """Offset of sample ``n - 1`` from the first, ``round((n - 1) * 1e9 / rate)`` exactly as
    :func:`sample_times_ns` computes it (0 for ``n <= 1``); a Python int, never wrapped.

    Raises ConfigError unless the rate is finite and > 0 with a finite period
    and the offset is finite.

    >>> from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
    >>> last_sample_offset_ns(DFMUX_SAMPLE_RATE_HZ, 2)  # one DfMux sample: 655,360 ticks of 10 ns
    6553600
    """
    rate = float(sample_rate_hz)
    step = 1e9 / rate if math.isfinite(rate) and rate > 0 else math.nan
    if not math.isfinite(step):  # 1e-300 Hz: an infinite step, and 0 * inf is NaN even for sample 0
        raise ConfigError(f"sample rate must be finite and > 0 with a finite period, got {sample_rate_hz!r}")
    if n <= 1:
        return 0
    off = float(np.rint(np.float64(n - 1) * step))
    if not math.isfinite(off):
        raise ConfigError(f"{n} samples at {rate} Hz span more than any time can")
    return int(off)


def sample_times_ns(t0_ns: int, sample_rate_hz: float, n: int) -> np.ndarray:
    """Times of a regularly sampled chunk: ``t0_ns + round(k * 1e9 / rate)``, int64 (n,).

    Raises ConfigError when the last time does not fit int64 (numpy would wrap it silently).

    >>> sample_times_ns(1_000, 3.0, 4).tolist()
    [1000, 333334333, 666667667, 1000001000]
    """
    n, t0 = int(n), int(t0_ns)
    last = t0 + last_sample_offset_ns(sample_rate_hz, n)
    if not (_INT64_MIN <= t0 <= _INT64_MAX and last <= _INT64_MAX):
        raise ConfigError(f"{n} samples from t0 {t0} ns at {sample_rate_hz} Hz end beyond int64 ns")
    k = np.arange(n, dtype=np.float64)
    return np.int64(t0_ns) + np.rint(k * (1e9 / float(sample_rate_hz))).astype(np.int64)


@dataclass(frozen=True)
class Aligned:
    """Housekeeping at sample times.

    Attributes
    ----------
    value : ndarray of float64, shape (n,) or (n, k)
        NaN where ``HK_MISSING``.
    flags : ndarray of uint16, shape (n,)
        ``HK_STALE``, ``HK_MISSING``, ``ENV_OUT_OF_RANGE`` bits.
    age_ns : ndarray of int64, shape (n,)
        Distance to the nearest reading used (-1 where missing).
    """

    value: np.ndarray
    flags: np.ndarray
    age_ns: np.ndarray


def align(
    t_ns,
    hk_t_ns,
    hk_value,
    staleness_ns: int,
    valid_range: tuple[float, float] | None = None,
) -> Aligned:
    """Housekeeping values at sample times ``t_ns``.

    Parameters
    ----------
    t_ns : array_like of int64, shape (n,)
        Sample times (any order).
    hk_t_ns : array_like of int64, shape (m,)
        Reading times, strictly increasing.
    hk_value : array_like of float, shape (m,) or (m, k)
        Readings; rows with any non-finite entry are ignored.
    staleness_ns : int
        Largest allowed age of a value before ``HK_STALE``.
    valid_range : (lo, hi), optional
        Readings outside ``[lo, hi]`` flag ``ENV_OUT_OF_RANGE``.

    Returns
    -------
    Aligned
    """
    t = np.asarray(t_ns, dtype=np.int64)
    ht = np.asarray(hk_t_ns, dtype=np.int64)
    hv = np.asarray(hk_value, dtype=np.float64)
    if t.ndim != 1 or ht.ndim != 1 or hv.ndim not in (1, 2) or hv.shape[0] != ht.shape[0]:
        raise ConfigError(f"align: shapes t {t.shape}, hk_t {ht.shape}, hk_value {hv.shape} do not fit")
    if ht.size > 1 and np.any(np.diff(ht) <= 0):
        raise ConfigError("align: housekeeping times must be strictly increasing")
    if staleness_ns < 0:
        raise ConfigError("align: staleness must be >= 0")
    finite = np.isfinite(hv) if hv.ndim == 1 else np.all(np.isfinite(hv), axis=1)
    if not np.all(finite):
        ht, hv = ht[finite], hv[finite]
    return _align_checked(t, ht, hv, staleness_ns, valid_range)


def _align_checked(t: np.ndarray, ht: np.ndarray, hv: np.ndarray, staleness_ns: int, valid_range) -> Aligned:
    """:func:`align` on inputs it has checked: ``t`` int64 (n,), ``ht`` int64 (m,) strictly increasing,
    ``hv`` float64 (m,) or (m, k) all finite, ``staleness_ns`` >= 0.

    :class:`HkSeries` keeps its history so (sorted, non-finite readings dropped on add) and calls this
    directly: the checks cost more than the alignment of a short chunk. Steps whose outcome is known
    (every sample after a reading, no reading out of range, none missing) are skipped; the arithmetic
    of every value is the same as when they are not.
    """
    n, m = t.size, ht.size
    flag_dtype = fl.FLAG_DTYPE
    if m == 0:
        return Aligned(np.full((n,) + hv.shape[1:], np.nan), np.full(n, fl.HK_MISSING, dtype=flag_dtype),
                       np.full(n, -1, dtype=np.int64))
    # prev: newest reading at or before t; nxt: oldest reading at or after t (idx <= m: prev <= m - 1).
    idx = np.searchsorted(ht, t, side="right")
    prev = np.maximum(idx - 1, 0)
    has_prev = idx > 0
    all_prev = bool(has_prev.all())
    ht_prev = ht[prev]
    exact = has_prev & (ht_prev == t)
    nxt = np.minimum(idx, m - 1)
    if exact.any():
        nxt = np.where(exact, prev, nxt)
    has_next = exact | (idx < m)
    bracketed = has_prev & has_next
    ht_next = ht[nxt]
    # int64 differences: exact for ns timestamps.
    d_prev = t - ht_prev
    d_next = ht_next - t
    span = ht_next - ht_prev
    w = np.zeros(n)
    np.divide(d_prev, span, out=w, where=bracketed & (span > 0))
    hv_prev, hv_next = hv[prev], hv[nxt]
    value = hv_prev + (w if hv.ndim == 1 else w[:, None]) * (hv_next - hv_prev)
    # Before the oldest reading: the oldest value (age d_next); after the newest: hold.
    age = np.where(bracketed, np.minimum(d_prev, d_next), np.where(has_prev, d_prev, d_next))
    if all_prev:
        missing = None
        stale = age > staleness_ns
    else:
        value[~has_prev] = hv_next[~has_prev]
        missing = ~has_prev & (d_next > staleness_ns)
        stale = ~missing & (age > staleness_ns)
    flags = stale.astype(flag_dtype) * np.array(fl.HK_STALE, dtype=flag_dtype)
    if valid_range is not None:
        lo, hi = valid_range
        inside = (hv >= lo) & (hv <= hi)
        bad = ~(inside if hv.ndim == 1 else np.all(inside, axis=1))
        if bad.any():
            used_prev = has_prev & (~bracketed | (w < 1.0))
            used_next = ~has_prev | (bracketed & (w > 0.0))
            out_of_range = (used_prev & bad[prev]) | (used_next & bad[nxt])
            if missing is not None:
                out_of_range &= ~missing
            flags[out_of_range] |= fl.ENV_OUT_OF_RANGE
    if missing is not None and missing.any():
        flags[missing] |= fl.HK_MISSING
        value[missing] = np.nan
        age = np.where(missing, -1, age)
    return Aligned(value=value, flags=flags, age_ns=age.astype(np.int64, copy=False))


class HkSeries:
    """A growing, bounded history of one sensor's readings (pure state, no I/O).

    Readings may arrive in any order; a reading at an existing time replaces
    the old one. Non-finite readings (failed sensor reads) are dropped.
    Readings older than ``retention_ns`` before the caller's clock (``now_ns``
    of :meth:`add`) are pruned, so memory stays bounded in a long run. Without
    ``now_ns`` the newest reading is the clock: then one reading stamped far
    in the future prunes the whole history, so callers that cannot vouch for
    the readings' times pass ``now_ns``.

    Parameters
    ----------
    width : int or None
        None for scalar sensors; the number of channels for per-channel ones.
    retention_ns : int
        History kept behind the clock.
    """

    def __init__(self, width: int | None = None, retention_ns: int = 600 * 10**9):
        self.width = width
        self.retention_ns = int(retention_ns)
        self.t_ns = np.zeros(0, dtype=np.int64)
        self.value = np.zeros((0,) if width is None else (0, width))
        self.version = 0  # incremented by every add(): lets callers cache alignments

    def __len__(self) -> int:
        return int(self.t_ns.size)

    @property
    def newest_t_ns(self) -> int | None:
        return int(self.t_ns[-1]) if self.t_ns.size else None

    def add(self, t_ns, value, now_ns: int | None = None) -> None:
        """Add readings: ``t_ns`` (n,) int64, ``value`` (n,) or (n, width).

        ``now_ns``: the caller's clock; history older than ``now_ns -
        retention_ns`` is pruned (default: relative to the newest reading);
        the newest reading is always kept.
        """
        t = np.asarray(t_ns, dtype=np.int64).reshape(-1)
        v = np.asarray(value, dtype=np.float64)
        want = (t.size,) if self.width is None else (t.size, self.width)
        if v.shape != want:
            raise ConfigError(f"HkSeries.add: value shape {v.shape}, expected {want}")
        if v.ndim == 1:
            finite = np.isfinite(v)
        else:
            finite = np.all(np.isfinite(v), axis=1)
        if not finite.all():  # align() would ignore them anyway; dropping them here keeps windows exact
            t, v = t[finite], v[finite]
        if t.size == 0:
            return
        self.version += 1
        if self.t_ns.size and t.min() > self.t_ns[-1] and np.all(np.diff(t) > 0):
            self.t_ns = np.concatenate([self.t_ns, t])
            self.value = np.concatenate([self.value, v])
        else:
            # Out of order: sort only the new readings (last of equal times wins), then place
            # them by binary search. A trickle of old readings costs O(k log n) searches and
            # one copy, never a re-sort of the whole history.
            order = np.argsort(t, kind="stable")
            t, v = t[order], v[order]
            last = np.ones(t.size, dtype=bool)
            last[:-1] = t[1:] != t[:-1]
            t, v = t[last], v[last]
            pos = np.searchsorted(self.t_ns, t, side="left")
            inside = pos < self.t_ns.size
            same = np.zeros(t.size, dtype=bool)
            same[inside] = self.t_ns[pos[inside]] == t[inside]
            if same.any():  # a reading at an existing time replaces it: newest message wins
                self.value = self.value.copy()
                self.value[pos[same]] = v[same]
            new = ~same
            self.t_ns = np.insert(self.t_ns, pos[new], t[new])
            self.value = np.insert(self.value, pos[new], v[new], axis=0)
        ref = int(self.t_ns[-1]) if now_ns is None else int(now_ns)
        # The newest reading always stays: a silent sensor's last value holds (flagged stale).
        cut = min(int(np.searchsorted(self.t_ns, max(ref - self.retention_ns, _INT64_MIN), side="left")),
                  self.t_ns.size - 1)
        if cut > 0:
            self.t_ns, self.value = self.t_ns[cut:], self.value[cut:]

    def align(self, t_ns, staleness_ns: int, valid_range=None) -> Aligned:
        """:func:`align` against this history; only the readings that can matter are looked at."""
        t = np.asarray(t_ns, dtype=np.int64)
        if t.ndim != 1 or staleness_ns < 0 or t.size == 0 or self.t_ns.size == 0:
            return align(t, self.t_ns, self.value, staleness_ns, valid_range)  # its checks, or nothing to do
        # The newest reading at or before min(t) and the oldest at or after max(t)
        # bound everything align() uses (non-finite readings were dropped on add).
        i0 = max(int(np.searchsorted(self.t_ns, t.min(), side="right")) - 1, 0)
        i1 = min(int(np.searchsorted(self.t_ns, t.max(), side="left")) + 1, self.t_ns.size)
        # The history is sorted, strictly increasing and finite (add keeps it so): align()'s checks hold.
        return _align_checked(t, self.t_ns[i0:i1], self.value[i0:i1], staleness_ns, valid_range)
