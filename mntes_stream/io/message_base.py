"""What every message class shares: envelope unpacking, field order, encode/decode (``io.messages``)."""

from __future__ import annotations

import functools
from dataclasses import fields
from typing import Any, ClassVar

import numpy as np

from mntes_stream.core.ids import detector_id
from mntes_stream.errors import SchemaError
from mntes_stream.io.codec import decode_array, encode_array, pack, unpack

__all__ = ["MessageBase", "unpack_payload", "detector_ids_for", "_time_body"]


def unpack_payload(payload: Any, expected=None) -> dict:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise SchemaError(f"payload must be bytes, got {type(payload).__name__}", "malformed")
    msg = unpack(bytes(payload))
    # Checked after the envelope so an unknown name or version is reported as such.
    names = (expected,) if isinstance(expected, str) else expected
    if names is not None and msg["schema"] not in names:
        raise SchemaError(f"expected schema {'/'.join(names)}, got {msg['schema']!r}", "wrong_schema")
    return msg


@functools.cache
def _field_names(cls) -> frozenset[str]:
    return frozenset(f.name for f in fields(cls))


@functools.cache
def _field_order(cls) -> tuple[str, ...]:
    return tuple(f.name for f in fields(cls))


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


class MessageBase:
    """Shared encode/decode machinery; subclasses are frozen dataclasses."""

    SCHEMA: ClassVar[str]
    _ARRAYS: ClassVar[dict[str, tuple[str, int | tuple[int, ...]]]] = {}
    # Fields that may be absent on the wire although the constructor takes them positionally.
    _OPTIONAL: ClassVar[tuple[str, ...]] = ()

    def _body(self) -> dict:
        body = {}
        for name in _field_order(type(self)):
            value = getattr(self, name)
            if value is None:
                continue
            if name in self._ARRAYS:
                value = encode_array(value)
            elif isinstance(value, tuple):
                value = list(value)
            body[name] = value
        return body

    @classmethod
    def unchecked(cls, **values):
        """Every field, from values this process made and checked itself (the converter's own power: the checks
        would cost as much as the encoding); anything from outside goes through the constructor or from_bytes."""
        if set(values) != _field_names(cls):
            raise SchemaError(f"{cls.SCHEMA}: unchecked() takes every field ({', '.join(_field_order(cls))})")
        obj = object.__new__(cls)
        obj.__dict__.update(values)
        return obj

    def to_bytes(self) -> bytes:
        """msgpack bytes of this message (envelope with schema name and version)."""
        return pack(self.SCHEMA, self._body())

    @classmethod
    def from_bytes(cls, payload: bytes):
        """Decode and validate; raises :class:`SchemaError` (with ``.reason``)."""
        return cls._from_map(unpack_payload(payload, cls.SCHEMA))

    @classmethod
    def _from_map(cls, msg: dict):
        names = _field_names(cls)
        extra = set(msg) - names - {"schema", "version"}
        if extra:
            raise SchemaError(f"{cls.SCHEMA}: unknown field(s) {sorted(map(str, extra))}")
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
                    raise SchemaError(f"{cls.SCHEMA}: {exc}") from None
            kwargs[name] = value
        for name in cls._OPTIONAL:
            kwargs.setdefault(name, None)
        try:
            return cls(**kwargs)
        except SchemaError as exc:
            raise SchemaError(f"{cls.SCHEMA}: {exc}", exc.reason) from None
        except TypeError as exc:  # missing required fields
            raise SchemaError(f"{cls.SCHEMA}: {exc}") from None
