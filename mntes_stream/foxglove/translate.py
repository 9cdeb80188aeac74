"""mntes messages -> json messages a person can plot in Foxglove without code (no I/O, no foxglove import).

Foxglove reads json, protobuf, flatbuffer, ros1 and cdr message encodings,
not msgpack; so the bridge (live) and the transcoder/recorder (MCAP) turn each
decoded message into zero or more json messages on these topics, each with a
JSON Schema (:data:`SCHEMAS`, schema encoding ``jsonschema``):

========================================  =========================  ===========================================
topic                                     schema                     one message per
========================================  =========================  ===========================================
``/mntes/<setup>/power/<board>/<module>`` ``mntes.foxglove.power``   power sample (decimated to ``max_rate_hz``)
``/mntes/<setup>/flag_rates/<service>``   ``mntes.foxglove.flag_rates`` status interval of a converter
``/mntes/<setup>/hk/<sensor>``            ``mntes.foxglove.hk``      housekeeping reading
``/mntes/<setup>/status/<service>``       ``mntes.foxglove.status``  status message
========================================  =========================  ===========================================

Power is in pW (``p_opt_pw``, keyed by detector id: plot
``/mntes/lab/power/0/0.p_opt_pw.b0m0c001``); NaN (no usable power) is null.
Every message has ``timestamp`` ``{sec, nsec}`` (Foxglove's time type) and
``t_ns``; the log time is the sample (or reading, or status) time.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.io.messages import HousekeepingChunk, PowerChunk, StatusMessage, detector_ids_for

__all__ = ["SCHEMAS", "FoxgloveView", "JsonMessage"]

_TIME = {
    "type": "object",
    "description": "Foxglove time: seconds and nanoseconds since 1970-01-01T00:00:00Z",
    "properties": {"sec": {"type": "integer", "minimum": 0}, "nsec": {"type": "integer", "minimum": 0, "maximum": 999999999}},
    "required": ["sec", "nsec"],
}
_T_NS = {"type": "integer", "minimum": 0, "description": "ns since 1970-01-01T00:00:00Z"}
_NUMBER_OR_NULL = {"type": ["number", "null"]}
_FLAG_NAMES = list(fl.NAMES.values())


def _schema(name: str, description: str, properties: dict, required: list[str]) -> dict:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": name, "description": description,
            "type": "object", "properties": {"timestamp": _TIME, "t_ns": _T_NS, **properties},
            "required": ["timestamp", "t_ns", *required], "additionalProperties": False}


SCHEMAS: dict[str, dict] = {
    "mntes.foxglove.power": _schema(
        "mntes.foxglove.power",
        "one sample of optical power of the selected detectors of a module (from mntes.power)",
        {"board": {"type": "integer", "minimum": 0}, "module": {"type": "integer", "minimum": 0},
         "seq": {"type": "integer", "minimum": 0, "description": "sequence number of the source chunk"},
         "p_opt_pw": {"type": "object", "description": "optical power in pW by detector id; null: no usable power",
                      "additionalProperties": _NUMBER_OR_NULL},
         "flags": {"type": "object", "description": "flag bitmask by detector id (schemas/flags.v1.json)",
                   "additionalProperties": {"type": "integer", "minimum": 0, "maximum": 65535}},
         "flag_names": {"type": "object", "description": "names of the flag bits set, by detector id (only flagged ones)",
                        "additionalProperties": {"type": "array", "items": {"enum": _FLAG_NAMES}}}},
        ["board", "module", "seq", "p_opt_pw", "flags", "flag_names"]),
    "mntes.foxglove.flag_rates": _schema(
        "mntes.foxglove.flag_rates",
        "fraction of converted samples carrying each flag over one status interval (from mntes.status)",
        {"service": {"type": "string"}, "interval_s": {"type": "number", "minimum": 0},
         "samples": {"type": "integer", "minimum": 0, "description": "samples converted in the interval"},
         "fraction": {"type": "object", "properties": {n: {"type": "number", "minimum": 0} for n in _FLAG_NAMES},
                      "required": _FLAG_NAMES, "additionalProperties": False},
         "per_s": {"type": "object", "description": "flagged samples per second",
                   "properties": {n: {"type": "number", "minimum": 0} for n in _FLAG_NAMES},
                   "required": _FLAG_NAMES, "additionalProperties": False}},
        ["service", "interval_s", "samples", "fraction", "per_s"]),
    "mntes.foxglove.hk": _schema(
        "mntes.foxglove.hk",
        "one housekeeping reading (from mntes.hk): value for t_bath (K) and b_field (T), value_by_detector for bias (V RMS)",
        {"sensor": {"type": "string"}, "unit": {"enum": ["K", "T", "V", "flags"]}, "value": _NUMBER_OR_NULL,
         "board": {"type": "integer", "minimum": 0}, "module": {"type": "integer", "minimum": 0},
         "value_by_detector": {"type": "object", "additionalProperties": _NUMBER_OR_NULL}},
        ["sensor", "unit"]),
    "mntes.foxglove.status": _schema(
        "mntes.foxglove.status",
        "converter health (mntes.status fields; counters cumulative since start, rates and latencies over the interval)",
        {"setup": {"type": "string"}, "service": {"type": "string"}, "uptime_s": {"type": "number"},
         "interval_s": {"type": "number"},
         **{k: {"type": "integer"} for k in StatusMessage.COUNTERS if k != "t_ns"},
         "bad_messages": {"type": "object", "additionalProperties": {"type": "integer"}},
         "flag_counts": {"type": "object", "additionalProperties": {"type": "integer"}},
         "hk_age_s": {"type": "object", "additionalProperties": _NUMBER_OR_NULL},
         "rate_chunks_per_s": {"type": "number"}, "rate_msamples_per_s": {"type": "number"},
         **{k: _NUMBER_OR_NULL for k in StatusMessage.LATENCIES},
         "last_error": {"type": "string"}},
        ["setup", "service", "chunks_converted", "chunks_lost", "bad_messages", "flag_counts"]),
}


@dataclass(frozen=True, slots=True)
class JsonMessage:
    """One json message for a Foxglove channel; ``log_time_ns`` is the data time it stands for."""

    topic: str
    schema: str
    log_time_ns: int
    message: dict


def _stamp(t_ns: int) -> dict:
    return {"sec": int(t_ns) // 1_000_000_000, "nsec": int(t_ns) % 1_000_000_000}


def _num(x: float) -> float | None:
    return float(x) if math.isfinite(x) else None


class FoxgloveView:
    """Turns decoded mntes messages into :class:`JsonMessage` lists (stateful: decimation, status deltas).

    Parameters
    ----------
    detectors : iterable of str
        Detector ids whose power is shown; empty: the first ``per_module`` rows of every module.
    per_module : int
        Rows per module shown when ``detectors`` is empty (0: every row).
    max_rate_hz : float
        Power samples per second and module at most (0: every sample); samples are
        picked, never averaged, so each json value is one published value.
    """

    def __init__(self, detectors: Iterable[str] = (), per_module: int = 4, max_rate_hz: float = 50.0):
        self.detectors = frozenset(detectors)
        self.per_module = int(per_module)
        self.min_step_ns = int(1e9 / max_rate_hz) if max_rate_hz > 0 else 0
        self._last_power_ns: dict[tuple[int, int], int] = {}
        self._last_status: dict[tuple[str, str], StatusMessage] = {}

    def translate(self, msg) -> list[JsonMessage]:
        """The json messages for one decoded message (other message types: none)."""
        if isinstance(msg, PowerChunk):
            return self.power(msg)
        if isinstance(msg, HousekeepingChunk):
            return self.hk(msg)
        if isinstance(msg, StatusMessage):
            return self.status(msg)
        return []

    def rows(self, msg: PowerChunk) -> np.ndarray:
        """Row indices of ``msg`` that are shown."""
        if self.detectors:
            return np.array([i for i, d in enumerate(msg.detector_ids) if d in self.detectors], dtype=np.intp)
        n = msg.p_opt_w.shape[0]
        return np.arange(n if self.per_module <= 0 else min(n, self.per_module))

    def power(self, msg: PowerChunk) -> list[JsonMessage]:
        rows = self.rows(msg)
        if rows.size == 0:
            return []
        ids = [msg.detector_ids[i] for i in rows]
        t = msg.times_ns()
        key = (msg.board, msg.module)
        last = self._last_power_ns.get(key)
        topic = f"/mntes/{msg.setup}/power/{msg.board}/{msg.module}"
        p_pw = msg.p_opt_w[rows] * 1e12
        flags = msg.flags[rows]
        out = []
        for k in range(t.size):
            tk = int(t[k])
            if last is not None and tk - last < self.min_step_ns and tk >= last:
                continue
            last = tk
            col_f = flags[:, k].tolist()
            out.append(JsonMessage(topic, "mntes.foxglove.power", tk, {
                "timestamp": _stamp(tk), "t_ns": tk, "board": msg.board, "module": msg.module, "seq": msg.seq,
                "p_opt_pw": {d: _num(v) for d, v in zip(ids, p_pw[:, k].tolist())},
                "flags": dict(zip(ids, col_f)),
                "flag_names": {d: fl.describe(f) for d, f in zip(ids, col_f) if f},
            }))
        if last is not None:
            self._last_power_ns[key] = last
        return out

    def hk(self, msg: HousekeepingChunk) -> list[JsonMessage]:
        per_channel = msg.channels is not None
        sensor = f"{msg.sensor}/{msg.board}/{msg.module}" if per_channel else msg.sensor
        topic = f"/mntes/{msg.setup}/hk/{sensor}"
        out = []
        ids = detector_ids_for(msg.board, msg.module, msg.channels) if per_channel else ()
        for k, tk in enumerate(msg.t_ns.tolist()):
            body = {"timestamp": _stamp(tk), "t_ns": tk, "sensor": sensor, "unit": msg.unit}
            if per_channel:
                body.update(board=msg.board, module=msg.module,
                            value_by_detector={d: _num(v) for d, v in zip(ids, msg.value[k].tolist())})
            else:
                body["value"] = _num(float(msg.value[k]))
            out.append(JsonMessage(topic, "mntes.foxglove.hk", tk, body))
        return out

    def status(self, msg: StatusMessage) -> list[JsonMessage]:
        body = {k: v for k, v in _status_fields(msg).items() if k in SCHEMAS["mntes.foxglove.status"]["properties"]}
        body["hk_age_s"] = {k: _num(v) for k, v in msg.hk_age_s.items()}  # JSON has no inf/NaN
        for k in (*StatusMessage.RATES, *StatusMessage.LATENCIES):
            body[k] = None if body[k] is None else _num(body[k])
        body["timestamp"] = _stamp(msg.t_ns)
        out = [JsonMessage(f"/mntes/{msg.setup}/status/{msg.service}", "mntes.foxglove.status", msg.t_ns, body)]
        key = (msg.setup, msg.service)
        prev = self._last_status.get(key)
        self._last_status[key] = msg
        if prev is None or msg.t_ns <= prev.t_ns or msg.samples_converted < prev.samples_converted:
            return out  # first one, or a restarted service: no interval to take a rate over
        dt_s = (msg.t_ns - prev.t_ns) / 1e9
        samples = msg.samples_converted - prev.samples_converted
        delta = {n: max(msg.flag_counts.get(n, 0) - prev.flag_counts.get(n, 0), 0) for n in _FLAG_NAMES}
        out.append(JsonMessage(f"/mntes/{msg.setup}/flag_rates/{msg.service}", "mntes.foxglove.flag_rates", msg.t_ns, {
            "timestamp": _stamp(msg.t_ns), "t_ns": msg.t_ns, "service": msg.service, "interval_s": dt_s,
            "samples": samples, "fraction": {n: (d / samples if samples else 0.0) for n, d in delta.items()},
            "per_s": {n: d / dt_s for n, d in delta.items()},
        }))
        return out


def _status_fields(msg: StatusMessage) -> dict:
    from dataclasses import fields

    return {f.name: getattr(msg, f.name) for f in fields(msg)}
