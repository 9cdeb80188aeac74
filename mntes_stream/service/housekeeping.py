"""The converter's housekeeping state: sensor histories, per-module bias, the data clock.

Free of zenoh like the pipeline that owns it. Readings are kept relative to
the *data clock* (the receive clock minus the median delay of the latest
counts chunks), so a replayed old recording is judged by its own time and one
bad ``t_pub_ns`` cannot move it.
"""

from __future__ import annotations

import collections
import math
import statistics

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core.align import HkSeries
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk
from mntes_stream.service.pipeline_config import SCALAR_SENSORS, PipelineConfig

__all__ = ["Housekeeping", "ns"]

_INT64_MIN, _INT64_MAX = -(1 << 63), (1 << 63) - 1
_OFFSETS = 32  # counts chunks whose receive delay sets the data clock
_ENV_CACHE = 1024  # aligned (times, sensor) results kept: every module of a step shares its times


def ns(seconds: float) -> int | float:
    """Seconds to integer ns; infinity stays infinite (a disabled limit)."""
    return math.inf if math.isinf(seconds) else int(round(seconds * 1e9))


class Housekeeping:
    """Sensor histories and bias per module, aligned on request to a chunk's sample times.

    Parameters
    ----------
    config : PipelineConfig
    nominal_bias_v : dict of str to float
        Bias per detector id, used before any bias reading of its module.
    """

    def __init__(self, config: PipelineConfig, nominal_bias_v: dict[str, float]):
        self.config = config
        self._nominal_bias_v = nominal_bias_v
        self._staleness_ns = ns(config.hk_staleness_s)
        self._bias_staleness_ns = ns(config.bias_staleness_s)
        self._retention_ns = ns(config.hk_retention_s)
        self._ahead_ns = ns(config.hk_max_ahead_s)
        self.sensors: dict[str, HkSeries] = {s: HkSeries(None, self._retention_ns) for s in SCALAR_SENSORS}
        self._bias: dict[tuple[int, int], tuple[np.ndarray, HkSeries]] = {}
        self._delays: collections.deque[int] = collections.deque(maxlen=_OFFSETS)  # receive minus t_pub_ns
        self._env_cache: dict[tuple, tuple] = {}

    def note_delay(self, delay_ns: int) -> None:
        """One counts chunk's receive time minus its ``t_pub_ns`` (sets the data clock)."""
        self._delays.append(int(delay_ns))

    def data_clock(self, t_recv_ns: int) -> int:
        """Receive clock minus the counts' median delay (none yet: the receive clock)."""
        return t_recv_ns - (int(statistics.median_low(self._delays)) if self._delays else 0)

    def add(self, hk: HousekeepingChunk, t_recv_ns: int) -> str:
        """Keep a chunk's readings; returns why some were dropped ("" if none were).

        Readings stamped more than ``hk_max_ahead_s`` ahead of the data clock,
        or (bias excepted: a setting holds) more than ``hk_retention_s`` behind
        it once the data clock is known, are dropped.
        """
        now = self.data_clock(t_recv_ns)
        t_ns, value = hk.t_ns, hk.value
        lo = now - self._retention_ns if self._delays and hk.sensor != "bias" else _INT64_MIN
        ok = (t_ns >= max(lo, _INT64_MIN)) & (t_ns <= min(now + self._ahead_ns, _INT64_MAX))
        problem = ""
        if not ok.all():
            bad = t_ns[~ok]
            problem = (f"{bad.size} reading(s) stamped {(int(bad[0]) - now) / 1e9:+.4g} s from the data clock "
                       f"(accepted: -{self.config.hk_retention_s:g} s to +{self.config.hk_max_ahead_s:g} s)")
            t_ns, value = t_ns[ok], value[ok]
        if hk.sensor == "bias":
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

    def bracketed(self, t_last_ns: int | None) -> bool:
        """True when every required sensor has a reading at or after ``t_last_ns``."""
        if t_last_ns is None:
            return True
        for sensor in self.config.required_hk:
            newest = self.sensors[sensor].newest_t_ns
            if newest is None or newest < t_last_ns:
                return False
        return True

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
        n_ch, n = chunk.channels.size, t.size
        v = np.empty((n_ch, n))
        col = {int(c): j for j, c in enumerate(channels.tolist())}
        for r, c in enumerate(chunk.channels.tolist()):
            j = col.get(int(c))
            v[r] = self._nominal_bias_v.get(ids[r], np.nan) if j is None else a.value[:, j]
        missing = (a.flags & fl.HK_MISSING) != 0
        flags = a.flags & ~np.uint16(fl.HK_MISSING)
        if missing.any():  # before any bias reading: the nominal bias
            nominal = np.array([self._nominal_bias_v.get(d, np.nan) for d in ids])[:, None]
            v = np.where(missing[None, :], nominal, v)
        return v, np.broadcast_to(flags, (n_ch, n))
