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

from dataclasses import dataclass, field, fields
from typing import Any, ClassVar

import numpy as np

from mntes_stream.core.align import sample_times_ns
from mntes_stream.errors import SCHEMA_REASONS, SchemaError
from mntes_stream.io import fields as fc
from mntes_stream.io.fields import SAMPLE_RATE_RANGE_HZ
from mntes_stream.io.keys import NAME_PATTERN
from mntes_stream.io.message_base import MessageBase, detector_ids_for, unpack_payload

__all__ = [
    "REASONS",
    "SENSOR_UNITS",
    "PER_CHANNEL_SENSORS",
    "SAMPLE_RATE_RANGE_HZ",
    "CountsChunk",
    "HousekeepingChunk",
    "PowerChunk",
    "StatusMessage",
    "Provenance",
    "MESSAGE_TYPES",
    "decode",
    "detector_ids_for",
]

# Why a message was rejected; the keys of StatusMessage.bad_messages.
REASONS = SCHEMA_REASONS
SENSOR_UNITS = {"t_bath": "K", "b_field": "T", "bias": "V", "readout_flags": "flags"}
# Per channel of one (board, module): bias (RMS volts) and the board's readout flags (a flags.v1 bitmask held
# from each reading to the next: tuning state, rails, housekeeping gone stale).
PER_CHANNEL_SENSORS = frozenset({"bias", "readout_flags"})

# --- messages --------------------------------------------------------------------------


@dataclass(frozen=True, eq=False)
class CountsChunk(MessageBase):
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
    detector_ids : tuple of str, length n_ch, optional
        The rows' detector ids when the source names them (``dfmux-bridge``: the names the boards' hardware map
        stores); absent: ``core.ids.detector_id(board, module, channel)``. The power carries the same ids.
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
    detector_ids: tuple | None = None

    @classmethod
    def unchecked(cls, **values):
        """As :meth:`MessageBase.unchecked`; ``detector_ids`` may be left out (absent: the b/m/c ids)."""
        values.setdefault("detector_ids", None)
        return super().unchecked(**values)

    def __post_init__(self) -> None:
        fc.as_str(self.setup, "setup", NAME_PATTERN)
        for name in ("board", "module", "seq", "t_pub_ns"):
            object.__setattr__(self, name, fc.as_int(getattr(self, name), name))
        ch = fc.as_channels(self.channels)
        if self.detector_ids is not None:
            object.__setattr__(self, "detector_ids", fc.as_detector_ids(
                self.detector_ids, detector_ids_for(self.board, self.module, ch)))
        ci = fc.as_array(self.counts_i, "counts_i", "<i4", 2)
        cq = fc.as_array(self.counts_q, "counts_q", "<i4", 2)
        if ci.shape != cq.shape or ci.shape[0] != ch.size:
            raise SchemaError(f"counts_i {ci.shape} and counts_q {cq.shape} must both be (n_ch={ch.size}, n_samp)")
        object.__setattr__(self, "channels", ch)
        object.__setattr__(self, "counts_i", ci)
        object.__setattr__(self, "counts_q", cq)
        fc.check_times(self, ci.shape[1])

    @property
    def n_samples(self) -> int:
        return int(self.counts_i.shape[1])

    def row_ids(self) -> tuple:
        """The rows' detector ids: :attr:`detector_ids`, or the b/m/c ids of the channels."""
        return self.detector_ids if self.detector_ids is not None else \
            detector_ids_for(self.board, self.module, self.channels)

    def times_ns(self) -> np.ndarray:
        """Sample times, int64 (n_samp,)."""
        if self.t_ns is not None:
            return self.t_ns
        return sample_times_ns(self.t0_ns, self.sample_rate_hz, self.n_samples)


