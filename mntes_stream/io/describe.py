"""What the data says about itself: flag bits, units and payload schemas, for files and the wire.

The source is ``schemas/flags.v1.json`` (bit names, meanings, which bits make
power unusable, and units) next to the message schemas; this module reads it
and shapes it for each carrier:

- MCAP: metadata records ``mntes.flags`` (``bit3`` -> ``env_out_of_range: ...``)
  and ``mntes.units`` (:func:`mcap_metadata`), written by every recorder file;
- HDF5: the same as attributes (:func:`flag_attrs`);
- zenoh: the sample encoding ``application/msgpack;mntes.power.v1``
  (:func:`zenoh_encoding`), so a subscriber knows the schema before decoding.
"""

from __future__ import annotations

import functools
import json
from importlib import resources

__all__ = ["flag_bits", "units", "mcap_metadata", "flag_attrs", "zenoh_encoding", "FLAGS_METADATA", "UNITS_METADATA"]

FLAGS_METADATA = "mntes.flags"
UNITS_METADATA = "mntes.units"
_KIND_SCHEMA = {"counts": "mntes.counts", "hk": "mntes.hk", "power": "mntes.power", "status": "mntes.status",
                "provenance": "mntes.provenance"}


@functools.cache
def _flags_doc() -> dict:
    return json.loads((resources.files("mntes_stream") / "schemas" / "flags.v1.json").read_text())


def flag_bits() -> list[dict]:
    """``[{bit, mask, name, unusable, meaning}, ...]`` in bit order."""
    return [dict(b) for b in _flags_doc()["x-mntes-bits"]]


def units() -> dict[str, str]:
    """Unit of each field / sensor (``p_opt_w``: ``W ...``)."""
    return dict(_flags_doc()["x-mntes-units"])


def mcap_metadata() -> dict[str, dict[str, str]]:
    """The ``mntes.flags`` and ``mntes.units`` MCAP metadata records (str -> str)."""
    flags = {f"bit{b['bit']}": f"{b['name']}: {b['meaning']}" + (" (power unusable)" if b["unusable"] else "")
             for b in flag_bits()}
    flags["dtype"] = "uint16 bitmask, bit n has mask 1 << n; field 'flags' of mntes.power"
    flags["schema"] = json.dumps(_flags_doc(), separators=(",", ":"))
    return {FLAGS_METADATA: flags, UNITS_METADATA: units()}


def flag_attrs() -> dict[str, str]:
    """HDF5 attributes describing the flag bits (``flag_bit3`` = ``env_out_of_range: ...``) and the whole table."""
    out = {f"flag_bit{b['bit']}": f"{b['name']}: {b['meaning']}" for b in flag_bits()}
    out["flag_bits_json"] = json.dumps(flag_bits())
    return out


@functools.cache
def zenoh_encoding(key: str) -> str:
    """``application/msgpack;<schema>.v<version>`` for an mntes key (plain msgpack for a foreign one)."""
    from mntes_stream.io import keys
    from mntes_stream.io.codec import schema_versions

    name = _KIND_SCHEMA.get(keys.kind_of(key))
    if name is None:
        return "application/msgpack"
    return f"application/msgpack;{name}.v{schema_versions()[name]}"
