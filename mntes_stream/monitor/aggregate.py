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
from mntes_stream.core.lag import who_is_behind
from mntes_stream.core.sequence import StreamSequence
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError
from mntes_stream.monitor.analysis import (
    decimate_minmax,
    estimate_f_hwp,
    hwp_harmonics_hz,
    log_bin,
    welch_psd,
)
from mntes_stream.monitor.history import Ring, SlowRing
from mntes_stream.monitor.leakage_live import LiveLeakage
from mntes_stream.monitor.ledger_view import ShedWatch, ledger_view

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
# A TES that dropped out of the transition on the low side shows "superconducting", whichever bit says so
# (a LATCHED bit, where the flag set has one, as well as SUPERCONDUCTING).
_LOW_FLAGS = np.uint16(sum(bit for bit, name in fl.NAMES.items() if name in ("superconducting", "latched")))
_OTHER_FLAGS = np.uint16(sum(fl.NAMES) & ~(fl.SATURATED | _LOW_FLAGS))
_SCALAR_SENSORS = ("t_bath", "b_field")
_LATENCIES_KEPT = 10_000  # per tick interval: the latency figures' sample


@dataclass(frozen=True)
class MonitorConfig(Settings):
    """What the monitor keeps, how it reduces it, and its memory budget.

    Attributes
    ----------
    history_s : float
        Full-rate power kept for every channel (the default time-stream window
        and the spectrum's data), and housekeeping history.
    long_history_s : float
        History of the plotted channels at full rate, and of every channel as
        ``slow_bin_s`` means.
    slow_bin_s : float
        Bin of the downsampled long history of every channel.
    full_rate_channels : int
        Channels (the most recently plotted) kept at full rate for ``long_history_s``.
    max_rate_hz : float
        Rings hold ``window x max_rate_hz`` samples at most: they are sized
        from configuration, never from the rate a message claims (a faster
        stream keeps a shorter window).
    memory_mb : float
        Budget of every buffer; a new stream that does not fit evicts idle
        ones, else it is refused and counted (``over_budget``).
    max_services : int
        Service statuses kept (the stalest is evicted first).
    max_points : int
        Points per time-stream or housekeeping trace sent to the page.
    spectrum_points : int
        Log-spaced points per spectrum sent to the page.
    f_hwp_hz : float or None
        HWP rotation frequency whose 1f/2f/4f are marked; None estimates it
        from the spectra (:func:`~mntes_stream.monitor.analysis.estimate_f_hwp`).
    silent_s : float
        A module with no power chunk for this long shows its channels silent
        (and may be evicted for a new one).
    stale_chunks, stale_min_s : float
        No power for more than ``stale_chunks`` chunk intervals (at least
        ``stale_min_s``) makes the whole view stale.
    replay_after_s : float
        Power published longer than this before it arrives is a replay.
    lagging_after_s : float
        Power whose newest sample is older than this when it arrives is not
        live: a recording replayed through a converter, or a converter behind.
    shedding_recent_s : float
        A converter whose shed count grew this recently (or that holds chunks
        set aside) shows SHEDDING.
    max_ledger_streams : int
        Streams of each converter's ledger sent to the page (lossy ones first).
    flag_frac : float
        Fraction of a channel's samples (since the last tick) that must be
        saturated, superconducting or otherwise flagged for it to leave "transition".
    hk_stale_s : float
        Housekeeping (or a service status) not received for this long is stale.
    max_selected : int
        Channels one page may plot at once.
    latency_reports : int
        Page render reports kept for the latency figures.
    leakage_detectors, leakage_window_s, leakage_every_s
        The live 2f -> 4f leakage of the linear conversion against MNTES
        (``monitor/leakage_live.py``): how many detectors (the first in
        transition, layout order; 0: off), over what window, how often.
    """

    history_s: float = setting(30.0, "full-rate power kept per channel and plotted", unit="s", gt=0, le=3600)
    long_history_s: float = setting(3600.0, "history of plotted channels at full rate, of the rest downsampled",
                                    unit="s", gt=0, le=86400)
    slow_bin_s: float = setting(1.0, "bin of the downsampled history of every channel", unit="s", gt=0)
    full_rate_channels: int = setting(16, "plotted channels kept at full rate over long_history_s", ge=0, le=1024)
    max_rate_hz: float = setting(200.0, "rings hold window x this many samples at most (never sized from a "
                                 "claimed rate)", unit="Hz", gt=0, le=1e5)
    memory_mb: float = setting(768.0, "budget of every buffer: new streams beyond it evict idle ones or are refused",
                               unit="MB", gt=0)
    max_services: int = setting(64, "service statuses kept (the stalest evicted first)", ge=1)
    max_points: int = setting(1200, "points per time-stream or housekeeping trace sent to the page", ge=2)
    spectrum_points: int = setting(400, "log-spaced points per spectrum sent to the page", ge=2)
    f_hwp_hz: float | None = setting(0.77, "HWP frequency whose 1f/2f/4f are marked (absent: estimated)", unit="Hz",
                                     gt=0)
    silent_s: float = setting(3.0, "a module without data this long shows its channels silent", unit="s", gt=0)
    stale_chunks: float = setting(3.0, "no power for this many chunk intervals: the view is stale", gt=0)
    stale_min_s: float = setting(0.5, "the stale threshold is at least this", unit="s", ge=0)
    replay_after_s: float = setting(60.0, "power published longer than this before it arrives is a replay",
                                    unit="s", gt=0)
    lagging_after_s: float = setting(30.0, "power whose newest sample is older than this on arrival is not live "
                                     "(LAGGING: a replay through a converter, or a converter behind)", unit="s", gt=0)
    shedding_recent_s: float = setting(10.0, "a converter that shed chunks this recently, or holds chunks set "
                                       "aside, shows SHEDDING", unit="s", gt=0)
    max_ledger_streams: int = setting(256, "streams of each converter's ledger sent to the page (lossy ones first)",
                                      ge=1, le=100_000)
    flag_frac: float = setting(0.1, "share of a channel's samples flagged for it to leave 'transition'", gt=0, le=1)
    hk_stale_s: float = setting(2.0, "housekeeping or a service status not received this long is stale", unit="s",
                                gt=0)
    max_selected: int = setting(16, "channels one page may plot at once", ge=2)
    latency_reports: int = setting(600, "page render reports kept for the latency figures", ge=2)
    leakage_detectors: int = setting(8, "detectors whose linear-conversion leakage (2f -> 4f, against MNTES) is "
                                     "measured live: their modules' counts are subscribed (0: off)", ge=0, le=64)
    leakage_window_s: float = setting(60.0, "power window of the live leakage fit", unit="s", ge=10, le=300)
    leakage_every_s: float = setting(10.0, "period of the live leakage measurement", unit="s", ge=1, le=3600)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.full_rate_bytes() >= self.memory_mb * 1e6:
            raise ConfigError(f"memory_mb: {self.memory_mb} MB does not even hold the {self.full_rate_channels} "
                              f"full-rate channels ({self.full_rate_bytes() / 1e6:.0f} MB); raise it or lower "
                              "full_rate_channels, long_history_s or max_rate_hz")
        if self.full_rate_bytes() + self.leakage_bytes() >= self.memory_mb * 1e6:
            raise ConfigError(f"memory_mb: {self.memory_mb} MB does not hold the live leakage's rings too "
                              f"({self.leakage_bytes() / 1e6:.1f} MB); raise it or lower leakage_detectors or "
                              "leakage_window_s")

    def ring_samples(self, window_s: float, rate_hz: float) -> int:
        """Samples a ring over ``window_s`` holds: the window at the stream's rate, capped by ``max_rate_hz``."""
        return max(int(math.ceil(window_s * min(rate_hz, self.max_rate_hz))), 16)

    def leakage_bytes(self) -> int:
        """Bytes reserved for the live leakage: two float64 rings per measured detector."""
        return 2 * self.leakage_detectors * (self.ring_samples(self.leakage_window_s, self.max_rate_hz) * 16)

    def full_rate_bytes(self) -> int:
        """Bytes reserved for the full-rate long history of ``full_rate_channels``."""
        return self.full_rate_channels * Ring.max_nbytes(1, self.ring_samples(self.long_history_s, self.max_rate_hz))

    def module_bytes(self, n_ch: int) -> int:
        """Bytes reserved for one module of ``n_ch`` channels (rings at their cap, counters, ids)."""
        return (Ring.max_nbytes(n_ch, self.ring_samples(self.history_s, self.max_rate_hz))
                + SlowRing.max_nbytes(n_ch, self.slow_bin_s, self.long_history_s)
                + _MODULE_OVERHEAD_B + _CHANNEL_OVERHEAD_B * n_ch)


