"""JSON Schema validation of real msgpack payloads (test helper).

JSON has no bytes type, so the schemas in ``schemas/`` mark msgpack ``bin``
fields with the custom keyword ``{"x-msgpack": "bin"}``. Standard validators
ignore unknown keywords; this module extends the draft 2020-12 validator with
a check for it (the instance must be ``bytes``), see ``schemas/README.md``.
"""

from __future__ import annotations

import functools

import jsonschema
import msgpack
from jsonschema import Draft202012Validator, ValidationError

from mntes_stream.io.codec import json_schema


def _x_msgpack(validator, value, instance, schema):
    if value == "bin" and not isinstance(instance, (bytes, bytearray)):
        yield ValidationError(f"{type(instance).__name__} is not msgpack bin (bytes)")


MsgpackValidator = jsonschema.validators.extend(Draft202012Validator, {"x-msgpack": _x_msgpack})


@functools.cache
def validator(name: str, version: int | None = None):
    schema = json_schema(name, version)
    Draft202012Validator.check_schema(schema)
    return MsgpackValidator(schema)


def unpack(payload: bytes):
    return msgpack.unpackb(payload, raw=False)


def errors(msg) -> list[str]:
    """Schema violations of a decoded msgpack map (empty list: valid)."""
    if not isinstance(msg, dict) or not isinstance(msg.get("schema"), str):
        return ["not a message map"]
    try:
        v = validator(msg["schema"])
    except Exception as exc:  # unknown schema name
        return [str(exc)]
    return [e.message for e in v.iter_errors(msg)]


def validate_payload(payload: bytes) -> dict:
    """Unpack and validate; raises AssertionError listing the violations."""
    msg = unpack(payload)
    problems = errors(msg)
    assert not problems, problems
    return msg
