"""msgpack envelope and array codec shared by every message and file.

Conventions (``ARCHITECTURE.md``): every payload is a msgpack map with a
``schema`` name and integer ``version``; numeric arrays travel as raw
little-endian bytes in a map ``{"dtype": "<f8", "shape": [..], "data": b".."}``.

The JSON Schemas in ``schemas/`` (file ``<name>.v<version>.json``) are the one
source of truth for message names and versions: this module reads the current
version of each message from them.
"""

from __future__ import annotations

import functools
import json
import math
from importlib import resources
from typing import Any

import msgpack
import numpy as np

from mntes_stream.errors import SchemaError

__all__ = [
    "ALLOWED_DTYPES",
    "encode_array",
    "decode_array",
    "pack",
    "unpack",
    "schema_versions",
    "current_versions",
    "json_schema",
]

# Explicit little-endian dtypes only; anything else is a schema error.
ALLOWED_DTYPES = frozenset({"<i1", "<i2", "<i4", "<i8", "<u1", "<u2", "<u4", "<u8", "<f4", "<f8", "<c8", "<c16", "|b1", "|u1", "|i1"})
_MAX_ELEMENTS = 1 << 28


def _schema_dir():
    return resources.files("mntes_stream") / "schemas"


@functools.cache
def _schemas() -> dict[tuple[str, int], dict]:
    out = {}
    for entry in _schema_dir().iterdir():
        if not entry.name.endswith(".json"):
            continue
        doc = json.loads(entry.read_text())
        props = doc.get("properties", {})
        name = props.get("schema", {}).get("const")
        version = props.get("version", {}).get("const")
        if name is None or version is None:
            continue
        out[(name, int(version))] = doc
    return out


def schema_versions() -> dict[str, int]:
    """Current (highest) version of each message schema, from ``schemas/``."""
    return dict(current_versions())


@functools.cache
def current_versions() -> dict[str, int]:
    """:func:`schema_versions` itself, shared and cached: read on every message, never to be modified."""
    versions: dict[str, int] = {}
    for name, version in _schemas():
        versions[name] = max(version, versions.get(name, 0))
    return versions


def json_schema(name: str, version: int | None = None) -> dict:
    """The JSON Schema document for a message (current version by default)."""
    version = schema_versions().get(name) if version is None else version
    try:
        return _schemas()[(name, version)]
    except KeyError:
        raise SchemaError(f"no JSON Schema for message {name!r} version {version}") from None


def encode_array(a: np.ndarray) -> dict:
    """Array to ``{"dtype", "shape", "data"}`` with explicit little-endian dtype."""
    a = np.asarray(a)
    dt = a.dtype.newbyteorder("<") if a.dtype.byteorder not in ("|", "<") else a.dtype
    # tobytes() writes C order from any layout: a strided view (a chunk of a larger block) is copied once.
    return {"dtype": dt.str, "shape": list(a.shape), "data": a.astype(dt, copy=False).tobytes()}


def decode_array(d: Any, field: str = "array", dtype: str | None = None, ndim: int | None = None) -> np.ndarray:
    """Inverse of :func:`encode_array`, validating dtype, shape and byte length.

    Returns a read-only view on the message bytes (no copy).
    """
    if not isinstance(d, dict) or set(d) != {"dtype", "shape", "data"}:
        raise SchemaError(f"{field}: expected an array map with dtype, shape, data")
    dt, shape, data = d["dtype"], d["shape"], d["data"]
    if not isinstance(dt, str) or dt not in ALLOWED_DTYPES:
        raise SchemaError(f"{field}: dtype {dt!r} not allowed (little-endian numeric only)")
    if dtype is not None and dt != dtype:
        raise SchemaError(f"{field}: dtype must be {dtype!r}, got {dt!r}")
    if not isinstance(shape, list) or not all(
        isinstance(s, int) and not isinstance(s, bool) and s >= 0 for s in shape
    ):
        raise SchemaError(f"{field}: shape must be a list of non-negative integers")
    if ndim is not None and len(shape) != ndim:
        raise SchemaError(f"{field}: expected {ndim} dimensions, got shape {shape}")
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise SchemaError(f"{field}: data must be bytes")
    # Python ints: numpy's int64 product wraps for hostile shapes like [2**32, 2**32].
    n = math.prod(shape)
    if n > _MAX_ELEMENTS or any(s > _MAX_ELEMENTS for s in shape):
        raise SchemaError(f"{field}: shape {shape} exceeds the limit of {_MAX_ELEMENTS} elements")
    npdt = np.dtype(dt)
    if len(data) != n * npdt.itemsize:
        raise SchemaError(f"{field}: {len(data)} bytes do not match shape {shape} of {dt}")
    try:
        return np.frombuffer(data, dtype=npdt).reshape(tuple(shape))
    except ValueError as exc:  # belt and braces: decoding raises SchemaError and nothing else
        raise SchemaError(f"{field}: {exc}") from None


def pack(schema: str, body: dict) -> bytes:
    """Serialise a message: ``body`` plus ``schema`` and its current ``version``."""
    versions = current_versions()
    if schema not in versions:
        raise SchemaError(f"unknown message schema {schema!r}")
    msg = {"schema": schema, "version": versions[schema]}
    msg.update(body)
    return msgpack.packb(msg, use_bin_type=True)


def unpack(payload: bytes, expected: str | tuple[str, ...] | None = None) -> dict:
    """Parse and check the envelope; raise :class:`SchemaError` on anything wrong.

    Parameters
    ----------
    payload : bytes
    expected : str or tuple of str, optional
        Schema name(s) the caller accepts.
    """
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=True)
    except Exception as exc:  # msgpack raises several unrelated types
        raise SchemaError(f"malformed msgpack: {type(exc).__name__}: {exc}", "malformed") from None
    if not isinstance(msg, dict):
        raise SchemaError(f"message is a {type(msg).__name__}, not a map", "malformed")
    name, version = msg.get("schema"), msg.get("version")
    if not isinstance(name, str) or not isinstance(version, int) or isinstance(version, bool):
        raise SchemaError("message lacks a string 'schema' and an integer 'version'", "malformed")
    if expected is not None:
        names = (expected,) if isinstance(expected, str) else expected
        if name not in names:
            raise SchemaError(f"expected schema {'/'.join(names)}, got {name!r}", "wrong_schema")
    current = current_versions().get(name)
    if current is None:
        raise SchemaError(f"unknown message schema {name!r}", "unknown_schema")
    if version != current:
        raise SchemaError(f"{name}: version {version} not supported (this build speaks version {current})", "wrong_version")
    return msg