@dataclass(frozen=True, eq=False)
class HousekeepingChunk(MessageBase):
    """Readings of one housekeeping sensor.

    Attributes
    ----------
    setup : str
    sensor : {"t_bath", "b_field", "bias", "readout_flags"}
    seq : int
    t_ns : ndarray of int64, shape (n,), strictly increasing
    value : ndarray of float64, shape (n,), or (n, n_ch) per channel (``PER_CHANNEL_SENSORS``)
        Non-finite entries mark failed readings. ``readout_flags``: each channel's flags.v1 bits from that
        reading until the next (a step, never interpolated).
    unit : str
        ``SENSOR_UNITS[sensor]`` ("K", "T", "V": SI, bias is RMS volts; "flags" for readout_flags).
    board, module : int, per-channel sensors only
    channels : ndarray of int32, shape (n_ch,), per-channel sensors only
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
        fc.as_str(self.setup, "setup", NAME_PATTERN)
        if self.sensor not in SENSOR_UNITS:
            raise SchemaError(f"sensor {self.sensor!r} not one of {sorted(SENSOR_UNITS)}")
        if self.unit != SENSOR_UNITS[self.sensor]:
            raise SchemaError(f"{self.sensor} unit must be {SENSOR_UNITS[self.sensor]!r}, got {self.unit!r}")
        object.__setattr__(self, "seq", fc.as_int(self.seq, "seq"))
        t = fc.as_array(self.t_ns, "t_ns", "<i8", 1)
        if t.size and (int(t.min()) < 0 or np.any(np.diff(t) <= 0)):
            raise SchemaError("t_ns must be >= 0 and strictly increasing")
        per_channel = self.sensor in PER_CHANNEL_SENSORS
        v = fc.as_array(self.value, "value", "<f8", 2 if per_channel else 1)
        if v.shape[0] != t.size:
            raise SchemaError(f"value has {v.shape[0]} rows for {t.size} times")
        if per_channel:
            if self.board is None or self.module is None or self.channels is None:
                raise SchemaError(f"{self.sensor} readings need board, module and channels")
            object.__setattr__(self, "board", fc.as_int(self.board, "board"))
            object.__setattr__(self, "module", fc.as_int(self.module, "module"))
            ch = fc.as_channels(self.channels)
            if v.shape[1] != ch.size:
                raise SchemaError(f"{self.sensor} value has {v.shape[1]} columns for {ch.size} channels")
            object.__setattr__(self, "channels", ch)
        elif self.board is not None or self.module is not None or self.channels is not None:
            raise SchemaError(f"{self.sensor} readings take no board/module/channels")
        object.__setattr__(self, "t_ns", t)
        object.__setattr__(self, "value", v)


@dataclass(frozen=True, eq=False)
class PowerChunk(MessageBase):
    """Optical power of one module chunk (the converter's output).

    Attributes
    ----------
    setup : str
    board, module : int
    channels : ndarray of int32, shape (n_ch,)
    detector_ids : tuple of str, length n_ch
        ``core.ids.detector_id(board, module, channel)`` of each row, or the source counts chunk's
        ``detector_ids`` (the boards' names).
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
    late : bool or None
        True: converted late, after being set aside under overload (older than the
        stream's live power); None (absent on the wire): converted live.
    sigma_p_w : ndarray of float32, shape (n_ch, n_samp), or None
        Per-sample power uncertainty from the readout noise (``core.uncertainty``),
        NaN where the power is NaN; None (absent on the wire): not computed.
    """

    SCHEMA: ClassVar[str] = "mntes.power"
    _ARRAYS: ClassVar[dict] = {"channels": ("<i4", 1), "p_opt_w": ("<f8", 2), "flags": ("<u2", 2), "t_ns": ("<i8", 1),
                               "sigma_p_w": ("<f4", 2)}
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
    late: bool | None = None
    sigma_p_w: np.ndarray | None = None

    @classmethod
    def unchecked(cls, **values):
        """As :meth:`MessageBase.unchecked`; ``sigma_p_w`` may be left out (optional: callers from before it stay valid)."""
        values.setdefault("sigma_p_w", None)
        return super().unchecked(**values)

    def __post_init__(self) -> None:
        fc.as_str(self.setup, "setup", NAME_PATTERN)
        if self.late is not None and not isinstance(self.late, bool):
            raise SchemaError("late must be true, or absent")
        if self.sigma_p_w is not None:
            sp = fc.as_array(self.sigma_p_w, "sigma_p_w", "<f4", 2)
            if sp.shape != np.shape(self.p_opt_w):
                raise SchemaError(f"sigma_p_w {sp.shape} must have the shape of p_opt_w {np.shape(self.p_opt_w)}")
            if np.any(sp < 0) or np.any(np.isinf(sp)):
                raise SchemaError("sigma_p_w must be finite and >= 0 (or NaN where there is no power)")
            object.__setattr__(self, "sigma_p_w", sp)
        for name in ("board", "module", "seq", "source_t_pub_ns", "t_pub_ns"):
            object.__setattr__(self, name, fc.as_int(getattr(self, name), name))
        fc.as_str(self.table_identity, "table_identity")
        fc.as_str(self.converter_kind, "converter_kind")
        ch = fc.as_channels(self.channels)
        if not isinstance(self.detector_ids, (list, tuple)):
            raise SchemaError("detector_ids must be a list of strings")
        ids = tuple(self.detector_ids)
        own = detector_ids_for(self.board, self.module, ch)
        if ids != own:  # names (from the counts): safe and distinct
            ids = fc.as_detector_ids(ids, own)
        p = fc.as_array(self.p_opt_w, "p_opt_w", "<f8", 2)
        f = fc.as_array(self.flags, "flags", "<u2", 2)
        if p.shape != f.shape or p.shape[0] != ch.size:
            raise SchemaError(f"p_opt_w {p.shape} and flags {f.shape} must both be (n_ch={ch.size}, n_samp)")
        object.__setattr__(self, "channels", ch)
        object.__setattr__(self, "detector_ids", ids)
        object.__setattr__(self, "p_opt_w", p)
        object.__setattr__(self, "flags", f)
        fc.check_times(self, p.shape[1])

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
        raise SchemaError(f"{name} must be a map")
    return {fc.as_str(k, f"{name} key"): fc.as_int(v, f"{name}[{k}]") for k, v in value.items()}


@dataclass(frozen=True, eq=False)
class StatusMessage(MessageBase):
    """Converter health, published periodically (schema ``status.v1.json``).

    Counters are cumulative since start; ``rate_*`` and ``latency_*`` cover
    the last interval (latency: source publication to power publication;
    arrival: source publication to the converter's receipt, the source's and
    the link's share of it; None when no chunk was converted or received).
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
    arrival_p50_ms: float | None = None
    arrival_p99_ms: float | None = None
    last_error: str = ""
    owns: dict = field(default_factory=dict)
    chunks_missing: int = 0
    chunks_shed: int = 0
    chunks_late: int = 0
    chunks_rejected: int = 0
    chunks_set_aside: int = 0
    ledger: dict = field(default_factory=dict)
    began_at: dict = field(default_factory=dict)
    conflicts: dict = field(default_factory=dict)

    # Absent from statuses of earlier versions of the converter: decoded with their defaults.
    _LATER: ClassVar[frozenset] = frozenset(
        {"owns", "chunks_missing", "chunks_shed", "chunks_late", "chunks_rejected", "chunks_set_aside", "ledger",
         "arrival_p50_ms", "arrival_p99_ms", "began_at", "conflicts"})
    # The fields by kind (rates >= 0, latencies that may be negative, counters), for readers of statuses too.
    RATES: ClassVar[tuple[str, ...]] = ("uptime_s", "interval_s", "rate_chunks_per_s", "rate_msamples_per_s")
    LATENCIES: ClassVar[tuple[str, ...]] = ("latency_p50_ms", "latency_p99_ms", "latency_max_ms", "arrival_p50_ms",
                                            "arrival_p99_ms")
    COUNTERS: ClassVar[tuple[str, ...]] = (
        "t_ns", "chunks_received", "chunks_converted", "chunks_pending", "samples_converted", "chunks_lost",
        "chunks_duplicated", "chunks_out_of_order", "hk_received", "hk_stale_samples", "hk_missing_samples",
        "unknown_channel_samples", "chunks_missing", "chunks_shed", "chunks_late", "chunks_rejected",
        "chunks_set_aside",
    )

    def __post_init__(self) -> None:
        fc.as_str(self.setup, "setup", NAME_PATTERN)
        fc.as_str(self.service, "service")
        fc.as_str(self.last_error, "last_error")
        for name in self.RATES:
            v = fc.as_float(getattr(self, name), name)
            if v < 0:
                raise SchemaError(f"{name} must be >= 0")
            object.__setattr__(self, name, v)
        for name in self.LATENCIES:  # may be negative when clocks disagree
            object.__setattr__(self, name, fc.as_float(getattr(self, name), name, optional=True))
        for name in self.COUNTERS:
            object.__setattr__(self, name, fc.as_int(getattr(self, name), name))
        object.__setattr__(self, "bad_messages", _count_map(self.bad_messages, "bad_messages"))
        object.__setattr__(self, "flag_counts", _count_map(self.flag_counts, "flag_counts"))
        if not isinstance(self.hk_age_s, dict):
            raise SchemaError("hk_age_s must be a map")
        object.__setattr__(
            self, "hk_age_s", {fc.as_str(k, "hk_age_s key"): float(fc.as_float(v, f"hk_age_s[{k}]")) for k, v in self.hk_age_s.items()}
        )
        object.__setattr__(self, "owns", _owns_map(self.owns))
        object.__setattr__(self, "ledger", _ledger_map(self.ledger))
        object.__setattr__(self, "began_at", _count_map(self.began_at, "began_at"))
        object.__setattr__(self, "conflicts", _count_map(self.conflicts, "conflicts"))

    def _body(self) -> dict:
        # Optional latencies travel as nil (the schema allows null), not absent; an unsharded converter says no owns,
        # one that took every stream from its first chunk (or from a checkpoint) no began_at, and one whose streams
        # each come from one publisher no conflicts.
        return {f.name: getattr(self, f.name) for f in fields(self)
                if f.name not in ("owns", "began_at", "conflicts") or getattr(self, f.name)}

    @classmethod
    def _from_map(cls, msg: dict):
        missing = {f.name for f in fields(cls)} - set(msg) - cls._LATER
        if missing:
            raise SchemaError(f"{cls.SCHEMA}: missing field(s) {sorted(missing)}")
        return super()._from_map(msg)


@dataclass(frozen=True, eq=False)
class Provenance(MessageBase):
    """What a conversion used: enough to reproduce it from a recording.

    Attributes
    ----------
    setup : str
    params_toml : str
        The detector parameter file (``io.paramfile`` TOML text).
    table_identity, converter_kind, software_version : str
    t_ns : int
    owns : dict
        The part of the focal plane a converter shard covers (empty: all of it).
    noise : dict
        The readout noise behind each sample's sigma_P and the LOW_RESPONSIVITY rule
        (``core.uncertainty.NoiseModel.provenance``); empty (absent on the wire): no sigma_P.
    """

    SCHEMA: ClassVar[str] = "mntes.provenance"

    setup: str
    params_toml: str
    table_identity: str
    converter_kind: str
    software_version: str
    t_ns: int
    owns: dict = field(default_factory=dict)
    noise: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        fc.as_str(self.setup, "setup", NAME_PATTERN)
        for name in ("params_toml", "table_identity", "converter_kind", "software_version"):
            fc.as_str(getattr(self, name), name)
        object.__setattr__(self, "t_ns", fc.as_int(self.t_ns, "t_ns"))
        object.__setattr__(self, "owns", _owns_map(self.owns))
        if not isinstance(self.noise, dict) or not all(isinstance(k, str) for k in self.noise):
            raise SchemaError("noise must be a map with string keys")

    def _body(self) -> dict:
        body = super()._body()
        for name in ("owns", "noise"):  # absent when empty: the bytes of before
            if not getattr(self, name):
                body.pop(name, None)
        return body


def _ledger_map(value) -> dict:
    """A status's ledger: stream -> columns (ints, or maps of reason -> int for shed and rejected)."""
    if not isinstance(value, dict):
        raise SchemaError("ledger must be a map")
    out = {}
    for stream, cols in value.items():
        if not isinstance(cols, dict):
            raise SchemaError(f"ledger[{stream}] must be a map")
        out[fc.as_str(stream, "ledger key")] = {
            fc.as_str(k, "ledger column"): _count_map(v, f"ledger[{stream}][{k}]") if isinstance(v, dict)
            else fc.as_int(v, f"ledger[{stream}][{k}]") for k, v in cols.items()}
    return out


def _owns_map(value) -> dict:
    """What part of the focal plane a converter owns (status, provenance): str keys, scalar or list values."""
    if not isinstance(value, dict):
        raise SchemaError("owns must be a map")
    out = {}
    for k, v in value.items():
        items = v if isinstance(v, (list, tuple)) else [v]
        if not all(isinstance(x, (str, int, float, bool)) for x in items):
            raise SchemaError(f"owns[{k}] must be a string, number, or list of them")
        out[fc.as_str(k, "owns key")] = list(v) if isinstance(v, (list, tuple)) else v
    return out


MESSAGE_TYPES: dict[str, type] = {
    cls.SCHEMA: cls for cls in (CountsChunk, HousekeepingChunk, PowerChunk, StatusMessage, Provenance)
}


def decode(payload: bytes, expected: str | tuple[str, ...] | None = None):
    """Decode any message by its schema name; :class:`SchemaError` on anything wrong."""
    msg = unpack_payload(payload, expected)
    cls = MESSAGE_TYPES.get(msg["schema"])
    if cls is None:  # a schema in schemas/ without a class here
        raise SchemaError(f"no message class for schema {msg['schema']!r}", "unknown_schema")
    return cls._from_map(msg)
