"""OCS fields as the project's housekeeping: which field is which sensor, readings as messages."""

from __future__ import annotations

import heapq
import math
from dataclasses import dataclass

import numpy as np

from mntes_stream.core.settings import Settings, setting
from mntes_stream.io import keys
from mntes_stream.io.messages import SENSOR_UNITS, HousekeepingChunk

__all__ = ["OcsFields", "UNIT_SCALE", "feed_readings", "hk_messages", "merge_by_time", "within"]

# unit of the OCS field -> factor to the message's SI unit (SENSOR_UNITS)
UNIT_SCALE = {"K": 1.0, "mK": 1e-3, "T": 1.0, "mT": 1e-3, "G": 1e-4}


@dataclass(frozen=True)
class OcsFields(Settings):
    """Which OCS field gives which sensor (full names: feed address + field)."""

    t_bath_field: str = setting("", "bath temperature, e.g. observatory.LS372.feeds.temperatures.Channel_06_T "
                                "('': none)")
    t_bath_unit: str = setting("K", "unit of the t_bath field", choices=("K", "mK"))
    b_field_field: str = setting("", "magnetic field at the array ('': none)")
    b_field_unit: str = setting("T", "unit of the b_field field", choices=("T", "mT", "G"))

    def sensors(self) -> dict[str, tuple[str, float]]:
        """``sensor -> (full field name, factor to SI)`` of the fields named."""
        out = {}
        if self.t_bath_field:
            out["t_bath"] = (self.t_bath_field, UNIT_SCALE[self.t_bath_unit])
        if self.b_field_field:
            out["b_field"] = (self.b_field_field, UNIT_SCALE[self.b_field_unit])
        return out


def within(t_ns: np.ndarray, start_ns: int | None, end_ns: int | None) -> slice:
    """The readings that matter to data in [start_ns, end_ns]: those inside, and one on each side
    (so every sample is bracketed when the thermometer covers it)."""
    lo = 0 if start_ns is None else max(int(np.searchsorted(t_ns, start_ns, "right")) - 1, 0)
    hi = t_ns.size if end_ns is None else min(int(np.searchsorted(t_ns, end_ns, "left")) + 1, t_ns.size)
    return slice(lo, max(lo, hi))


def hk_messages(setup: str, sensor: str, t_ns: np.ndarray, value: np.ndarray, *, seq0: int = 0,
                per_message: int = 1) -> list[tuple[int, str, bytes]]:
    """``(t_ns, key, payload)`` HousekeepingChunk messages of readings already in SI units.

    Each message is stamped with its last reading's time: when a live reading
    could have been published. One reading per message by default, so an
    offline conversion sees each reading when it was taken.
    """
    key = keys.hk_key(setup, sensor)
    out = []
    for k, i in enumerate(range(0, t_ns.size, per_message)):
        t, v = t_ns[i:i + per_message], value[i:i + per_message]
        msg = HousekeepingChunk(setup=setup, sensor=sensor, seq=seq0 + k, t_ns=np.asarray(t, np.int64),
                                value=np.asarray(v, np.float64), unit=SENSOR_UNITS[sensor])
        out.append((int(t[-1]), key, msg.to_bytes()))
    return out


def merge_by_time(*streams):
    """Streams of ``(t_ns, key, payload)``, each in time order, as one in time order."""
    return heapq.merge(*streams, key=lambda m: m[0])


def hk_from_files(path, fields: OcsFields, setup: str, start_ns: int | None = None,
                  end_ns: int | None = None) -> list[tuple[int, str, bytes]]:
    """Every configured sensor's readings from OCS HK file(s) ``path`` as messages, in time order,
    limited to what data in [start_ns, end_ns] needs (:func:`within`)."""
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3.ocs_hkfile import read_fields

    sensors = fields.sensors()
    if not sensors:
        raise ConfigError("--hk needs a field to read: --t-bath-field FULL.FIELD.NAME")
    series = read_fields(path, [name for name, _ in sensors.values()])
    streams = []
    for sensor, (name, scale) in sensors.items():
        s = series[name]
        sl = within(s.t_ns, start_ns, end_ns)
        if sl.stop - sl.start == 0 or (start_ns is not None and s.t_ns[-1] < start_ns) or (
                end_ns is not None and s.t_ns[0] > end_ns):
            raise ConfigError(f"--hk {path}: {name} has no reading near the data ({_span(s.t_ns)} vs the data's "
                              f"{_span(np.array([start_ns or 0, end_ns or 0]))})")
        streams.append(hk_messages(setup, sensor, s.t_ns[sl], s.value[sl] * scale))
    return list(merge_by_time(*streams))


def _span(t_ns) -> str:
    from datetime import UTC, datetime

    def iso(t):
        return datetime.fromtimestamp(int(t) / 1e9, UTC).strftime("%Y-%m-%dT%H:%M:%SZ")

    return f"{iso(t_ns[0])} .. {iso(t_ns[-1])}"


def feed_readings(message, field: str) -> tuple[np.ndarray, np.ndarray, int]:
    """``(t_ns, values, bad)`` of ``field`` in one OCS feed publication, in time order.

    ``message`` is what an agent's feed publishes on its WAMP topic: ``(data,
    feed)`` where ``data`` is, for an aggregated feed, ``{block_name:
    {"timestamps": [...], "data": {field: [...]}}}``, otherwise one message
    ``{"timestamp" or "timestamps", "block_name", "data": {field: value(s)}}``.
    A value that is not a number becomes NaN (a failed reading); ``bad``
    counts those and entries whose shape does not fit (skipped).
    """
    data = message[0] if isinstance(message, (list, tuple)) and message else message
    if not isinstance(data, dict):
        return np.empty(0, np.int64), np.empty(0), 1
    blocks = [data] if "data" in data and isinstance(data.get("data"), dict) else list(data.values())
    ts, vs, bad = [], [], 0
    for b in blocks:
        if not isinstance(b, dict) or not isinstance(b.get("data"), dict) or field not in b["data"]:
            continue
        t, v = b.get("timestamps", b.get("timestamp")), b["data"][field]
        t, v = (t, v) if isinstance(t, list) else ([t], [v])
        if not isinstance(v, list) or len(v) != len(t):
            bad += 1
            continue
        for ti, vi in zip(t, v):
            try:
                tf = float(ti)
            except (TypeError, ValueError):
                bad += 1
                continue
            try:
                vf = float(vi)
            except (TypeError, ValueError):
                vf, bad = math.nan, bad + 1
            if math.isfinite(tf) and tf > 0:
                ts.append(round(tf * 1e9))
                vs.append(vf)
            else:
                bad += 1
    t_ns, val = np.asarray(ts, np.int64), np.asarray(vs, np.float64)
    order = np.argsort(t_ns, kind="stable")
    return t_ns[order], val[order], bad
