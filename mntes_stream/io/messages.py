"""The stream's messages: frozen dataclasses <-> msgpack bytes (schemas in ``schemas/``).

Every class has ``to_bytes()`` and ``from_bytes(payload)``. Construction
validates and normalises (dtypes, shapes, ranges), so an object that exists
is a valid message; decoding raises :class:`SchemaError` and nothing else,
with a ``reason`` attribute (see :data:`REASONS`) that status messages count.

Sample times of counts and power chunks are either ``t0_ns`` plus
``sample_rate_hz`` (sample k at ``t0_ns + round(k * 1e9 / rate)``,
:func:`mntes_stream.core.align.sample_times_ns`) or an explicit ``t_ns`` array.
"""

from __future__ import annotations

import functools
import math
import operator
import re
from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np

from mntes_stream.core.align import last_sample_offset_ns, sample_times_ns
from mntes_stream.core.ids import detector_id
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io.codec import decode_array, encode_array, json_schema, pack, unpack
from mntes_stream.io.keys import NAME_PATTERN

__all__ = [
    "REASONS",
    "SENSOR_UNITS",
    "SAMPLE_RATE_RANGE_HZ",
    "CountsChunk",
    "HousekeepingChunk",
    "PowerChunk",
    "StatusMessage",
    "Provenance",
    "MESSAGE_TYPES",
    "decode",
    "detector_ids_for",
    "reason_of",
]

# Why a message was rejected; the keys of StatusMessage.bad_messages.
REASONS = ("malformed", "unknown_schema", "wrong_schema", "wrong_version", "invalid", "wrong_key")
SENSOR_UNITS = {"t_bath": "K", "b_field": "T", "bias": "V"}
# Sample rates a chunk may declare (from the schema, the one source): beyond,
# sample times lose meaning (1e-300 Hz puts sample 1 beyond int64 ns).
_RATE_SCHEMA = json_schema("mntes.counts")["properties"]["sample_rate_hz"]
SAMPLE_RATE_RANGE_HZ = (float(_RATE_SCHEMA["minimum"]), float(_RATE_SCHEMA["maximum"]))
_INT64_MAX = (1 << 63) - 1


def _error(reason: str, message: str) -> SchemaError:
    exc = SchemaError(message)
    exc.reason = reason
    return exc


def reason_of(exc: SchemaError) -> str:
    """The rejection reason of a decoding error (one of :data:`REASONS`)."""
    reason = getattr(exc, "reason", None)
    if reason in REASONS:
        return reason
    text = str(exc)
    # codec.unpack's messages, mapped once here.
    if text.startswith(("malformed msgpack", "message is a", "message lacks")):
        return "malformed"
    if text.startswith("unknown message schema"):
        return "unknown_schema"
    if text.startswith("expected schema"):
        return "wrong_schema"
    if "not supported (this build speaks" in text:
        return "wrong_version"
    return "invalid"


def _unpack(payload: Any, expected=None) -> dict:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise _error("malformed", f"payload must be bytes, got {type(payload).__name__}")
    try:
        msg = unpack(bytes(payload))
    except SchemaError as exc:
        raise _error(reason_of(exc), str(exc)) from None
    # Checked after the envelope so an unknown name or version is reported as such.
    names = (expected,) if isinstance(expected, str) else expected
    if names is not None and msg["schema"] not in names:
        raise _error("wrong_schema", f"expected schema {'/'.join(names)}, got {msg['schema']!r}")
    return msg


# --- field checks (raise SchemaError "invalid") -----------------------------------------


def _int(value: Any, name: str, lo: int = 0, hi: int = _INT64_MAX) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise _error("invalid", f"{name} must be an integer, got a bool")
    try:
        v = operator.index(value)
    except TypeError:
        raise _error("invalid", f"{name} must be an integer, got {type(value).__name__}") from None
    if not lo <= v <= hi:
        raise _error("invalid", f"{name} = {v} outside [{lo}, {hi}]")
    return v


