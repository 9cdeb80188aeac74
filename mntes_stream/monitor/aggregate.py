"""The monitor's aggregation core: decoded messages in, what the page shows out.

No I/O and no clock of its own: every method that needs the time takes it
(``now_ns``, ``t_recv_ns``: wall clock, int64 ns), so the core can be driven
by a test exactly as by the zenoh subscriber.

What it keeps, per ``(board, module)`` power stream, is a ring buffer of the
last ``history_s`` of power at full rate (float32) and the sample times; per
channel, flag counters since the last :meth:`Aggregator.tick`, from which the
channel's state is classified (:data:`STATE_NAMES`):

- ``silent``: no power chunk from its module for ``silent_s`` (receive clock);
- ``saturated`` (TES normal), ``superconducting`` or ``flagged`` (any other
  flag, or NaN without a flag): whichever of these three the most samples
  carry, provided at least ``flag_frac`` of the samples do;
- ``transition``: otherwise, i.e. usable power.

A tick with no samples from a module keeps its channels' states (chunks may
come slower than ticks) until the module falls silent.
"""

from __future__ import annotations

import collections
import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core.ids import detector_id
from mntes_stream.core.sequence import StreamSequence
from mntes_stream.core.settings import Settings, setting
from mntes_stream.monitor.analysis import (
    decimate_minmax,
    estimate_f_hwp,
    hwp_harmonics_hz,
    log_bin,
    welch_psd,
)

__all__ = [
    "STATE_NAMES",
    "STATE_TRANSITION",
    "STATE_SATURATED",
    "STATE_SUPERCONDUCTING",
    "STATE_FLAGGED",
    "STATE_SILENT",
    "MonitorConfig",
    "ModuleBuffer",
    "Aggregator",
]

STATE_NAMES = ("transition", "saturated", "superconducting", "flagged", "silent")
STATE_TRANSITION, STATE_SATURATED, STATE_SUPERCONDUCTING, STATE_FLAGGED, STATE_SILENT = range(5)

# Flags that make a channel "flagged" (saturated and superconducting have their own states).
_OTHER_FLAGS = np.uint16(sum(fl.NAMES) & ~(fl.SATURATED | fl.SUPERCONDUCTING))
_SCALAR_SENSORS = ("t_bath", "b_field")


@dataclass(frozen=True)
class MonitorConfig(Settings):
    """What the monitor keeps and how it reduces it.

    Attributes
    ----------
    history_s : float
        Full-rate power kept per channel (the time-stream window and the
        spectrum's data), and housekeeping history.
    max_points : int
        Points per time-stream or housekeeping trace sent to the page.
    spectrum_points : int
        Log-spaced points per spectrum sent to the page.
    f_hwp_hz : float or None
        HWP rotation frequency whose 1f/2f/4f are marked; None estimates it
        from the spectra (:func:`~mntes_stream.monitor.analysis.estimate_f_hwp`).
    silent_s : float
        A module with no power chunk for this long shows its channels silent.
    flag_frac : float
        Fraction of a channel's samples (since the last tick) that must be
        saturated, superconducting or otherwise flagged for it to leave "transition".
    hk_stale_s : float
        Housekeeping (or a service status) not received for this long is stale.
    max_selected : int
        Channels one page may plot at once.
    latency_reports : int
        Page render reports kept for the latency figures.
    """

    history_s: float = setting(30.0, "full-rate power kept per channel and plotted", unit="s", gt=0)
    max_points: int = setting(1200, "points per time-stream or housekeeping trace sent to the page", ge=2)
    spectrum_points: int = setting(400, "log-spaced points per spectrum sent to the page", ge=2)
    f_hwp_hz: float | None = setting(0.77, "HWP frequency whose 1f/2f/4f are marked (absent: estimated)", unit="Hz",
                                     gt=0)
    silent_s: float = setting(3.0, "a module without data this long shows its channels silent", unit="s", gt=0)
    flag_frac: float = setting(0.1, "share of a channel's samples flagged for it to leave 'transition'", gt=0, le=1)
    hk_stale_s: float = setting(2.0, "housekeeping or a service status not received this long is stale", unit="s",
                                gt=0)
    max_selected: int = setting(16, "channels one page may plot at once", ge=2)
    latency_reports: int = setting(600, "page render reports kept for the latency figures", ge=2)


