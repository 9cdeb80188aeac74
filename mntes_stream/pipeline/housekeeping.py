"""The converter's housekeeping state: sensor histories, per-module bias, the data clock.

Free of zenoh like the pipeline that owns it. Readings are kept relative to
the *data clock*: the receive clock minus the median over streams of each
stream's latest delay (receive time minus ``t_pub_ns``), so a replayed old
recording is judged by its own time and one stream, whatever its
``t_pub_ns``, has one vote. Readings outside physical acceptance ranges
(non-finite ones, and a bias or bath temperature not above zero, which no
converter can use, included) and oversized messages are rejected at the door
and counted, never held: the last good reading stays in force, so one bad
reading cannot poison a module until the next good one.
"""

from __future__ import annotations

import collections
import math
import statistics

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core.align import HkSeries
from mntes_stream.core.ids import parse_detector_id
from mntes_stream.errors import ConfigError
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk
from mntes_stream.pipeline.config import SCALAR_SENSORS, PipelineConfig

__all__ = ["DelayFloor", "Housekeeping", "known_modules", "ns"]

_INT64_MIN, _INT64_MAX = -(1 << 63), (1 << 63) - 1
_ENV_CACHE = 1024  # aligned (times, sensor) results kept: every module of a step shares its times
# The converters need these above zero (log of the bath temperature, R from V / I): 0 K or 0 V is a
# failed read or a switched-off supply, never an operating point, whatever the acceptance range says.
_POSITIVE = frozenset({"t_bath", "bias"})
_FLAG_BITS = int(sum(fl.NAMES))  # every bit flags.v1 defines


def ns(seconds: float) -> int | float:
    """Seconds to integer ns; infinity stays infinite (a disabled limit)."""
    return math.inf if math.isinf(seconds) else int(round(seconds * 1e9))


def known_modules(detector_ids) -> frozenset[tuple[int, int]] | None:
    """``(board, module)`` of every ``b<B>m<M>c<C>`` id; None when some id is not of that form (then any module)."""
    out = set()
    for d in detector_ids:
        try:
            b, m, _ = parse_detector_id(d)
        except ConfigError:
            return None
        out.add((b, m))
    return frozenset(out)


class DelayFloor:
    """The smallest receive delay of one stream over the last ``window_ns`` of its data time.

    A chunk's delay above this floor is how far it is behind its own stream's
    pace: zero in steady state (whatever the clock offset or a replay's age),
    growing when the converter falls behind. A sliding-window minimum
    (monotone queue): O(1) amortised per chunk, at most ``max_entries`` kept.
    """

    __slots__ = ("_q", "window_ns", "max_entries")

    def __init__(self, window_ns: int = 60 * 10**9, max_entries: int = 4096):
        self._q: collections.deque[tuple[int, int]] = collections.deque()
        self.window_ns = int(window_ns)
        self.max_entries = int(max_entries)

    def add(self, t_ns: int, delay_ns: int) -> int:
        """Book one chunk (its first sample time and delay); returns the floor including it."""
        q = self._q
        while q and q[-1][1] >= delay_ns:
            q.pop()
        q.append((t_ns, delay_ns))
        while q[0][0] < t_ns - self.window_ns or len(q) > self.max_entries:
            q.popleft()
        return q[0][1]