def _str(value: Any, name: str, pattern: re.Pattern | None = None) -> str:
    if not isinstance(value, str):
        raise _error("invalid", f"{name} must be a string, got {type(value).__name__}")
    if pattern is not None and not pattern.match(value):
        raise _error("invalid", f"{name} {value!r} does not match {pattern.pattern}")
    return value


def _float(value: Any, name: str, positive: bool = False, optional: bool = False) -> float | None:
    if value is None and optional:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise _error("invalid", f"{name} must be a number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v) or (positive and v <= 0):
        raise _error("invalid", f"{name} = {v} must be finite{' and > 0' if positive else ''}")
    return v


def _array(value: Any, name: str, dtype: str, ndim: int | tuple[int, ...]) -> np.ndarray:
    """Coerce to the wire dtype: integers only into integer types, in range."""
    a = np.asarray(value)
    ndims = (ndim,) if isinstance(ndim, int) else ndim
    if a.ndim not in ndims:
        raise _error("invalid", f"{name}: expected {' or '.join(map(str, ndims))} dimensions, got shape {a.shape}")
    target = np.dtype(dtype)
    if a.dtype == target:
        return a
    if target.kind in "iu":
        if a.dtype.kind not in "iu":
            raise _error("invalid", f"{name}: integer array required, got dtype {a.dtype}")
        info = np.iinfo(target)
        if a.size and (int(a.min()) < info.min or int(a.max()) > info.max):
            raise _error("invalid", f"{name}: values outside the range of {target}")
    elif a.dtype.kind not in "iuf":
        raise _error("invalid", f"{name}: real numeric array required, got dtype {a.dtype}")
    return np.ascontiguousarray(a, dtype=target)


def _channels(value: Any) -> np.ndarray:
    ch = _array(value, "channels", "<i4", 1)
    if ch.size and int(ch.min()) < 0:
        raise _error("invalid", "channels must be >= 0")
    if np.unique(ch).size != ch.size:
        raise _error("invalid", "channels must be distinct")
    return ch


def _times(obj, n_samp: int) -> None:
    """Check the (t0_ns, sample_rate_hz) xor t_ns convention on a chunk."""
    if obj.t_ns is not None:
        if obj.t0_ns is not None or obj.sample_rate_hz is not None:
            raise _error("invalid", "give either t_ns or (t0_ns, sample_rate_hz), not both")
        t = _array(obj.t_ns, "t_ns", "<i8", 1)
        if t.size != n_samp:
            raise _error("invalid", f"t_ns has {t.size} entries for {n_samp} samples")
        if t.size and (int(t.min()) < 0 or np.any(np.diff(t) < 0)):
            raise _error("invalid", "t_ns must be >= 0 and non-decreasing")
        object.__setattr__(obj, "t_ns", t)
    else:
        if obj.t0_ns is None or obj.sample_rate_hz is None:
            raise _error("invalid", "t0_ns and sample_rate_hz (or t_ns) are required")
        t0 = _int(obj.t0_ns, "t0_ns")
        rate = _float(obj.sample_rate_hz, "sample_rate_hz", positive=True)
        lo, hi = SAMPLE_RATE_RANGE_HZ
        if not lo <= rate <= hi:
            raise _error("invalid", f"sample_rate_hz = {rate} outside [{lo:g}, {hi:g}]")
        try:
            last = t0 + last_sample_offset_ns(rate, n_samp)
        except ConfigError as exc:
            raise _error("invalid", str(exc)) from None
        if last > _INT64_MAX:
            raise _error("invalid", f"the last of {n_samp} samples from t0_ns = {t0} at {rate} Hz is beyond int64 ns")
        object.__setattr__(obj, "t0_ns", t0)
        object.__setattr__(obj, "sample_rate_hz", rate)


@functools.lru_cache(maxsize=4096)
def _ids(board: int, module: int, channels: bytes) -> tuple[str, ...]:
    return tuple(detector_id(board, module, c) for c in np.frombuffer(channels, dtype="<i4").tolist())


def detector_ids_for(board: int, module: int, channels: np.ndarray) -> tuple[str, ...]:
    """Detector ids of a module's channel rows (cached: streams repeat them every chunk)."""
    return _ids(int(board), int(module), np.ascontiguousarray(channels, dtype="<i4").tobytes())


def _time_body(obj) -> dict:
    if obj.t_ns is not None:
        return {"t_ns": encode_array(obj.t_ns)}
    return {"t0_ns": obj.t0_ns, "sample_rate_hz": obj.sample_rate_hz}


class _Message:
    """Shared encode/decode machinery; subclasses are frozen dataclasses."""

    SCHEMA: ClassVar[str]
    _ARRAYS: ClassVar[dict[str, tuple[str, int | tuple[int, ...]]]] = {}
    # Fields that may be absent on the wire although the constructor takes them positionally.
    _OPTIONAL: ClassVar[tuple[str, ...]] = ()

    def _body(self) -> dict:
        body = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if value is None:
                continue
            if f.name in self._ARRAYS:
                value = encode_array(value)
            elif isinstance(value, tuple):
                value = list(value)
            body[f.name] = value
        return body

    def to_bytes(self) -> bytes:
        """msgpack bytes of this message (envelope with schema name and version)."""
        return pack(self.SCHEMA, self._body())

    @classmethod
    def from_bytes(cls, payload: bytes):
        """Decode and validate; raises :class:`SchemaError` (with ``.reason``)."""
        return cls._from_map(_unpack(payload, cls.SCHEMA))

    @classmethod
    def _from_map(cls, msg: dict):
        names = {f.name for f in fields(cls)}
        extra = set(msg) - names - {"schema", "version"}
        if extra:
            raise _error("invalid", f"{cls.SCHEMA}: unknown field(s) {sorted(map(str, extra))}")
        kwargs = {}
        for name in names:
            if name not in msg:
                continue
            value = msg[name]
            if name in cls._ARRAYS:
                dtype, ndim = cls._ARRAYS[name]
                try:
                    value = decode_array(value, name, dtype, ndim if isinstance(ndim, int) else None)
                except SchemaError as exc:
                    raise _error("invalid", f"{cls.SCHEMA}: {exc}") from None
            kwargs[name] = value
        for name in cls._OPTIONAL:
            kwargs.setdefault(name, None)
        try:
            return cls(**kwargs)
        except SchemaError as exc:
            raise _error(reason_of(exc), f"{cls.SCHEMA}: {exc}") from None
        except TypeError as exc:  # missing required fields
            raise _error("invalid", f"{cls.SCHEMA}: {exc}") from None


# --- messages --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CountsChunk(_Message):
    """One chunk of demodulated I/Q counts from one module.

    Attributes
    ----------
    setup : str
    board, module : int
    channels : ndarray of int32, shape (n_ch,)
    seq : int
        Per-stream sequence number.
    t0_ns : int or None
        First sample time (with ``sample_rate_hz``), or None with ``t_ns``.
    sample_rate_hz : float or None
    counts_i, counts_q : ndarray of int32, shape (n_ch, n_samp)
    t_pub_ns : int
        Publication time at the source.
    t_ns : ndarray of int64, shape (n_samp,), optional
        Explicit sample times instead of ``t0_ns``/``sample_rate_hz``.
    """

    SCHEMA: ClassVar[str] = "mntes.counts"
    _ARRAYS: ClassVar[dict] = {"channels": ("<i4", 1), "counts_i": ("<i4", 2), "counts_q": ("<i4", 2), "t_ns": ("<i8", 1)}
    _OPTIONAL: ClassVar[tuple] = ("t0_ns", "sample_rate_hz")

    setup: str
    board: int
    module: int
    channels: np.ndarray
    seq: int
    t0_ns: int | None
    sample_rate_hz: float | None
    counts_i: np.ndarray
    counts_q: np.ndarray
    t_pub_ns: int
    t_ns: np.ndarray | None = None

    def __post_init__(self) -> None:
        _str(self.setup, "setup", NAME_PATTERN)
        for name in ("board", "module", "seq", "t_pub_ns"):
            object.__setattr__(self, name, _int(getattr(self, name), name))
        ch = _channels(self.channels)
        ci = _array(self.counts_i, "counts_i", "<i4", 2)
        cq = _array(self.counts_q, "counts_q", "<i4", 2)
        if ci.shape != cq.shape or ci.shape[0] != ch.size:
            raise _error("invalid", f"counts_i {ci.shape} and counts_q {cq.shape} must both be (n_ch={ch.size}, n_samp)")
        object.__setattr__(self, "channels", ch)
        object.__setattr__(self, "counts_i", ci)
        object.__setattr__(self, "counts_q", cq)
        _times(self, ci.shape[1])

    @property
    def n_samples(self) -> int:
        return int(self.counts_i.shape[1])

    def times_ns(self) -> np.ndarray:
        """Sample times, int64 (n_samp,)."""
        if self.t_ns is not None:
            return self.t_ns
        return sample_times_ns(self.t0_ns, self.sample_rate_hz, self.n_samples)


@dataclass(frozen=True, eq=False)
class HousekeepingChunk(_Message):
    """Readings of one housekeeping sensor.

    Attributes
    ----------
    setup : str
    sensor : {"t_bath", "b_field", "bias"}
    seq : int
    t_ns : ndarray of int64, shape (n,), strictly increasing
    value : ndarray of float64, shape (n,), or (n, n_ch) for bias
        Non-finite entries mark failed readings.
    unit : str
        ``SENSOR_UNITS[sensor]`` ("K", "T", "V": SI, bias is RMS volts).
    board, module : int, bias only
    channels : ndarray of int32, shape (n_ch,), bias only
    """

    SCHEMA: ClassVar[str] = "mntes.hk"
    _ARRAYS: ClassVar[dict] = {"t_ns": ("<i8", 1), "value": ("<f8", (1, 2)), "channels": ("<i4", 1)}

    setup: str
    sensor: str
    seq: int
    t_ns: np.ndarray
    value: np.ndarray
    unit: str
    board: int | None = None
    module: int | None = None
    channels: np.ndarray | None = None

    def __post_init__(self) -> None:
        _str(self.setup, "setup", NAME_PATTERN)
        if self.sensor not in SENSOR_UNITS:
            raise _error("invalid", f"sensor {self.sensor!r} not one of {sorted(SENSOR_UNITS)}")
        if self.unit != SENSOR_UNITS[self.sensor]:
            raise _error("invalid", f"{self.sensor} unit must be {SENSOR_UNITS[self.sensor]!r}, got {self.unit!r}")
        object.__setattr__(self, "seq", _int(self.seq, "seq"))
        t = _array(self.t_ns, "t_ns", "<i8", 1)
        if t.size and (int(t.min()) < 0 or np.any(np.diff(t) <= 0)):
            raise _error("invalid", "t_ns must be >= 0 and strictly increasing")
        per_channel = self.sensor == "bias"
        v = _array(self.value, "value", "<f8", 2 if per_channel else 1)
        if v.shape[0] != t.size:
            raise _error("invalid", f"value has {v.shape[0]} rows for {t.size} times")
        if per_channel:
            if self.board is None or self.module is None or self.channels is None:
                raise _error("invalid", "bias readings need board, module and channels")
            object.__setattr__(self, "board", _int(self.board, "board"))
            object.__setattr__(self, "module", _int(self.module, "module"))
            ch = _channels(self.channels)
            if v.shape[1] != ch.size:
                raise _error("invalid", f"bias value has {v.shape[1]} columns for {ch.size} channels")
            object.__setattr__(self, "channels", ch)
        elif self.board is not None or self.module is not None or self.channels is not None:
            raise _error("invalid", f"{self.sensor} readings take no board/module/channels")
        object.__setattr__(self, "t_ns", t)
        object.__setattr__(self, "value", v)


@dataclass(frozen=True, eq=False)
class PowerChunk(_Message):
    """Optical power of one module chunk (the converter's output).

    Attributes
    ----------
    setup : str
    board, module : int
    channels : ndarray of int32, shape (n_ch,)
    detector_ids : tuple of str, length n_ch
        ``core.ids.detector_id(board, module, channel)`` of each row.
    seq : int
        Sequence number of the source counts chunk.
    t0_ns, sample_rate_hz, t_ns
        As in :class:`CountsChunk`.
    p_opt_w : ndarray of float64, shape (n_ch, n_samp)
        NaN where no usable power.
    flags : ndarray of uint16, shape (n_ch, n_samp)
    table_identity, converter_kind : str
    source_t_pub_ns, t_pub_ns : int
        Publication times of the counts chunk and of this chunk.
    """

    SCHEMA: ClassVar[str] = "mntes.power"
    _ARRAYS: ClassVar[dict] = {"channels": ("<i4", 1), "p_opt_w": ("<f8", 2), "flags": ("<u2", 2), "t_ns": ("<i8", 1)}
    _OPTIONAL: ClassVar[tuple] = ("t0_ns", "sample_rate_hz")

    setup: str
    board: int
    module: int
    channels: np.ndarray
    detector_ids: tuple
    seq: int
    t0_ns: int | None
    sample_rate_hz: float | None
    p_opt_w: np.ndarray
    flags: np.ndarray
    table_identity: str
    converter_kind: str
    source_t_pub_ns: int
    t_pub_ns: int
    t_ns: np.ndarray | None = None

    def __post_init__(self) -> None:
        _str(self.setup, "setup", NAME_PATTERN)
        for name in ("board", "module", "seq", "source_t_pub_ns", "t_pub_ns"):
            object.__setattr__(self, name, _int(getattr(self, name), name))
        _str(self.table_identity, "table_identity")
        _str(self.converter_kind, "converter_kind")
        ch = _channels(self.channels)
        if not isinstance(self.detector_ids, (list, tuple)):
            raise _error("invalid", "detector_ids must be a list of strings")
        ids = tuple(self.detector_ids)
        if ids != detector_ids_for(self.board, self.module, ch):
            raise _error("invalid", "detector_ids do not match board/module/channels")
        p = _array(self.p_opt_w, "p_opt_w", "<f8", 2)
        f = _array(self.flags, "flags", "<u2", 2)
        if p.shape != f.shape or p.shape[0] != ch.size:
            raise _error("invalid", f"p_opt_w {p.shape} and flags {f.shape} must both be (n_ch={ch.size}, n_samp)")
        object.__setattr__(self, "channels", ch)
        object.__setattr__(self, "detector_ids", ids)
        object.__setattr__(self, "p_opt_w", p)
        object.__setattr__(self, "flags", f)
        _times(self, p.shape[1])

    @property
    def n_samples(self) -> int:
        return int(self.p_opt_w.shape[1])

    def times_ns(self) -> np.ndarray:
        """Sample times, int64 (n_samp,)."""
        if self.t_ns is not None:
            return self.t_ns
        return sample_times_ns(self.t0_ns, self.sample_rate_hz, self.n_samples)


def _count_map(value: Any, name: str) -> dict:
    if not isinstance(value, dict):
        raise _error("invalid", f"{name} must be a map")
    return {_str(k, f"{name} key"): _int(v, f"{name}[{k}]") for k, v in value.items()}


@dataclass(frozen=True, eq=False)
class StatusMessage(_Message):
    """Converter health, published periodically (schema ``status.v1.json``).

    Counters are cumulative since start; ``rate_*`` and ``latency_*`` cover
    the last interval (latency: source publication to power publication;
    None when no chunk was converted in the interval).
    """

    SCHEMA: ClassVar[str] = "mntes.status"

    setup: str
    service: str
    t_ns: int
    uptime_s: float
    interval_s: float
    chunks_received: int = 0
    chunks_converted: int = 0
    chunks_pending: int = 0
    samples_converted: int = 0
    chunks_lost: int = 0
    chunks_duplicated: int = 0
    chunks_out_of_order: int = 0
    hk_received: int = 0
    hk_stale_samples: int = 0
    hk_missing_samples: int = 0
    unknown_channel_samples: int = 0
    bad_messages: dict = field(default_factory=dict)
    flag_counts: dict = field(default_factory=dict)
    hk_age_s: dict = field(default_factory=dict)
    rate_chunks_per_s: float = 0.0
    rate_msamples_per_s: float = 0.0
    latency_p50_ms: float | None = None
    latency_p99_ms: float | None = None
    latency_max_ms: float | None = None
    last_error: str = ""

    def __post_init__(self) -> None:
        _str(self.setup, "setup", NAME_PATTERN)
        _str(self.service, "service")
        _str(self.last_error, "last_error")
        for f in fields(self):
            value = getattr(self, f.name)
            if f.type == "int":
                object.__setattr__(self, f.name, _int(value, f.name))
            elif f.type == "float":
                v = _float(value, f.name)
                if v < 0:
                    raise _error("invalid", f"{f.name} must be >= 0")
                object.__setattr__(self, f.name, v)
            elif f.type == "float | None":  # latencies: negative when clocks disagree
                object.__setattr__(self, f.name, _float(value, f.name, optional=True))
        object.__setattr__(self, "bad_messages", _count_map(self.bad_messages, "bad_messages"))
        object.__setattr__(self, "flag_counts", _count_map(self.flag_counts, "flag_counts"))
        if not isinstance(self.hk_age_s, dict):
            raise _error("invalid", "hk_age_s must be a map")
        object.__setattr__(
            self, "hk_age_s", {_str(k, "hk_age_s key"): float(_float(v, f"hk_age_s[{k}]")) for k, v in self.hk_age_s.items()}
        )

    def _body(self) -> dict:
        # Optional latencies travel as nil (the schema allows null), not absent.
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def _from_map(cls, msg: dict):
        missing = {f.name for f in fields(cls)} - set(msg)
        if missing:
            raise _error("invalid", f"{cls.SCHEMA}: missing field(s) {sorted(missing)}")
        return super()._from_map(msg)


@dataclass(frozen=True, eq=False)
class Provenance(_Message):
    """What a conversion used: enough to reproduce it from a recording.

    Attributes
    ----------
    setup : str
    params_toml : str
        The detector parameter file (``io.paramfile`` TOML text).
    table_identity, converter_kind, software_version : str
    t_ns : int
    """

    SCHEMA: ClassVar[str] = "mntes.provenance"

    setup: str
    params_toml: str
    table_identity: str
    converter_kind: str
    software_version: str
    t_ns: int

    def __post_init__(self) -> None:
        _str(self.setup, "setup", NAME_PATTERN)
        for name in ("params_toml", "table_identity", "converter_kind", "software_version"):
            _str(getattr(self, name), name)
        object.__setattr__(self, "t_ns", _int(self.t_ns, "t_ns"))


MESSAGE_TYPES: dict[str, type] = {
    cls.SCHEMA: cls for cls in (CountsChunk, HousekeepingChunk, PowerChunk, StatusMessage, Provenance)
}


def decode(payload: bytes, expected: str | tuple[str, ...] | None = None):
    """Decode any message by its schema name; :class:`SchemaError` on anything wrong."""
    msg = _unpack(payload, expected)
    cls = MESSAGE_TYPES.get(msg["schema"])
    if cls is None:  # a schema in schemas/ without a class here
        raise _error("unknown_schema", f"no message class for schema {msg['schema']!r}")
    return cls._from_map(msg)
