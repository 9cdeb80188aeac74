"""What a recorded payload claims to be, read without trusting it; the file-level names and records."""

from __future__ import annotations

import json
import math
import socket
import time
from collections.abc import Mapping
from dataclasses import dataclass

import msgpack

from mntes_stream import __version__
from mntes_stream.errors import SchemaError

MESSAGE_ENCODING = "msgpack"
SCHEMA_ENCODING = "jsonschema"
PROVENANCE_SCHEMA = "mntes.provenance"
PROVENANCE_ATTACHMENT = "mntes.provenance.msgpack"
RECORDING_METADATA = "mntes.recording"



@dataclass(frozen=True, slots=True)
class Envelope:
    """What the recorder needs to know about a payload without trusting it.

    ``late`` is a power chunk's ``late: true``; ``samples`` the elements of its
    ``counts_i`` (counts) or ``p_opt_w`` (power) array as its ``shape`` claims
    (0 if absent): the recorder's samples, read without touching the data.
    """

    schema: str  # "" if the payload is not an mntes envelope
    version: int  # 0 if unknown
    publish_time_ns: int | None
    seq: int | None
    problem: str  # "" if the envelope is well formed
    late: bool = False
    samples: int = 0


_MAX_SAMPLES = 1 << 28  # as io.codec: a larger shape claims more than any valid array holds


def peek_envelope(payload: bytes) -> Envelope:
    """Read ``schema``, ``version``, ``t_pub_ns``/``t_ns``, ``seq``, ``late`` and an array's shape; never raises.

    One ``msgpack.unpackb`` with ``raw=True``: msgpack's C parser checks that
    the payload is one whole msgpack document, and nothing is decoded further
    (no text, no arrays; the array bytes are not looked at). Measured here:
    1.4 us a 128 x 20 counts chunk and 3.3 us a power chunk, where a
    key-by-key ``Unpacker`` that skips the values took 5-6 us and the full
    decode with text plus the ``late`` lookup before took 3.5 and 9. A payload
    that is not one whole msgpack map (truncated, trailing bytes, another
    type) has a ``problem``; what is inside the values is not checked (the
    converter validates what it converts).
    """
    try:
        msg = msgpack.unpackb(payload, raw=True, strict_map_key=False)
    except Exception as exc:  # msgpack raises several unrelated types; an unhashable key raises TypeError
        return Envelope("", 0, None, None, f"malformed msgpack ({type(exc).__name__})")
    if type(msg) is not dict:
        return Envelope("", 0, None, None, f"payload is a {type(msg).__name__}, not a map")
    name, version = msg.get(b"schema"), msg.get(b"version")
    if type(name) is not bytes or type(version) is not int:
        return Envelope("", 0, None, None, "no string 'schema' and integer 'version'")
    try:
        name = name.decode()
    except UnicodeDecodeError:
        return Envelope("", 0, None, None, "no string 'schema' and integer 'version'")
    t_pub = msg.get(b"t_pub_ns")
    if type(t_pub) is not int:
        t_pub = msg.get(b"t_ns")
        if type(t_pub) is not int:
            t_pub = None
    seq = msg.get(b"seq")
    array = msg.get(b"counts_i") or msg.get(b"p_opt_w")
    return Envelope(name, version, t_pub, seq if type(seq) is int else None, "", msg.get(b"late") is True,
                    _elements(array.get(b"shape")) if type(array) is dict else 0)


def _elements(shape) -> int:
    """Elements a ``shape`` claims (0 unless a list of small non-negative ints)."""
    if type(shape) is not list or not shape or not all(type(s) is int and 0 <= s <= _MAX_SAMPLES for s in shape):
        return 0
    n = math.prod(shape)
    return n if n <= _MAX_SAMPLES else 0


def derived_channel(payload: bytes) -> tuple[str, str, int] | None:
    """``(key, schema, version)`` that an mntes payload names (its setup, board/module or sensor), or None.

    Used for messages whose channel record is lost: the key a publisher uses
    is spelled by :mod:`mntes_stream.io.keys` from exactly these fields.
    Never raises.
    """
    from mntes_stream.io import keys

    env = peek_envelope(payload)
    if env.problem or not env.schema.startswith(keys.PREFIX + "."):
        return None
    kind = env.schema[len(keys.PREFIX) + 1:]
    try:
        msg = msgpack.unpackb(payload, raw=False, strict_map_key=False)
        setup = msg["setup"]
        if kind in ("counts", "power"):
            b, m = msg["board"], msg["module"]
            if not (_is_int(b) and _is_int(m)):
                return None
            key = keys.counts_key(setup, b, m) if kind == "counts" else keys.power_key(setup, b, m)
        elif kind == "hk":
            sensor = msg["sensor"]
            if not isinstance(sensor, str) or "/" in sensor or "*" in sensor:
                return None
            b, m = msg.get("board"), msg.get("module")
            if sensor in ("bias", "readout_flags") and not (_is_int(b) and _is_int(m)):
                return None
            key = keys.hk_key(setup, keys.hk_sensor(sensor, b, m))
        elif kind == "status":
            service = msg["service"]
            if not isinstance(service, str) or not keys.NAME_PATTERN.fullmatch(service):
                return None
            key = keys.status_key(setup, service)
        elif kind == "provenance":
            key = keys.provenance_key(setup)
        else:
            return None
    except Exception:  # a payload that claims a schema but lacks its fields: nothing to derive
        return None
    return key, env.schema, env.version


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def schema_text(name: str, version: int) -> bytes | None:
    from mntes_stream.io.codec import json_schema

    try:
        return json.dumps(json_schema(name, version), indent=1).encode()
    except SchemaError:
        return None


def as_metadata(fields: Mapping) -> dict[str, str]:
    """Flatten a decoded message to MCAP metadata (str -> str); bytes are summarised. Never raises."""
    out = {}
    for k, v in fields.items():
        if isinstance(v, str):
            out[str(k)] = v
        elif isinstance(v, (bytes, bytearray)):
            out[str(k)] = f"<{len(v)} bytes: see attachment {PROVENANCE_ATTACHMENT}>"
        else:
            try:
                out[str(k)] = json.dumps(v, default=repr, sort_keys=True)
            except (TypeError, ValueError):  # e.g. bytes or mixed-type map keys
                out[str(k)] = repr(v)
    return out


def check_provenance(payload: bytes, env: Envelope) -> Envelope:
    """``env``, or ``env`` with a problem if a ``mntes.provenance`` envelope does not decode as one.

    Only a valid provenance becomes an attachment and a metadata record; any
    peer on the setup's keys can publish, so nothing here may raise.
    """
    if env.problem or env.schema != PROVENANCE_SCHEMA:
        return env
    from mntes_stream.io.messages import Provenance

    try:
        Provenance.from_bytes(payload)
    except Exception as exc:  # SchemaError normally; anything else must not stop a recorder either
        # A bounded set of problem strings: each distinct one is a channel.
        reason = getattr(exc, "reason", "") or type(exc).__name__
        return Envelope(env.schema, env.version, env.publish_time_ns, env.seq, f"invalid {PROVENANCE_SCHEMA} message ({reason})")
    return env


def writer_description(**extra) -> dict[str, str]:
    """The ``mntes.recording`` metadata: who wrote the file, where, when."""
    import mcap

    desc = {
        "software": f"mntes-stream {__version__}",
        "mcap_library": f"mcap-python {getattr(mcap, '__version__', '?')}",
        "host": socket.gethostname(),
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }
    desc.update({k: v if isinstance(v, str) else json.dumps(v, default=str) for k, v in extra.items()})
    return desc


# ----------------------------------------------------------------------------- writer
