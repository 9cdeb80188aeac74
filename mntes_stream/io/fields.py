"""Checks of message fields: each coerces a decoded value or raises :class:`SchemaError` (reason ``invalid``)."""

from __future__ import annotations

import math
import operator
import re
from typing import Any

import numpy as np

from mntes_stream.core.align import last_sample_offset_ns
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io.codec import json_schema

# Sample rates a chunk may declare (from the schema, the one source): beyond,
# sample times lose meaning (1e-300 Hz puts sample 1 beyond int64 ns).
_RATE_SCHEMA = json_schema("mntes.counts")["properties"]["sample_rate_hz"]
SAMPLE_RATE_RANGE_HZ = (float(_RATE_SCHEMA["minimum"]), float(_RATE_SCHEMA["maximum"]))
INT64_MAX = (1 << 63) - 1


def as_int(value: Any, name: str, lo: int = 0, hi: int = INT64_MAX) -> int:
    if isinstance(value, (bool, np.bool_)):
        raise SchemaError(f"{name} must be an integer, got a bool")
    try:
        v = operator.index(value)
    except TypeError:
        raise SchemaError(f"{name} must be an integer, got {type(value).__name__}") from None
    if not lo <= v <= hi:
        raise SchemaError(f"{name} = {v} outside [{lo}, {hi}]")
    return v


def as_str(value: Any, name: str, pattern: re.Pattern | None = None) -> str:
    if not isinstance(value, str):
        raise SchemaError(f"{name} must be a string, got {type(value).__name__}")
    if pattern is not None and not pattern.match(value):
        raise SchemaError(f"{name} {value!r} does not match {pattern.pattern}")
    return value


def as_float(value: Any, name: str, positive: bool = False, optional: bool = False) -> float | None:
    if value is None and optional:
        return None
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise SchemaError(f"{name} must be a number, got {type(value).__name__}")
    v = float(value)
    if not math.isfinite(v) or (positive and v <= 0):
        raise SchemaError(f"{name} = {v} must be finite{' and > 0' if positive else ''}")
    return v


def as_array(value: Any, name: str, dtype: str, ndim: int | tuple[int, ...]) -> np.ndarray:
    """Coerce to the wire dtype: integers only into integer types, in range."""
    a = np.asarray(value)
    ndims = (ndim,) if isinstance(ndim, int) else ndim
    if a.ndim not in ndims:
        raise SchemaError(f"{name}: expected {' or '.join(map(str, ndims))} dimensions, got shape {a.shape}")
    target = np.dtype(dtype)
    if a.dtype == target:
        return a
    if target.kind in "iu":
        if a.dtype.kind not in "iu":
            raise SchemaError(f"{name}: integer array required, got dtype {a.dtype}")
        info = np.iinfo(target)
        if a.size and (int(a.min()) < info.min or int(a.max()) > info.max):
            raise SchemaError(f"{name}: values outside the range of {target}")
    elif a.dtype.kind not in "iuf":
        raise SchemaError(f"{name}: real numeric array required, got dtype {a.dtype}")
    return np.ascontiguousarray(a, dtype=target)


_CHANNELS_OK: set[bytes] = set()  # channel lists already found valid: a stream repeats its list every chunk


def as_channels(value: Any) -> np.ndarray:
    ch = as_array(value, "channels", "<i4", 1)
    raw = ch.tobytes()
    if raw in _CHANNELS_OK:
        return ch
    if ch.size and int(ch.min()) < 0:
        raise SchemaError("channels must be >= 0")
    if np.unique(ch).size != ch.size:
        raise SchemaError("channels must be distinct")
    if len(_CHANNELS_OK) >= 4096:
        _CHANNELS_OK.clear()
    _CHANNELS_OK.add(raw)
    return ch


def check_times(obj, n_samp: int) -> None:
    """Check the (t0_ns, sample_rate_hz) xor t_ns convention on a chunk."""
    if obj.t_ns is not None:
        if obj.t0_ns is not None or obj.sample_rate_hz is not None:
            raise SchemaError("give either t_ns or (t0_ns, sample_rate_hz), not both")
        t = as_array(obj.t_ns, "t_ns", "<i8", 1)
        if t.size != n_samp:
            raise SchemaError(f"t_ns has {t.size} entries for {n_samp} samples")
        if t.size and (int(t.min()) < 0 or np.any(np.diff(t) < 0)):
            raise SchemaError("t_ns must be >= 0 and non-decreasing")
        object.__setattr__(obj, "t_ns", t)
    else:
        if obj.t0_ns is None or obj.sample_rate_hz is None:
            raise SchemaError("t0_ns and sample_rate_hz (or t_ns) are required")
        t0 = as_int(obj.t0_ns, "t0_ns")
        rate = as_float(obj.sample_rate_hz, "sample_rate_hz", positive=True)
        lo, hi = SAMPLE_RATE_RANGE_HZ
        if not lo <= rate <= hi:
            raise SchemaError(f"sample_rate_hz = {rate} outside [{lo:g}, {hi:g}]")
        try:
            last = t0 + last_sample_offset_ns(rate, n_samp)
        except ConfigError as exc:
            raise SchemaError(str(exc)) from None
        if last > INT64_MAX:
            raise SchemaError(f"the last of {n_samp} samples from t0_ns = {t0} at {rate} Hz is beyond int64 ns")
        object.__setattr__(obj, "t0_ns", t0)
        object.__setattr__(obj, "sample_rate_hz", rate)


def as_detector_ids(value: Any, own: tuple) -> tuple:
    """Detector ids of rows whose b/m/c ids are ``own``: distinct safe names (``core.ids.check_detector_id``), an
    id of the b<B>m<M>c<C> form only the row's own (never another channel's), as a tuple."""
    from mntes_stream.core.ids import DETECTOR_ID_PATTERN, is_channel_id

    if not isinstance(value, (list, tuple)):
        raise SchemaError("detector_ids must be a list of strings")
    ids = tuple(value)
    if len(ids) != len(own):
        raise SchemaError(f"detector_ids has {len(ids)} names for {len(own)} channels")
    if not all(isinstance(d, str) and DETECTOR_ID_PATTERN.match(d) for d in ids):
        raise SchemaError("detector_ids must be safe names (letters, digits, '_', '.', '-'; up to 128 characters)")
    if len(set(ids)) != len(ids):
        raise SchemaError("detector_ids must be distinct")
    if any(d != o and is_channel_id(d) for d, o in zip(ids, own)):
        raise SchemaError("detector_ids do not match board/module/channels (a b<B>m<M>c<C> id of another channel)")
    return ids