class Housekeeping:
    """Sensor histories and bias per module, aligned on request to a chunk's sample times.

    Parameters
    ----------
    config : PipelineConfig
    nominal_bias_v : dict of str to float
        Bias per detector id, used before any bias reading of its module.
    modules : set of (board, module), optional
        The modules whose bias is kept (the ones the parameters know); None: any.
    """

    def __init__(self, config: PipelineConfig, nominal_bias_v: dict[str, float], modules=None):
        self.config = config
        self._nominal_bias_v = nominal_bias_v
        self._modules = modules
        self._accept = {"t_bath": config.t_bath_accept_k, "b_field": config.b_field_accept_t,
                        "bias": config.bias_accept_v, "readout_flags": (0, _FLAG_BITS)}
        self._staleness_ns = ns(config.hk_staleness_s)
        self._bias_staleness_ns = ns(config.bias_staleness_s)
        self._retention_ns = ns(config.hk_retention_s)
        self._ahead_ns = ns(config.hk_max_ahead_s)
        self.sensors: dict[str, HkSeries] = {s: HkSeries(None, self._retention_ns) for s in SCALAR_SENSORS}
        self._bias: dict[tuple[int, int], tuple[np.ndarray, HkSeries]] = {}
        # (board, module) -> (channels, times list, values list of uint16 (n_ch,)): readout flags, a step
        self._readout: dict[tuple[int, int], tuple[np.ndarray, list, list]] = {}
        self._delays: dict[tuple[int, int], int] = {}  # latest receive minus t_pub_ns per counts stream
        self._offset_ns: int | None = None  # median of _delays, refreshed when a reading arrives
        self._env_cache: dict[tuple, tuple] = {}
        self._bias_cols: dict[tuple, tuple] = {}  # (board, module, channel bytes) -> (bias channels, rows)
        self._bracket_key: tuple | None = None  # versions of the required series when _bracket_ns was read
        self._bracket_ns: int | None = None  # their oldest newest reading (None: one has none)

    def note_delay(self, stream: tuple[int, int], delay_ns: int) -> None:
        """One counts chunk's receive time minus its ``t_pub_ns`` (sets the data clock)."""
        self._delays[stream] = int(delay_ns)
        self._offset_ns = None

    def data_clock(self, t_recv_ns: int) -> int:
        """Receive clock minus the median over streams of their latest delay (none yet: the receive clock)."""
        if self._offset_ns is None:
            self._offset_ns = int(statistics.median_low(self._delays.values())) if self._delays else 0
        return t_recv_ns - self._offset_ns

    def add(self, hk: HousekeepingChunk, t_recv_ns: int) -> list[tuple[str, str]]:
        """Keep a chunk's readings; returns ``(reason, detail)`` of each kind of reading dropped (none: []).

        Rejected whole: more than ``max_hk_readings`` readings (``too_large``),
        bias or readout flags of a module the parameters do not know (``unknown_stream``).
        Rejected (``hk_range``): readings that are not finite, outside the
        sensor's acceptance range, or (bias, bath temperature) not above zero;
        a bias row is rejected when any of its channels is. Dropped
        (``hk_time``): readings stamped more than ``hk_max_ahead_s`` ahead of
        the data clock, or (bias excepted: a setting holds) more than
        ``hk_retention_s`` behind it once the data clock is known. A rejected
        reading never reaches the history: the last good one holds.
        """
        cfg = self.config
        if hk.t_ns.size > cfg.max_hk_readings:
            return [("too_large", f"{hk.t_ns.size} readings in one message (at most {cfg.max_hk_readings})")]
        if hk.channels is not None and self._modules is not None and (hk.board, hk.module) not in self._modules:
            return [("unknown_stream", f"{hk.sensor} of board {hk.board} module {hk.module}: not in the parameters")]
        now = self.data_clock(t_recv_ns)
        t_ns, value = hk.t_ns, hk.value
        lo_v, hi_v = self._accept[hk.sensor]
        positive = hk.sensor in _POSITIVE
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(value) & (value >= lo_v) & (value <= hi_v)
            if positive:
                ok &= value > 0
            if hk.sensor == "readout_flags":  # whole flags.v1 bits only
                ok &= (value == np.round(value)) & ((np.nan_to_num(value).astype(np.int64) & ~_FLAG_BITS) == 0)
        good = ok if ok.ndim == 1 else ok.all(axis=1)
        problems = []
        if not good.all():
            example = float(value[~ok][0])
            accepted = f"finite, in [{lo_v:g}, {hi_v:g}]" + (" and > 0" if positive else "")
            problems.append(("hk_range", f"{int((~good).sum())} {hk.sensor} reading(s) rejected (e.g. {example:g}; "
                                         f"accepted: {accepted}): the last good reading holds"))
            t_ns, value = t_ns[good], value[good]
        return problems + self._keep(hk, t_ns, value, now)

    def _keep(self, hk: HousekeepingChunk, t_ns: np.ndarray, value: np.ndarray, now: int) -> list[tuple[str, str]]:
        held = hk.channels is not None  # a setting or a state holds: bias and readout flags are never too old
        lo = now - self._retention_ns if self._delays and not held else _INT64_MIN
        ok = (t_ns >= max(lo, _INT64_MIN)) & (t_ns <= min(now + self._ahead_ns, _INT64_MAX))
        problem = []
        if not ok.all():
            bad = t_ns[~ok]
            problem = [("hk_time", f"{bad.size} reading(s) stamped {(int(bad[0]) - now) / 1e9:+.4g} s from the data "
                        f"clock (accepted: -{self.config.hk_retention_s:g} s to +{self.config.hk_max_ahead_s:g} s)")]
            t_ns, value = t_ns[ok], value[ok]
        if t_ns.size == 0:  # nothing left: above all, a bias history is not reset by a message it never uses
            return problem
        if hk.sensor == "readout_flags":
            self._keep_readout(hk, t_ns, value, now)
        elif hk.sensor == "bias":
            module = (hk.board, hk.module)
            entry = self._bias.get(module)
            if entry is None or not np.array_equal(entry[0], hk.channels):
                # A new channel list starts a new history: columns must line up.
                entry = (hk.channels.copy(), HkSeries(hk.channels.size, self._retention_ns))
                self._bias[module] = entry
            entry[1].add(t_ns, value, now_ns=now)
        else:
            self.sensors[hk.sensor].add(t_ns, value, now_ns=now)
        return problem

    def _keep_readout(self, hk: HousekeepingChunk, t_ns: np.ndarray, value: np.ndarray, now: int) -> None:
        module = (hk.board, hk.module)
        entry = self._readout.get(module)
        if entry is None or not np.array_equal(entry[0], hk.channels):
            entry = self._readout[module] = (hk.channels.copy(), [], [])
        _, times, values = entry
        for tk, row in zip(t_ns.tolist(), value.astype(np.uint16)):
            k = int(np.searchsorted(np.asarray(times, dtype=np.int64), tk))
            if k < len(times) and times[k] == tk:
                values[k] = row
            else:
                times.insert(k, tk)
                values.insert(k, row)
        # Bounded: readings older than the retention behind the data clock go, but the one in force then.
        cut = int(np.searchsorted(np.asarray(times, dtype=np.int64), now - self._retention_ns, side="right")) - 1
        if cut > 0:
            del times[:cut], values[:cut]

    def readout_flags(self, chunk: CountsChunk, t: np.ndarray) -> np.ndarray | None:
        """The board's readout flags in force at each sample, shape (n_ch, n_samp) uint16; None: none read.

        Before the module's first reading, and on a channel the readings do not list, no bits."""
        entry = self._readout.get((chunk.board, chunk.module))
        if entry is None or not entry[1]:
            return None
        channels, times, values = entry
        idx = np.searchsorted(np.asarray(times, dtype=np.int64), t, side="right") - 1
        table = np.vstack([np.zeros((1, channels.size), dtype=np.uint16), np.stack(values)])  # row 0: before any
        col = {int(c): j for j, c in enumerate(channels.tolist())}
        cols = np.array([col.get(int(c), -1) for c in chunk.channels.tolist()], dtype=np.intp)
        out = table[idx + 1][:, np.clip(cols, 0, None)].T.astype(fl.FLAG_DTYPE)
        out[cols < 0] = 0
        return out

    def nominal_bias(self, ids, n_samp: int) -> np.ndarray:
        """Each detector's nominal bias (NaN without parameters) at every sample, shape (n_ch, n_samp)."""
        v = np.array([self._nominal_bias_v.get(d, np.nan) for d in ids], dtype=np.float64)
        return np.repeat(v[:, None], n_samp, axis=1)

    def bracketed(self, t_last_ns: int | None) -> bool:
        """True when every required sensor has a reading at or after ``t_last_ns``."""
        if t_last_ns is None:
            return True
        # Asked for every held chunk at every message: the oldest newest reading is kept until a
        # required series changes (its version), instead of read from each series every time.
        key = tuple(self.sensors[s].version for s in self.config.required_hk)
        if key != self._bracket_key:
            newest = [self.sensors[s].newest_t_ns for s in self.config.required_hk]
            self._bracket_ns = None if None in newest else min(newest, default=_INT64_MAX)
            self._bracket_key = key
        return self._bracket_ns is not None and self._bracket_ns >= t_last_ns

    def ages_s(self, now_ns: int) -> dict[str, float]:
        """Age of each scalar sensor's newest reading (sensors never read are absent)."""
        return {s: (now_ns - series.newest_t_ns) / 1e9 for s, series in self.sensors.items() if len(series)}

    def scalar(self, sensor: str, chunk: CountsChunk, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Aligned value and flags of ``t_bath`` or ``b_field``, shape (n_samp,) each (read-only)."""
        series = self.sensors[sensor]
        times = (chunk.t0_ns, chunk.sample_rate_hz, t.size) if chunk.t_ns is None else t.tobytes()
        key = (sensor, times)
        hit = self._env_cache.get(key)
        if hit is not None and hit[0] == series.version:
            return hit[1], hit[2]
        value, flags = self._scalar_uncached(sensor, t)
        value.setflags(write=False)
        flags.setflags(write=False)
        if len(self._env_cache) > _ENV_CACHE:
            self._env_cache.clear()
        self._env_cache[key] = (series.version, value, flags)
        return value, flags

    def _scalar_uncached(self, sensor: str, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cfg = self.config
        default, valid_range = ((cfg.t_bath_default_k, cfg.t_bath_range_k) if sensor == "t_bath"
                                else (cfg.b_field_default_t, cfg.b_field_range_t))
        series = self.sensors[sensor]
        required = sensor in cfg.required_hk
        if not len(series):
            flags = np.full(t.size, fl.HK_MISSING if required else 0, dtype=fl.FLAG_DTYPE)
            return np.full(t.size, default), flags
        a = series.align(t, self._staleness_ns, valid_range)
        missing = (a.flags & fl.HK_MISSING) != 0
        flags = a.flags if required else a.flags & ~np.uint16(fl.HK_MISSING)
        return np.where(missing, default, a.value), flags

    def bias(self, chunk: CountsChunk, t: np.ndarray, ids) -> tuple[np.ndarray | None, np.ndarray | None]:
        """Bias per row and sample, shape (n_ch, n_samp), and its flags; (None, None) before any reading."""
        entry = self._bias.get((chunk.board, chunk.module))
        if entry is None or not len(entry[1]):
            return None, None
        channels, series = entry
        a = series.align(t, self._bias_staleness_ns, self.config.bias_range_v)
        cols, has_col, nominal = self._bias_rows(chunk, channels, ids)
        # Each row is its column of the aligned readings (gathered by index: a copy) or else its nominal bias.
        v = np.ascontiguousarray(a.value.T[cols]) if has_col is None else np.empty((cols.size, t.size))
        if has_col is not None:
            v[has_col] = a.value.T[cols[has_col]]
            v[~has_col] = nominal[~has_col]
        missing = (a.flags & fl.HK_MISSING) != 0
        flags = a.flags & ~np.uint16(fl.HK_MISSING)
        if missing.any():  # before any bias reading: the nominal bias
            v = np.where(missing[None, :], nominal, v)
        return v, np.broadcast_to(flags, (cols.size, t.size))

    def _bias_rows(self, chunk: CountsChunk, channels: np.ndarray, ids) -> tuple:
        """Where each row of a chunk finds its bias: column in the module's bias readings, and nominal bias.

        Returns ``cols`` (n_ch,) int (0 for a row without a column), ``has_col`` (n_ch,) bool or None when
        every row has one, ``nominal`` (n_ch, 1) float (NaN for a detector without parameters). Cached per
        module and channel list, for as long as the module's bias history keeps its channel list (a new list
        is a new ``channels`` array: the cache entry's ``is`` check fails and it is made again).
        """
        key = (chunk.board, chunk.module, chunk.channels.tobytes())
        hit = self._bias_cols.get(key)
        if hit is not None and hit[0] is channels:
            return hit[1]
        col = {int(c): j for j, c in enumerate(channels.tolist())}
        found = [col.get(int(c)) for c in chunk.channels.tolist()]
        has = np.array([j is not None for j in found], dtype=bool)
        cols = np.array([0 if j is None else j for j in found], dtype=np.intp)
        nominal = np.array([self._nominal_bias_v.get(d, np.nan) for d in ids], dtype=np.float64)[:, None]
        if len(self._bias_cols) > _ENV_CACHE:
            self._bias_cols.clear()
        rows = (cols, None if has.all() else has, nominal)
        self._bias_cols[key] = (channels, rows)
        return rows