# Python objects around a module's arrays (sequence tracker, dicts, ids): measured order of magnitude.
_MODULE_OVERHEAD_B = 16_000
_CHANNEL_OVERHEAD_B = 200


class ModuleBuffer:
    """Full-rate power ring, downsampled long history and state counters of one ``(board, module)`` stream.

    Parameters
    ----------
    board, module : int
    channels : ndarray of int32, shape (n_ch,)
    sample_rate_hz : float
        As the chunks claim it: it sets the window, never the memory
        (see :meth:`MonitorConfig.ring_samples`).
    config : MonitorConfig
    """

    def __init__(self, board: int, module: int, channels: np.ndarray, sample_rate_hz: float, config: MonitorConfig):
        self.board = int(board)
        self.module = int(module)
        self.channels = np.asarray(channels, dtype=np.int32).copy()
        self.ids = tuple(detector_id(board, module, c) for c in self.channels.tolist())
        self.sample_rate_hz = float(sample_rate_hz)
        self.config = config
        n_ch = self.channels.size
        self.capacity = config.ring_samples(config.history_s, self.sample_rate_hz)
        self.ring = Ring(n_ch, self.capacity)
        self.slow = SlowRing(n_ch, config.slow_bin_s, config.long_history_s)
        self.watched: dict[int, Ring] = {}  # row -> full-rate long history of a plotted channel
        self.reserved_bytes = config.module_bytes(n_ch)
        self.newest_t_ns: int | None = None
        self.newest_t_pub_ns = 0
        self.last_recv_ns: int | None = None
        self._recv_times: collections.deque = collections.deque(maxlen=17)
        self._chunk_s = 0.1
        self.replay = False
        self.sequence = StreamSequence()
        self.late = 0
        self.late_power = 0  # power the converter marked late (converted after being set aside)
        self.lag_s: float | None = None  # newest sample to receipt, of the last live chunk
        self.restarts = 0
        self.state = np.full(n_ch, STATE_SILENT, dtype=np.uint8)
        # Focal-plane figures of the last tick with samples (NaN: none yet).
        self.power_w = np.full(n_ch, np.nan)
        self.flag_frac = np.full(n_ch, np.nan)
        self.noise_w_rthz = np.full(n_ch, np.nan)
        self._reset_counters()

    def _reset_counters(self) -> None:
        n_ch = self.channels.size
        self._n = 0
        self._n_sat = np.zeros(n_ch, dtype=np.int64)
        self._n_sc = np.zeros(n_ch, dtype=np.int64)
        self._n_other = np.zeros(n_ch, dtype=np.int64)
        self._n_flag = np.zeros(n_ch, dtype=np.int64)
        self._sum_p = np.zeros(n_ch)
        self._n_p = np.zeros(n_ch, dtype=np.int64)
        self._sum_d2 = np.zeros(n_ch)
        self._n_d2 = np.zeros(n_ch, dtype=np.int64)

    @property
    def capacity_bytes(self) -> int:
        """Bytes the buffers hold now (grows with the data received, up to :attr:`reserved_bytes`)."""
        return self.ring.nbytes + self.slow.nbytes + sum(r.nbytes for r in self.watched.values())

    def matches(self, channels: np.ndarray, sample_rate_hz: float) -> bool:
        return np.array_equal(channels, self.channels) and abs(sample_rate_hz - self.sample_rate_hz) <= 1e-6 * self.sample_rate_hz

    def chunk_interval_s(self) -> float:
        """Time between this stream's chunks: the mean receive gap of the last 16 (bursts average out),
        else one chunk's span."""
        if len(self._recv_times) >= 3:
            return max((self._recv_times[-1] - self._recv_times[0]) / (len(self._recv_times) - 1) / 1e9, 1e-4)
        return self._chunk_s

    def add(self, t_ns: np.ndarray, p_opt_w: np.ndarray, flags: np.ndarray, seq: int, t_pub_ns: int, t_recv_ns: int,
            late: bool = False) -> None:
        """Append one chunk: times (n,), power and flags (n_ch, n); ``late``: converted late (not a lag)."""
        if late:
            self.late_power += 1
        elif t_ns.size:
            self.lag_s = (int(t_recv_ns) - int(t_ns[-1])) / 1e9
        if self.last_recv_ns is None or t_recv_ns >= self.last_recv_ns:
            self._recv_times.append(int(t_recv_ns))
        self.last_recv_ns = int(t_recv_ns)
        self._chunk_s = min(max(t_ns.size / self.sample_rate_hz, 1e-3), 60.0)
        self.replay = t_recv_ns - t_pub_ns > self.config.replay_after_s * 1e9
        self.newest_t_pub_ns = max(self.newest_t_pub_ns, int(t_pub_ns))
        self.sequence.observe(seq, int(t_ns[0]) if t_ns.size else int(t_pub_ns))
        sat = (flags & fl.SATURATED) != 0
        sc = (flags & _LOW_FLAGS) != 0
        finite = np.isfinite(p_opt_w)
        other = ((flags & _OTHER_FLAGS) != 0) | (~finite & ~sat & ~sc)
        self._n += flags.shape[1]
        self._n_sat += sat.sum(axis=1)
        self._n_sc += sc.sum(axis=1)
        self._n_other += other.sum(axis=1)
        self._n_flag += ((flags != 0) | ~finite).sum(axis=1)
        self._sum_p += np.where(finite, p_opt_w, 0.0).sum(axis=1)
        self._n_p += finite.sum(axis=1)
        if p_opt_w.shape[1] > 1:
            d = np.diff(p_opt_w, axis=1)
            ok = np.isfinite(d)
            self._sum_d2 += np.square(np.where(ok, d, 0.0)).sum(axis=1)
            self._n_d2 += ok.sum(axis=1)
        n = t_ns.size
        if n == 0:
            return
        if self.newest_t_ns is not None and int(t_ns[0]) <= self.newest_t_ns:
            history_ns = self.capacity / self.sample_rate_hz * 1e9
            if int(t_ns[-1]) < self.newest_t_ns - history_ns:
                # Much older than anything held: a replay started over; start afresh.
                self.restarts += 1
                self.ring.clear()
                self.slow.clear()
                for ring in self.watched.values():
                    ring.clear()
            else:
                self.late += 1  # counted in the state, not drawn: the rings stay time-ordered
                return
        self.ring.append(t_ns, p_opt_w)
        self.slow.add(t_ns, p_opt_w)
        for row, ring in self.watched.items():
            ring.append(t_ns, p_opt_w[row:row + 1])
        self.newest_t_ns = int(t_ns[-1])

    def classify(self, now_ns: int, config: MonitorConfig) -> None:
        """Set :attr:`state` and the focal-plane figures from the counters since the last call, then reset them."""
        if self.last_recv_ns is None or now_ns - self.last_recv_ns > config.silent_s * 1e9:
            self.state[:] = STATE_SILENT
        elif self._n > 0:
            counts = np.stack([self._n_sat, self._n_sc, self._n_other])  # (3, n_ch)
            worst = np.argmax(counts, axis=0)  # ties go to the first: saturated, superconducting, flagged
            codes = np.array([STATE_SATURATED, STATE_SUPERCONDUCTING, STATE_FLAGGED], dtype=np.uint8)
            state = codes[worst]
            state[counts.max(axis=0) < config.flag_frac * self._n] = STATE_TRANSITION
            self.state = state
        if self._n > 0:
            with np.errstate(invalid="ignore", divide="ignore"):
                self.power_w = np.where(self._n_p > 0, self._sum_p / np.maximum(self._n_p, 1), np.nan)
                self.flag_frac = self._n_flag / self._n
                # White-noise ASD from sample differences: var(d) = 2 sigma^2, one-sided PSD = 2 sigma^2 / fs.
                sigma2 = np.where(self._n_d2 > 0, self._sum_d2 / np.maximum(self._n_d2, 1) / 2, np.nan)
                self.noise_w_rthz = np.sqrt(2 * sigma2 / self.sample_rate_hz)
        self._reset_counters()

    def read(self, rows: np.ndarray, since_ns: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Samples held for ``rows``, oldest first: times (m,), power float64 (len(rows), m)."""
        return self.ring.read(rows, since_ns)

    def watch(self, row: int) -> None:
        """Keep ``row`` at full rate over ``long_history_s``, starting from what the short ring holds."""
        if row in self.watched:
            return
        ring = Ring(1, self.config.ring_samples(self.config.long_history_s, self.sample_rate_hz))
        t, p = self.ring.read(np.array([row]))
        ring.append(t, p)
        self.watched[row] = ring

    def unwatch(self, row: int) -> None:
        self.watched.pop(row, None)


def _round_list(a: np.ndarray, decimals: int) -> list:
    """JSON-ready list: rounded, non-finite -> None (JSON has no NaN)."""
    a = np.round(np.asarray(a, dtype=np.float64), decimals)
    out = a.tolist()
    if not np.all(np.isfinite(a)):
        out = [v if math.isfinite(v) else None for v in out]
    return out


def _sig_list(a: np.ndarray, digits: int = 4) -> list:
    """JSON-ready list rounded to ``digits`` significant digits; non-finite -> None.

    Vectorised (a tick rounds every channel's figures); the shortest decimal is exact while
    ``10**k`` is (``|a|`` above about ``1e-22 * 10**digits``), within an ulp below.
    """
    a = np.asarray(a, dtype=np.float64).ravel()
    finite = np.isfinite(a)
    with np.errstate(divide="ignore", invalid="ignore"):
        # Decimal exponent of the last kept digit; integer / 10**k is correctly rounded, so the JSON is short.
        k = digits - 1 - np.floor(np.log10(np.abs(np.where(finite & (a != 0), a, 1.0)))).astype(np.int64)
        k = np.clip(k, -300, 300)
        up = k >= 0
        scale = 10.0 ** np.abs(k)
        r = np.where(up, np.round(a * np.where(up, scale, 1.0)) / np.where(up, scale, 1.0),
                     np.round(a / np.where(up, 1.0, scale)) * np.where(up, 1.0, scale))
    if finite.all():
        return r.tolist()
    out = r.astype(object)
    out[~finite] = None
    return out.tolist()


class _HkHistory:
    """Readings of one scalar sensor over the last ``history_s`` (data clock)."""

    def __init__(self, history_s: float, max_n: int):
        self.history_ns = int(history_s * 1e9)
        self.max_n = int(max_n)
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
            self.t, self.v = self.t[keep][-self.max_n:], self.v[keep][-self.max_n:]


class Aggregator:
    """Everything the monitor knows, reduced on demand for the page and the text table.

    Feed it with :meth:`add_power`, :meth:`add_hk`, :meth:`add_status`
    (decoded message objects, duck-typed) and :meth:`add_bad`; call
    :meth:`tick` on the update cadence (it classifies the channels and
    returns the parts every page shares), :meth:`view` for one page's
    selected channels. Not thread-safe: the caller holds a lock.
    """

    def __init__(self, config: MonitorConfig | None = None, positions: dict | None = None):
        self.config = config or MonitorConfig()
        self.positions: dict[str, tuple[float, float]] = dict(positions or {})
        self.modules: collections.OrderedDict[tuple[int, int], ModuleBuffer] = collections.OrderedDict()  # by receipt
        self.reserved_bytes = 0
        self.budget_bytes = int(self.config.memory_mb * 1e6) - self.config.full_rate_bytes() - self.config.leakage_bytes()
        self.over_budget = 0
        self.evicted = 0
        self.services_evicted = 0
        self._watched: collections.OrderedDict = collections.OrderedDict()  # det id -> None, oldest first
        self._index: dict[str, tuple[tuple[int, int], int]] = {}
        self.layout_version = 0
        self._layout_cache: tuple[int, list] | None = None
        hk_max = self.config.ring_samples(self.config.history_s, self.config.max_rate_hz)
        self.hk: dict[str, _HkHistory] = {s: _HkHistory(self.config.history_s, hk_max) for s in _SCALAR_SENSORS}
        self.bias_readings = 0
        self.statuses: dict[str, tuple] = {}  # service -> (status, t_recv_ns, input rate or None)
        self._ledgers: dict[str, dict | None] = {}  # service -> its status's ledger as the page shows it
        self._shed_watch = ShedWatch()
        self.bad_messages: collections.Counter = collections.Counter()
        self.dropped = 0
        self.power_chunks = 0
        self.power_samples = 0
        self._interval_chunks = 0
        self._interval_samples = 0
        self._interval_latency_ms: collections.deque = collections.deque(maxlen=_LATENCIES_KEPT)
        self._last_tick_ns: int | None = None
        self._renders: collections.deque = collections.deque(maxlen=self.config.latency_reports)
        c = self.config
        self.leakage = LiveLeakage(c.leakage_detectors, c.leakage_window_s, c.leakage_every_s, c.max_rate_hz)

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
            buf = self._admit(key, chunk.channels, rate, int(t_recv_ns))
            if buf is None:
                return
        ids = getattr(chunk, "detector_ids", None)
        if ids and len(ids) == len(buf.ids) and ids != buf.ids:  # the source's names (dfmux-bridge: the boards')
            buf.ids = tuple(ids)
        late = bool(getattr(chunk, "late", None))
        buf.add(t_ns, chunk.p_opt_w, chunk.flags, int(chunk.seq), int(chunk.t_pub_ns), t_recv_ns, late)
        if key in self.leakage.module_keys:  # a set lookup per chunk: most modules have no measured detector
            self.leakage.add("mntes", buf.ids, t_ns, chunk.p_opt_w)
        self.modules.move_to_end(key)
        self.power_chunks += 1
        self.power_samples += int(chunk.p_opt_w.size)
        self._interval_chunks += 1
        self._interval_samples += int(chunk.p_opt_w.size)
        if late:  # converted after being set aside: its delay is the overload's, counted as late, not latency
            pass
        elif buf.replay:  # the recording's own clock: its samples' end to its publication
            if t_ns.size:
                self._interval_latency_ms.append((int(chunk.t_pub_ns) - int(t_ns[-1])) / 1e6)
        else:
            self._interval_latency_ms.append((int(t_recv_ns) - int(chunk.t_pub_ns)) / 1e6)

    def _admit(self, key: tuple[int, int], channels: np.ndarray, rate_hz: float, t_recv_ns: int) -> ModuleBuffer | None:
        """A new buffer for ``key`` if its reservation fits the budget (evicting idle modules), else None (counted)."""
        old = self.modules.get(key)
        if old is not None:
            self._drop(key)
        need = self.config.module_bytes(int(np.asarray(channels).size))
        idle_ns = t_recv_ns - int(self.config.silent_s * 1e9)
        # self.modules is in order of last receipt: the idle ones are at the front.
        while self.reserved_bytes + need > self.budget_bytes and self.modules:
            k, b = next(iter(self.modules.items()))
            if (b.last_recv_ns or 0) >= idle_ns:
                break
            self._drop(k)
            self.evicted += 1
        if self.reserved_bytes + need > self.budget_bytes:
            self.over_budget += 1
            return None
        buf = ModuleBuffer(key[0], key[1], channels, rate_hz, self.config)
        self.modules[key] = buf
        self.reserved_bytes += need
        for row, det in enumerate(buf.ids):
            self._index[det] = (key, row)
        self.layout_version += 1
        for det in self._watched:  # a replaced module keeps its plotted channels at full rate
            where = self._index.get(det)
            if where is not None and where[0] == key:
                buf.watch(where[1])
        return buf

    def watch(self, selection: Iterable[str]) -> None:
        """The channels a page plots: kept at full rate over ``long_history_s`` (the most recent
        ``full_rate_channels`` of them; older ones fall back to the downsampled history)."""
        for det in self.resolve(selection):
            if det in self._watched:
                self._watched.move_to_end(det)
                continue
            self._watched[det] = None
            key, row = self._index[det]
            if self.config.full_rate_channels > 0:
                self.modules[key].watch(row)
        while len(self._watched) > self.config.full_rate_channels:
            det, _ = self._watched.popitem(last=False)
            where = self._index.get(det)
            if where is not None:
                self.modules[where[0]].unwatch(where[1])

    def memory(self) -> dict:
        """What the buffers hold and reserve, in bytes, and what the budget refused."""
        return {
            "held_bytes": int(sum(b.capacity_bytes for b in self.modules.values())),
            "reserved_bytes": int(self.reserved_bytes + self.config.full_rate_bytes() + self.config.leakage_bytes()),
            "budget_bytes": int(self.config.memory_mb * 1e6),
            "over_budget": self.over_budget,
            "evicted": self.evicted,
            "services_evicted": self.services_evicted,
            "full_rate_channels": sorted(self._watched),
        }

    def add_linear(self, chunk) -> None:
        """A power chunk of the linear shadow (``monitor/shadow.py``): the linear baseline of the same counts."""
        ids = [detector_id(chunk.board, chunk.module, c) for c in np.asarray(chunk.channels).tolist()]
        self.leakage.add("linear", ids, chunk.times_ns(), chunk.p_opt_w)

    def add_hk(self, chunk, t_recv_ns: int) -> None:
        """One :class:`~mntes_stream.io.messages.HousekeepingChunk`."""
        if chunk.sensor in self.hk:
            self.hk[chunk.sensor].add(chunk.t_ns, chunk.value, chunk.unit, t_recv_ns)
        elif chunk.sensor == "bias":  # readout_flags show on the samples they flag (the power's flags)
            self.bias_readings += int(chunk.t_ns.size)

    def add_status(self, status, t_recv_ns: int) -> None:
        """One :class:`~mntes_stream.io.messages.StatusMessage`; the input rate comes from consecutive ones."""
        prev = self.statuses.get(status.service)
        rate = None
        if prev is not None and status.t_ns > prev[0].t_ns:
            dn = status.chunks_received - prev[0].chunks_received
            if dn >= 0:
                rate = dn / ((status.t_ns - prev[0].t_ns) / 1e9)
        if prev is None and len(self.statuses) >= self.config.max_services:
            stalest = min(self.statuses, key=lambda s: self.statuses[s][1])
            del self.statuses[stalest]
            self._ledgers.pop(stalest, None)
            self._shed_watch.forget(stalest)
            self.services_evicted += 1
        self.statuses[status.service] = (status, int(t_recv_ns), rate)
        # Reduced once per status, not per tick: a ledger may list thousands of streams.
        self._ledgers[status.service] = ledger_view(getattr(status, "ledger", None) or {},
                                                    self.config.max_ledger_streams,
                                                    getattr(status, "began_at", None) or {},
                                                    getattr(status, "conflicts", None) or {})
        self._shed_watch.observe(status.service, int(getattr(status, "chunks_shed", 0) or 0), int(t_recv_ns))

    def add_bad(self, reason: str) -> None:
        """A message that could not be decoded (counted and shown, never raised)."""
        self.bad_messages[reason] += 1

    def report_render(self, t_pub_ns: int, t_render_ns: int) -> None:
        """The page drew data whose newest power chunk was published at ``t_pub_ns``."""
        self._renders.append((int(t_pub_ns), int(t_render_ns)))

    # ------------------------------------------------------------------ layout

    def _drop(self, key: tuple[int, int]) -> None:
        buf = self.modules.pop(key)
        self.reserved_bytes -= buf.reserved_bytes
        for det in buf.ids:
            self._index.pop(det, None)
        self.layout_version += 1

    def layout(self) -> list[dict]:
        """The grid's rows: one per module, sorted, with its channel numbers."""
        if self._layout_cache is None or self._layout_cache[0] != self.layout_version:
            rows = []
            for b, m in sorted(self.modules):
                buf = self.modules[(b, m)]
                row = {"board": b, "module": m, "channels": buf.channels.tolist()}
                if self.positions:  # sky position [x, y] in degrees where the parameter file gives one
                    row["positions"] = [list(self.positions[d]) if d in self.positions else None for d in buf.ids]
                rows.append(row)
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
        return sorted(self._index)

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

    def _in_transition(self) -> list[str]:
        """Channels in transition, in layout order (module by module)."""
        out = []
        for key in sorted(self.modules):
            buf = self.modules[key]
            out.extend(buf.ids[r] for r in np.flatnonzero(buf.state == STATE_TRANSITION).tolist())
        return out

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

    def selection_settled(self, picks: list[str], n: int = 3) -> bool:
        """Whether a page may keep :meth:`default_selection`'s ``picks``: ``n`` channels, all in transition.

        A first classification can rest on a few samples, or come before some
        modules are heard; a default fixed then could hold a saturated or
        silent channel for good, so it is taken again until it settles.
        """
        return len(picks) >= n and all(self.state_of(d) == STATE_NAMES[STATE_TRANSITION] for d in picks)

    # ------------------------------------------------------------------ output

    def tick(self, now_ns: int) -> dict:
        """Classify every channel and build the parts all pages share (JSON-ready dict).

        Returns
        -------
        dict
            ``t_ns``, ``layout_version``, ``codes`` (one digit per channel in
            :meth:`layout` order, an index into ``state_names``),
            ``state_counts``, ``hk`` (decimated history per sensor),
            ``health``, ``freshness`` (:meth:`freshness`), ``focal`` (per
            channel in layout order: ``power_pw``, ``flag_pct``,
            ``noise_aw_rthz``, ``linear_nl_per_pw``, None where unknown), ``memory``,
            ``leakage`` (the live leakage: ``leakage_live.LiveLeakage.evaluate``).
        """
        now_ns = int(now_ns)
        for buf in self.modules.values():
            buf.classify(now_ns, self.config)
        states = self.states()
        if not self.leakage.chosen:
            self.leakage.choose(self._in_transition())  # measured by the subscriber, outside the lock
        interval_s = (now_ns - self._last_tick_ns) / 1e9 if self._last_tick_ns is not None else 0.0
        out = {
            "t_ns": now_ns,
            "layout_version": self.layout_version,
            "state_names": list(STATE_NAMES),
            "codes": (states + ord("0")).astype(np.uint8).tobytes().decode("ascii"),
            "state_counts": {name: int(np.count_nonzero(states == i)) for i, name in enumerate(STATE_NAMES)},
            "hk": self._hk_view(),
            "health": self._health(now_ns, interval_s),
            "freshness": self.freshness(now_ns),
            "focal": self._focal(),
            "memory": self.memory(),
            "leakage": self.leakage.last,
        }
        self._interval_chunks = 0
        self._interval_samples = 0
        self._interval_latency_ms.clear()
        self._last_tick_ns = now_ns
        return out

    def freshness(self, now_ns: int) -> dict:
        """Is the view live? Age of the newest power against ``stale_chunks`` chunk intervals.

        Returns
        -------
        dict
            ``state``: "waiting" (no power yet), "live", "stale",
            "replay" (live, but the data were published long before, see
            ``replay_after_s``), "lagging" (live, but the newest sample was
            older than ``lagging_after_s`` on arrival: a recording replayed
            through a converter, or a converter behind) or "shedding" (a
            converter holds chunks set aside or shed some within
            ``shedding_recent_s``; any state but stale); ``age_s`` of the
            newest power chunk (receive clock), ``threshold_s``,
            ``chunk_interval_s``, ``newest_t_ns`` (sample time of the newest
            data: the recording's clock in a replay), ``lag_s`` (newest sample
            to receipt), ``shedding`` (``services``, ``shed``, ``set_aside``),
            ``behind`` (which process holds a converter's latency, in words;
            "" when none is behind: ``core.lag``).
        """
        shedding = [x for x in (self._shedding(name, now_ns) for name in self.statuses) if x["shedding"]]
        shed = {"services": [x["service"] for x in shedding], "shed": int(sum(x["chunks_shed"] for x in shedding)),
                "set_aside": int(sum(x["chunks_set_aside"] for x in shedding))}
        # Which process holds the latency, from each converter's split of it (core.lag): not always the converter.
        behind = "; ".join(f"{name}: {who}" for name, (s, _, _) in sorted(self.statuses.items())
                           if (who := who_is_behind(s.latency_p99_ms, getattr(s, "arrival_p99_ms", None))))
        bufs = [b for b in self.modules.values() if b.last_recv_ns is not None]
        if not bufs:
            return {"state": "shedding" if shedding else "waiting", "age_s": None, "threshold_s": None,
                    "chunk_interval_s": None, "newest_t_ns": None, "replay": False,
                    "stale_chunks": self.config.stale_chunks, "lag_s": None,
                    "lagging_after_s": self.config.lagging_after_s, "shedding": shed, "behind": behind}
        newest = max(bufs, key=lambda b: b.last_recv_ns)
        recent = [b for b in bufs if newest.last_recv_ns - b.last_recv_ns <= self.config.silent_s * 1e9]
        interval = float(np.median([b.chunk_interval_s() for b in recent]))
        threshold = max(self.config.stale_chunks * interval, self.config.stale_min_s)
        age = max(int(now_ns) - newest.last_recv_ns, 0) / 1e9
        lags = [b.lag_s for b in recent if b.lag_s is not None]
        lag = float(np.median(lags)) if lags else None
        state = "stale" if age > threshold else ("replay" if newest.replay else "live")
        if state == "live" and lag is not None and lag > self.config.lagging_after_s:
            state = "lagging"
        if state != "stale" and shedding:  # no data at all is worse; otherwise shedding is what to know first
            state = "shedding"
        return {"state": state, "age_s": age, "threshold_s": threshold, "chunk_interval_s": interval,
                "newest_t_ns": newest.newest_t_ns, "replay": bool(newest.replay), "stale_chunks": self.config.stale_chunks,
                "lag_s": lag, "lagging_after_s": self.config.lagging_after_s, "shedding": shed, "behind": behind}

    def _shedding(self, name: str, now_ns: int) -> dict:
        """One service's ledger as the page shows it, and whether it is shedding now."""
        s, t_recv, _ = self.statuses[name]
        set_aside = int(getattr(s, "chunks_set_aside", 0) or 0)
        age = (now_ns - t_recv) / 1e9
        fresh = age <= max(self.config.hk_stale_s, 3 * s.interval_s)  # a silent converter sets nothing aside now
        recent = self._shed_watch.shed_recently(name, now_ns, self.config.shedding_recent_s)
        return {"service": name, "chunks_shed": int(getattr(s, "chunks_shed", 0) or 0),
                "chunks_late": int(getattr(s, "chunks_late", 0) or 0),
                "chunks_rejected": int(getattr(s, "chunks_rejected", 0) or 0),
                "chunks_missing": int(getattr(s, "chunks_missing", 0) or 0),
                "chunks_set_aside": set_aside,
                "shedding": bool(fresh and (set_aside > 0 or recent)),
                "ledger": self._ledgers.get(name)}

    def _focal(self) -> dict:
        parts = [self.modules[k] for k in sorted(self.modules)]

        def cat(name):
            return np.concatenate([getattr(b, name) for b in parts]) if parts else np.zeros(0)

        leak = self.leakage.focal()
        nl = [leak.get(d) for b in parts for d in b.ids] if leak else [None] * sum(b.channels.size for b in parts)
        return {"power_pw": _sig_list(cat("power_w") * 1e12), "flag_pct": _sig_list(cat("flag_frac") * 100, 3),
                "noise_aw_rthz": _sig_list(cat("noise_w_rthz") * 1e18, 3), "linear_nl_per_pw": nl}

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
                **self._shedding(name, now_ns),
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
                "late_power_chunks": int(sum(b.late_power for b in mods)),
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

    @staticmethod
    def _window(t: np.ndarray, p: np.ndarray, window_s: float | None) -> tuple[np.ndarray, np.ndarray]:
        """The last ``window_s`` of ``t`` (m,), ``p`` (rows, m)."""
        if window_s is None or t.size == 0:
            return t, p
        keep = t >= t[-1] - int(window_s * 1e9)
        return t[keep], p[:, keep]

    def resolve(self, selection: Iterable[str]) -> list[str]:
        """The known detector ids of ``selection``, in order, at most ``max_selected``."""
        out = []
        for det in selection:
            if det in self._index and det not in out:
                out.append(det)
        return out[: self.config.max_selected]

    def view(self, selection: Iterable[str], f_hwp_hz: float | None | str = "config", window_s: float | None = None) -> dict:
        """Time streams and spectra of the selected channels (JSON-ready dict).

        Parameters
        ----------
        selection : iterable of str
            Detector ids; unknown ones are skipped (see ``unknown`` in the result).
        f_hwp_hz : float, None or "config"
            Harmonics to mark: a frequency, None to estimate from these
            spectra, "config" for :attr:`MonitorConfig.f_hwp_hz`.
        window_s : float, optional
            Time-stream window (default ``history_s``). Beyond ``history_s``
            a channel comes from its full-rate long history if it has one
            (:meth:`watch`), else from the downsampled one; the spectrum
            always uses the last ``history_s`` at full rate.

        Returns
        -------
        dict
            ``streams``: per channel ``id``, ``state``, ``t_ms`` and ``p_pw``
            (min/max decimated, pW, None where flagged), ``resolution``
            ("full rate" or the bin of the means); ``spectrum``: per
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
            td, pd = decimate_minmax(*self._window(t, p, window_s), self.config.max_points)
            f, psd = welch_psd(p, buf.sample_rate_hz)
            if f.size:
                fb, pb = log_bin(f, psd, self.config.spectrum_points)
            if f_hwp_hz is None:  # finest resolution to locate the lines
                estimates.append(estimate_f_hwp(*welch_psd(p, buf.sample_rate_hz, segments=1)))
            for i, (row, det) in enumerate(members):
                t_i, p_i, resolution = td, pd[i], "full rate"
                if window_s is not None and window_s > self.config.history_s:
                    since = None if buf.newest_t_ns is None else buf.newest_t_ns - int(window_s * 1e9)
                    if row in buf.watched:
                        t_l, p_l = buf.watched[row].read(since_ns=since)
                    else:
                        t_l, p_l = buf.slow.read(np.array([row]), since)
                        resolution = f"{self.config.slow_bin_s:g} s means"
                    t_i, p_l = decimate_minmax(*self._window(t_l, p_l, window_s), self.config.max_points)
                    p_i = p_l[0]
                streams[det] = {
                    "id": det,
                    "state": STATE_NAMES[int(buf.state[row])],
                    "resolution": resolution,
                    "t_ms": _round_list(t_i / 1e6, 0),
                    "p_pw": _round_list(p_i * 1e12, 7),
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
