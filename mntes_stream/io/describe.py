"""What the data says about itself: flag bits, units and payload schemas, for files and the wire.

The source is ``schemas/flags.v1.json`` (bit names, meanings, which bits make
power unusable, and units) next to the message schemas; this module reads it
and shapes it for each carrier:

- MCAP: metadata records ``mntes.flags`` (``bit3`` -> ``env_out_of_range: ...``),
  ``mntes.units`` and ``mntes.encoding`` (how payloads are packed)
  (:func:`mcap_metadata`) in every file an ``McapFileWriter`` writes; each
  channel's schema record is its messages' JSON Schema (``io/mcap/writer.py``);
- HDF5: the same as attributes (:func:`flag_attrs`);
- zenoh: the sample encoding ``application/msgpack;schema=mntes.power.v1``
  (:func:`zenoh_encoding`) on every publication and queryable reply, so a
  subscriber knows the schema before decoding.
"""

from __future__ import annotations

import functools
import json
from importlib import resources

__all__ = ["flag_bits", "flags_schema", "units", "mcap_metadata", "flag_attrs", "zenoh_encoding", "FLAGS_METADATA", "UNITS_METADATA",
           "ENCODING_METADATA"]

FLAGS_METADATA = "mntes.flags"
UNITS_METADATA = "mntes.units"
ENCODING_METADATA = "mntes.encoding"
ENVELOPE = ("msgpack map with 'schema' (name) and 'version' (integer); numeric arrays are maps "
            "{dtype: little-endian numpy type string, shape: [ints], data: raw bytes}; JSON Schemas mark msgpack "
            "bin as {'x-msgpack': 'bin'}")
_KIND_SCHEMA = {"counts": "mntes.counts", "hk": "mntes.hk", "power": "mntes.power", "status": "mntes.status",
                "provenance": "mntes.provenance"}


@functools.cache
def _flags_doc() -> dict:
    return json.loads((resources.files("mntes_stream") / "schemas" / "flags.v1.json").read_text())


def flag_bits() -> list[dict]:
    """``[{bit, mask, name, unusable, meaning}, ...]`` in bit order."""
    return [dict(b) for b in _flags_doc()["x-mntes-bits"]]


def flags_schema() -> dict:
    """The whole of ``schemas/flags.v1.json``."""
    return json.loads(json.dumps(_flags_doc()))


def units() -> dict[str, str]:
    """Unit of each field / sensor (``p_opt_w``: ``W ...``)."""
    return dict(_flags_doc()["x-mntes-units"])


@functools.cache
def _mcap_metadata() -> dict[str, dict[str, str]]:
    flags = {f"bit{b['bit']}": f"{b['name']}: {b['meaning']}" + (" (power unusable)" if b["unusable"] else "")
             for b in flag_bits()}
    flags["dtype"] = "uint16 bitmask, bit n has mask 1 << n; field 'flags' of mntes.power"
    flags["schema"] = json.dumps(_flags_doc(), separators=(",", ":"))
    # The message schemas themselves are the channels' schema records: one copy each, only those used
    # (all of them in every file would cost ~20 kB a file).
    encoding = {"envelope": ENVELOPE, "channels": "message encoding msgpack; each channel's schema (encoding "
                "jsonschema) is the JSON Schema of its messages, named by the channel metadata mntes.schema"}
    return {FLAGS_METADATA: flags, UNITS_METADATA: units(), ENCODING_METADATA: encoding}


def mcap_metadata() -> dict[str, dict[str, str]]:
    """The ``mntes.flags``, ``mntes.units`` and ``mntes.encoding`` MCAP metadata records (str -> str)."""
    return {k: dict(v) for k, v in _mcap_metadata().items()}


def flag_attrs() -> dict[str, str]:
    """HDF5 attributes describing the flag bits (``flag_bit3`` = ``env_out_of_range: ...``) and the whole table
    (``flag_bits_json``: ``[{bit, mask, name, unusable, meaning}, ...]``)."""
    out = {f"flag_bit{b['bit']}": f"{b['name']}: {b['meaning']}" + (" (power unusable)" if b["unusable"] else "")
           for b in flag_bits()}
    out["flag_bits_json"] = json.dumps(flag_bits())
    return out


@functools.cache
def zenoh_encoding(key: str) -> str:
    """``application/msgpack;schema=<name>.v<version>`` for an mntes key (plain msgpack for a foreign one).

    msgpack is not one of zenoh's predefined encodings, so the whole string is the encoding's text; the
    ``schema=`` parameter names the file ``schemas/<name without mntes.>.v<version>.json``.
    """
    from mntes_stream.io import keys
    from mntes_stream.io.codec import schema_versions

    name = _KIND_SCHEMA.get(keys.kind_of(key))
    if name is None:
        return "application/msgpack"
    return f"application/msgpack;schema={name}.v{schema_versions()[name]}"