class ModuleBuffer:
    """Full-rate power ring and state counters of one ``(board, module)`` stream.

    Parameters
    ----------
    board, module : int
    channels : ndarray of int32, shape (n_ch,)
    sample_rate_hz : float
    history_s : float
    """

    def __init__(self, board: int, module: int, channels: np.ndarray, sample_rate_hz: float, history_s: float):
        self.board = int(board)
        self.module = int(module)
        self.channels = np.asarray(channels, dtype=np.int32).copy()
        self.ids = tuple(detector_id(board, module, c) for c in self.channels.tolist())
        self.sample_rate_hz = float(sample_rate_hz)
        self.capacity = max(int(math.ceil(history_s * self.sample_rate_hz)), 16)
        n_ch = self.channels.size
        self._t = np.zeros(self.capacity, dtype=np.int64)
        self._p = np.full((n_ch, self.capacity), np.nan, dtype=np.float32)
        self._head = 0      # next write position
        self.count = 0      # valid samples in the ring
        self.newest_t_ns: int | None = None
        self.newest_t_pub_ns = 0
        self.last_recv_ns: int | None = None
        self.sequence = StreamSequence()
        self.late = 0
        self.restarts = 0
        self.state = np.full(n_ch, STATE_SILENT, dtype=np.uint8)
        self._reset_counters()

    def _reset_counters(self) -> None:
        n_ch = self.channels.size
        self._n = 0
        self._n_sat = np.zeros(n_ch, dtype=np.int64)
        self._n_sc = np.zeros(n_ch, dtype=np.int64)
        self._n_other = np.zeros(n_ch, dtype=np.int64)

    def matches(self, channels: np.ndarray, sample_rate_hz: float) -> bool:
        return np.array_equal(channels, self.channels) and abs(sample_rate_hz - self.sample_rate_hz) <= 1e-6 * self.sample_rate_hz

    def add(self, t_ns: np.ndarray, p_opt_w: np.ndarray, flags: np.ndarray, seq: int, t_pub_ns: int, t_recv_ns: int) -> None:
        """Append one chunk: times (n,), power and flags (n_ch, n)."""
        self.last_recv_ns = int(t_recv_ns)
        self.newest_t_pub_ns = max(self.newest_t_pub_ns, int(t_pub_ns))
        self.sequence.observe(seq, int(t_ns[0]) if t_ns.size else int(t_pub_ns))
        sat = (flags & fl.SATURATED) != 0
        sc = (flags & fl.SUPERCONDUCTING) != 0
        other = ((flags & _OTHER_FLAGS) != 0) | (~np.isfinite(p_opt_w) & ~sat & ~sc)
        self._n += flags.shape[1]
        self._n_sat += sat.sum(axis=1)
        self._n_sc += sc.sum(axis=1)
        self._n_other += other.sum(axis=1)
        n = t_ns.size
        if n == 0:
            return
        if self.newest_t_ns is not None and int(t_ns[0]) <= self.newest_t_ns:
            history_ns = self.capacity / self.sample_rate_hz * 1e9
            if int(t_ns[-1]) < self.newest_t_ns - history_ns:
                # Much older than anything held: a replay started over; start afresh.
                self.restarts += 1
                self.count = 0
                self._head = 0
            else:
                self.late += 1  # counted in the state, not drawn: the ring stays time-ordered
                return
        if n >= self.capacity:
            t_ns, p_opt_w = t_ns[-self.capacity:], p_opt_w[:, -self.capacity:]
            n = self.capacity
        idx = (self._head + np.arange(n)) % self.capacity
        self._t[idx] = t_ns
        self._p[:, idx] = p_opt_w
        self._head = (self._head + n) % self.capacity
        self.count = min(self.count + n, self.capacity)
        self.newest_t_ns = int(t_ns[-1])

    def classify(self, now_ns: int, config: MonitorConfig) -> None:
        """Set :attr:`state` from the counters since the last call, then reset them."""
        if self.last_recv_ns is None or now_ns - self.last_recv_ns > config.silent_s * 1e9:
            self.state[:] = STATE_SILENT
        elif self._n > 0:
            counts = np.stack([self._n_sat, self._n_sc, self._n_other])  # (3, n_ch)
            worst = np.argmax(counts, axis=0)  # ties go to the first: saturated, superconducting, flagged
            codes = np.array([STATE_SATURATED, STATE_SUPERCONDUCTING, STATE_FLAGGED], dtype=np.uint8)
            state = codes[worst]
            state[counts.max(axis=0) < config.flag_frac * self._n] = STATE_TRANSITION
            self.state = state
        self._reset_counters()

    def read(self, rows: np.ndarray, since_ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Samples held for ``rows``, oldest first: times (m,), power float64 (len(rows), m)."""
        start = (self._head - self.count) % self.capacity
        idx = (start + np.arange(self.count)) % self.capacity
        t = self._t[idx]
        if since_ns is not None:
            keep = t >= since_ns
            idx, t = idx[keep], t[keep]
        return t, self._p[np.asarray(rows)[:, None], idx[None, :]].astype(np.float64)


def _round_list(a: np.ndarray, decimals: int) -> list:
    """JSON-ready list: rounded, non-finite -> None (JSON has no NaN)."""
    a = np.round(np.asarray(a, dtype=np.float64), decimals)
    out = a.tolist()
    if not np.all(np.isfinite(a)):
        out = [v if math.isfinite(v) else None for v in out]
    return out


def _sig_list(a: np.ndarray, digits: int = 4) -> list:
    """JSON-ready list rounded to ``digits`` significant digits; non-finite -> None."""
    a = np.asarray(a, dtype=np.float64)
    out = []
    for v in a.tolist():
        out.append(float(f"{v:.{digits}g}") if math.isfinite(v) else None)
    return out


class _HkHistory:
    """Readings of one scalar sensor over the last ``history_s`` (data clock)."""

    def __init__(self, history_s: float):
        self.history_ns = int(history_s * 1e9)
        self.t = np.zeros(0, dtype=np.int64)
        self.v = np.zeros(0)
        self.last_recv_ns: int | None = None
        self.unit = ""

    def add(self, t_ns: np.ndarray, value: np.ndarray, unit: str, t_recv_ns: int) -> None:
        self.last_recv_ns = int(t_recv_ns)
        self.unit = unit
        if self.t.size and t_ns.size and int(t_ns[0]) <= int(self.t[-1]):
            if int(t_ns[-1]) < int(self.t[-1]) - self.history_ns:  # a replay started over
                self.t, self.v = self.t[:0], self.v[:0]
            else:
                keep = t_ns > self.t[-1]
                t_ns, value = t_ns[keep], value[keep]
        self.t = np.concatenate([self.t, t_ns])
        self.v = np.concatenate([self.v, value])
        if self.t.size:
            keep = self.t >= self.t[-1] - self.history_ns
            self.t, self.v = self.t[keep], self.v[keep]


class Aggregator:
    """Everything the monitor knows, reduced on demand for the page and the text table.

    Feed it with :meth:`add_power`, :meth:`add_hk`, :meth:`add_status`
    (decoded message objects, duck-typed) and :meth:`add_bad`; call
    :meth:`tick` on the update cadence (it classifies the channels and
    returns the parts every page shares), :meth:`view` for one page's
    selected channels. Not thread-safe: the caller holds a lock.
    """

    def __init__(self, config: MonitorConfig | None = None):
        self.config = config or MonitorConfig()
        self.modules: dict[tuple[int, int], ModuleBuffer] = {}
        self._index: dict[str, tuple[tuple[int, int], int]] = {}
        self.layout_version = 0
        self._layout_cache: tuple[int, list] | None = None
        self.hk: dict[str, _HkHistory] = {s: _HkHistory(self.config.history_s) for s in _SCALAR_SENSORS}
        self.bias_readings = 0
        self.statuses: dict[str, tuple] = {}  # service -> (status, t_recv_ns, input rate or None)
        self.bad_messages: collections.Counter = collections.Counter()
        self.dropped = 0
        self.power_chunks = 0
        self.power_samples = 0
        self._interval_chunks = 0
        self._interval_samples = 0
        self._interval_latency_ms: list[float] = []
        self._last_tick_ns: int | None = None
        self._renders: collections.deque = collections.deque(maxlen=self.config.latency_reports)

    # ------------------------------------------------------------------ input

    def add_power(self, chunk, t_recv_ns: int) -> None:
        """One :class:`~mntes_stream.io.messages.PowerChunk` (or anything with its attributes)."""
        key = (int(chunk.board), int(chunk.module))
        t_ns = chunk.times_ns()
        rate = chunk.sample_rate_hz
        if rate is None:  # explicit times: the median spacing
            rate = 1e9 / float(np.median(np.diff(t_ns))) if t_ns.size > 1 else 1.0
        buf = self.modules.get(key)
        if buf is None or not buf.matches(chunk.channels, rate):
            buf = ModuleBuffer(key[0], key[1], chunk.channels, rate, self.config.history_s)
            self.modules[key] = buf
            self._reindex()
        buf.add(t_ns, chunk.p_opt_w, chunk.flags, int(chunk.seq), int(chunk.t_pub_ns), t_recv_ns)
        self.power_chunks += 1
        self.power_samples += int(chunk.p_opt_w.size)
        self._interval_chunks += 1
        self._interval_samples += int(chunk.p_opt_w.size)
        self._interval_latency_ms.append((int(t_recv_ns) - int(chunk.t_pub_ns)) / 1e6)

    def add_hk(self, chunk, t_recv_ns: int) -> None:
        """One :class:`~mntes_stream.io.messages.HousekeepingChunk`."""
        if chunk.sensor in self.hk:
            self.hk[chunk.sensor].add(chunk.t_ns, chunk.value, chunk.unit, t_recv_ns)
        else:
            self.bias_readings += int(chunk.t_ns.size)

    def add_status(self, status, t_recv_ns: int) -> None:
        """One :class:`~mntes_stream.io.messages.StatusMessage`; the input rate comes from consecutive ones."""
        prev = self.statuses.get(status.service)
        rate = None
        if prev is not None and status.t_ns > prev[0].t_ns:
            dn = status.chunks_received - prev[0].chunks_received
            if dn >= 0:
                rate = dn / ((status.t_ns - prev[0].t_ns) / 1e9)
        self.statuses[status.service] = (status, int(t_recv_ns), rate)

    def add_bad(self, reason: str) -> None:
        """A message that could not be decoded (counted and shown, never raised)."""
        self.bad_messages[reason] += 1

    def report_render(self, t_pub_ns: int, t_render_ns: int) -> None:
        """The page drew data whose newest power chunk was published at ``t_pub_ns``."""
        self._renders.append((int(t_pub_ns), int(t_render_ns)))

    # ------------------------------------------------------------------ layout

    def _reindex(self) -> None:
        self._index = {}
        for key in sorted(self.modules):
            for row, det in enumerate(self.modules[key].ids):
                self._index[det] = (key, row)
        self.layout_version += 1

    def layout(self) -> list[dict]:
        """The grid's rows: one per module, sorted, with its channel numbers."""
        if self._layout_cache is None or self._layout_cache[0] != self.layout_version:
            rows = [{"board": b, "module": m, "channels": self.modules[(b, m)].channels.tolist()} for b, m in sorted(self.modules)]
            self._layout_cache = (self.layout_version, rows)
        return self._layout_cache[1]

    def states(self) -> np.ndarray:
        """Channel states (uint8 codes into :data:`STATE_NAMES`) in layout order."""
        parts = [self.modules[k].state for k in sorted(self.modules)]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.uint8)

    def state_of(self, det_id: str) -> str | None:
        where = self._index.get(det_id)
        if where is None:
            return None
        return STATE_NAMES[int(self.modules[where[0]].state[where[1]])]

    def detector_ids(self) -> list[str]:
        return list(self._index)

    def channels_not_in_transition(self, limit: int) -> tuple[list[tuple[str, str]], int]:
        """Up to ``limit`` ``(detector id, state)`` not in transition, in layout order, and their total."""
        out, total = [], 0
        for key in sorted(self.modules):
            buf = self.modules[key]
            rows = np.flatnonzero(buf.state != STATE_TRANSITION)
            total += rows.size
            for r in rows[: max(limit - len(out), 0)].tolist():
                out.append((buf.ids[r], STATE_NAMES[int(buf.state[r])]))
        return out, total

    def default_selection(self, n: int = 3) -> list[str]:
        """Up to ``n`` channels in transition, spread over the modules (else any channels)."""
        picks: list[str] = []
        keys = sorted(self.modules)
        for state in (STATE_TRANSITION, None):
            for i in range(n):
                for key in keys:
                    buf = self.modules[key]
                    rows = np.flatnonzero(buf.state == state) if state is not None else np.arange(buf.channels.size)
                    if i < rows.size and buf.ids[rows[i]] not in picks:
                        picks.append(buf.ids[rows[i]])
                    if len(picks) >= n:
                        return picks
        return picks

    # ------------------------------------------------------------------ output

    def tick(self, now_ns: int) -> dict:
        """Classify every channel and build the parts all pages share (JSON-ready dict).

        Returns
        -------
        dict
            ``t_ns``, ``layout_version``, ``codes`` (one digit per channel in
            :meth:`layout` order, an index into ``state_names``),
            ``state_counts``, ``hk`` (decimated history per sensor),
            ``health``.
        """
        now_ns = int(now_ns)
        for buf in self.modules.values():
            buf.classify(now_ns, self.config)
        states = self.states()
        interval_s = (now_ns - self._last_tick_ns) / 1e9 if self._last_tick_ns is not None else 0.0
        out = {
            "t_ns": now_ns,
            "layout_version": self.layout_version,
            "state_names": list(STATE_NAMES),
            "codes": (states + ord("0")).astype(np.uint8).tobytes().decode("ascii"),
            "state_counts": {name: int(np.count_nonzero(states == i)) for i, name in enumerate(STATE_NAMES)},
            "hk": self._hk_view(),
            "health": self._health(now_ns, interval_s),
        }
        self._interval_chunks = 0
        self._interval_samples = 0
        self._interval_latency_ms = []
        self._last_tick_ns = now_ns
        return out

    def _hk_view(self) -> dict:
        out = {}
        for sensor, h in self.hk.items():
            t, v = decimate_minmax(h.t, h.v, self.config.max_points)
            out[sensor] = {"t_ms": _round_list(t / 1e6, 0), "value": _sig_list(v, 7), "unit": h.unit}
        return out

    def _health(self, now_ns: int, interval_s: float) -> dict:
        lat = np.asarray(self._interval_latency_ms)
        renders = np.asarray(self._renders, dtype=np.int64).reshape(-1, 2)
        page_lat = (renders[:, 1] - renders[:, 0]) / 1e6
        stale_s = self.config.hk_stale_s
        hk = {}
        for sensor, h in self.hk.items():
            age = None if h.last_recv_ns is None else (now_ns - h.last_recv_ns) / 1e9
            hk[sensor] = {
                "value": float(h.v[-1]) if h.v.size and math.isfinite(h.v[-1]) else None,  # NaN: a failed reading
                "unit": h.unit,
                "age_s": age,
                "stale": age is None or age > stale_s,
            }
        services = []
        for name in sorted(self.statuses):
            s, t_recv, in_rate = self.statuses[name]
            age = (now_ns - t_recv) / 1e9
            services.append({
                "service": name,
                "age_s": age,
                "stale": age > max(stale_s, 3 * s.interval_s),
                "in_chunks_per_s": in_rate,
                "out_chunks_per_s": s.rate_chunks_per_s,
                "out_msamples_per_s": s.rate_msamples_per_s,
                "latency_p50_ms": s.latency_p50_ms,
                "latency_p99_ms": s.latency_p99_ms,
                "latency_max_ms": s.latency_max_ms,
                "chunks_received": s.chunks_received,
                "chunks_converted": s.chunks_converted,
                "chunks_lost": s.chunks_lost,
                "chunks_pending": s.chunks_pending,
                "hk_stale_samples": s.hk_stale_samples,
                "hk_missing_samples": s.hk_missing_samples,
                "hk_age_s": dict(s.hk_age_s),
                "bad_messages": int(sum(s.bad_messages.values())),
                "last_error": s.last_error,
            })
        mods = self.modules.values()
        return {
            "monitor": {
                "chunks_per_s": self._interval_chunks / interval_s if interval_s > 0 else None,
                "msamples_per_s": self._interval_samples / interval_s / 1e6 if interval_s > 0 else None,
                "latency_p50_ms": float(np.median(lat)) if lat.size else None,
                "latency_max_ms": float(lat.max()) if lat.size else None,
                "power_chunks": self.power_chunks,
                "lost_chunks": int(sum(max(b.sequence.lost, 0) for b in mods)),
                "late_chunks": int(sum(b.late for b in mods)),
                "dropped": self.dropped,
                "bad_messages": dict(self.bad_messages),
                "channels": len(self._index),
                "modules": len(self.modules),
                "bias_readings": self.bias_readings,
            },
            "page_latency_ms": {
                "n": int(page_lat.size),
                "p50": float(np.median(page_lat)) if page_lat.size else None,
                "max": float(page_lat.max()) if page_lat.size else None,
                "last": float(page_lat[-1]) if page_lat.size else None,
            },
            "services": services,
            "hk": hk,
        }

    def resolve(self, selection: Iterable[str]) -> list[str]:
        """The known detector ids of ``selection``, in order, at most ``max_selected``."""
        out = []
        for det in selection:
            if det in self._index and det not in out:
                out.append(det)
        return out[: self.config.max_selected]

    def view(self, selection: Iterable[str], f_hwp_hz: float | None | str = "config") -> dict:
        """Time streams and spectra of the selected channels (JSON-ready dict).

        Parameters
        ----------
        selection : iterable of str
            Detector ids; unknown ones are skipped (see ``unknown`` in the result).
        f_hwp_hz : float, None or "config"
            Harmonics to mark: a frequency, None to estimate from these
            spectra, "config" for :attr:`MonitorConfig.f_hwp_hz`.

        Returns
        -------
        dict
            ``streams``: per channel ``id``, ``state``, ``t_ms`` and ``p_pw``
            (min/max decimated, pW, None where flagged); ``spectrum``: per
            channel ``f_hz`` and ``log10_asd`` (ASD in aW/sqrt(Hz)), plus
            ``f_hwp_hz``, ``f_hwp_source`` and ``harmonics_hz``;
            ``newest_t_pub_ns``: publication time of the newest power chunk
            drawn; ``unknown``: ids not (yet) seen.
        """
        selection = list(selection)
        chosen = self.resolve(selection)
        unknown = [d for d in selection if d not in self._index]
        by_module: dict[tuple[int, int], list[tuple[int, str]]] = {}
        for det in chosen:
            key, row = self._index[det]
            by_module.setdefault(key, []).append((row, det))
        if f_hwp_hz == "config":
            f_hwp_hz = self.config.f_hwp_hz
        source = "configured" if f_hwp_hz is not None else "not found"
        estimates = []
        streams, spectra = {}, {}
        newest_pub = 0
        for key, members in by_module.items():
            buf = self.modules[key]
            newest_pub = max(newest_pub, buf.newest_t_pub_ns)
            rows = np.array([r for r, _ in members])
            t, p = buf.read(rows)
            td, pd = decimate_minmax(t, p, self.config.max_points)
            f, psd = welch_psd(p, buf.sample_rate_hz)
            if f.size:
                fb, pb = log_bin(f, psd, self.config.spectrum_points)
            if f_hwp_hz is None:  # finest resolution to locate the lines
                estimates.append(estimate_f_hwp(*welch_psd(p, buf.sample_rate_hz, segments=1)))
            for i, (row, det) in enumerate(members):
                streams[det] = {
                    "id": det,
                    "state": STATE_NAMES[int(buf.state[row])],
                    "t_ms": _round_list(td / 1e6, 0),
                    "p_pw": _round_list(pd[i] * 1e12, 7),
                }
                if f.size and np.all(np.isfinite(pb[i])) and np.all(pb[i] > 0):
                    spectra[det] = {"id": det, "f_hz": _sig_list(fb, 5), "log10_asd": _round_list(np.log10(np.sqrt(pb[i]) * 1e18), 4)}
        estimates = [e for e in estimates if e is not None]
        if f_hwp_hz is None and estimates:
            f_hwp_hz, source = float(np.median(estimates)), "estimated"
        return {
            "selection": chosen,
            "unknown": unknown,
            "streams": [streams[d] for d in chosen if d in streams],
            "spectrum": {
                "channels": [spectra[d] for d in chosen if d in spectra],
                "f_hwp_hz": f_hwp_hz,
                "f_hwp_source": source,
                "harmonics_hz": hwp_harmonics_hz(f_hwp_hz) if f_hwp_hz is not None else [],
            },
            "newest_t_pub_ns": int(newest_pub),
        }
