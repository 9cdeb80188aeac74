"""Self-described data, read without project code: what bit 3 means, units, and every payload's schema.

A source and a converter run over real zenoh sessions on 127.0.0.1 (project
code: they are what is tested); everything that *reads* uses only zenoh,
msgpack, jsonschema, the mcap reader, h5py and the files in ``schemas/``:

- every publication's zenoh encoding names its schema file
  (``application/msgpack;schema=mntes.power.v1`` -> ``schemas/power.v1.json``)
  and the payload validates against that file;
- the provenance is answered on request by a zenoh queryable (a plain ``get``),
  and its parameters are the ones the converter was given;
- a recorded MCAP file's metadata records name the flag bits and units, each
  channel's schema is its payload's schema file and every message validates;
  the HDF5 export carries the flag bits as attributes.
"""

from __future__ import annotations

import contextlib
import json
import re
import threading
import time
import tomllib
from pathlib import Path

import jsonschema
import msgpack
import pytest

from mntes_stream.io.paramfile import dump_params
from mntes_stream.io.transport import free_tcp_port, loopback
from mntes_stream.service.converter import ConverterConfig, ConverterService
from mntes_stream.service.recorder import RecorderConfig, RecorderService
from mntes_stream.service.source import MinimalSource, SourceConfig, SourceService, SourceServiceConfig

zenoh = pytest.importorskip("zenoh")

SCHEMAS = Path(__file__).resolve().parents[1] / "schemas"
SRC = SourceConfig(modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1)
ENCODING = re.compile(r"^application/msgpack;schema=(mntes\.[a-z_]+)\.v(\d+)$")


def _bin(validator, value, instance, schema):
    if value == "bin" and not isinstance(instance, (bytes, bytearray)):
        yield jsonschema.ValidationError(f"{type(instance).__name__} is not msgpack bin")


# schemas/README.md: draft 2020-12 plus the one keyword x-msgpack (bytes).
Validator = jsonschema.validators.extend(jsonschema.Draft202012Validator, {"x-msgpack": _bin})


def _schema_file(name: str, version: int) -> dict:
    """``mntes.power`` v1 -> ``schemas/power.v1.json``, read as plain JSON."""
    return json.loads((SCHEMAS / f"{name.removeprefix('mntes.')}.v{version}.json").read_text())


def _validate(encoding: str, payload: bytes) -> dict:
    m = ENCODING.match(encoding)
    assert m, f"encoding {encoding!r} does not name a schema"
    msg = msgpack.unpackb(payload, raw=False)
    Validator(_schema_file(m[1], int(m[2]))).validate(msg)
    assert (msg["schema"], msg["version"]) == (m[1], int(m[2]))
    return msg


def test_flags_file_is_the_flags_the_code_sets():
    from mntes_stream.core import flags as fl

    doc = json.loads((SCHEMAS / "flags.v1.json").read_text())
    bits = doc["x-mntes-bits"]
    assert {b["mask"]: b["name"] for b in bits} == fl.NAMES
    assert all(b["mask"] == 1 << b["bit"] and b["meaning"] for b in bits)
    assert sum(b["mask"] for b in bits if b["unusable"]) == fl.UNUSABLE
    assert doc["x-mntes-units"]["p_opt_w"].startswith("W")


@contextlib.contextmanager
def _running(service):
    stop, ready, errors = threading.Event(), threading.Event(), []

    def main():
        try:
            service.start(stop, ready)
        except BaseException as exc:
            errors.append(exc)
            ready.set()

    t = threading.Thread(target=main, daemon=True)
    t.start()
    try:
        assert ready.wait(60) and not errors, errors
        yield service
    finally:
        stop.set()
        t.join(20)
    assert not t.is_alive() and not errors, errors


def _plain_session(listen: int, connect: int):
    """A zenoh session from zenoh's own API (no project code): loopback, no scouting."""
    conf = zenoh.Config.from_json5(json.dumps({
        "mode": "peer", "listen": {"endpoints": [f"tcp/127.0.0.1:{listen}"]},
        "connect": {"endpoints": [f"tcp/127.0.0.1:{connect}"]},
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
    return zenoh.open(conf)


def test_live_publications_recording_and_export_describe_themselves(tmp_path):
    import h5py
    from mcap.reader import make_reader

    from mntes_stream.feeds.hdf5 import export_hdf5

    params = tmp_path / "params.toml"
    truth = MinimalSource(SRC).params
    dump_params(truth, params)
    conv_port, raw_port, rec_port, rec_dir = free_tcp_port(), free_tcp_port(), free_tcp_port(), tmp_path / "rec"
    samples: list[tuple[str, str, bytes]] = []
    lock = threading.Lock()

    def on_sample(s):
        with lock:
            samples.append((str(s.key_expr), str(s.encoding), s.payload.to_bytes()))

    conv = ConverterService(ConverterConfig(params=str(params), kind="table", table_cache="",
                                            zenoh=loopback(conv_port), provenance_interval_s=0.0))
    # The source publishes to the converter, the recorder and the plain session directly (they listen).
    src = SourceService(SourceServiceConfig(source=SRC, params=str(params), linger_s=0.0,
                                            zenoh=loopback(None, [conv_port, raw_port, rec_port])))
    rec = RecorderService(RecorderConfig(directory=str(rec_dir), zenoh=loopback(rec_port, [conv_port])))
    with _running(conv), _running(rec), _plain_session(raw_port, conv_port) as z:
        sub = z.declare_subscriber("mntes/lab/**", on_sample)
        with _running(src):
            deadline = time.monotonic() + 30
            while time.monotonic() < deadline:
                with lock:
                    kinds = {k.split("/")[2] for k, _, _ in samples}
                if {"counts", "hk", "power", "status"} <= kinds:
                    break
                time.sleep(0.1)
            time.sleep(1.0)
            # Provenance on request: published at start only here (interval 0), a plain get still has it.
            replies = list(z.get("mntes/lab/provenance", timeout=10.0))
        sub.undeclare()
    with lock:
        got = list(samples)
    seen = {}
    for key, encoding, payload in got:
        kind = key.split("/")[2]
        msg = _validate(encoding, payload)
        assert msg["schema"] == f"mntes.{kind}"
        seen[kind] = seen.get(kind, 0) + 1
    assert {"counts", "hk", "power", "status"} <= set(seen), seen

    oks = [r.ok for r in replies if r.ok is not None]
    assert oks, "nobody answered mntes/lab/provenance"
    prov = _validate(str(oks[0].encoding), oks[0].payload.to_bytes())
    assert prov["schema"] == "mntes.provenance"
    answered = tomllib.loads(prov["params_toml"])
    assert answered == tomllib.loads(params.read_text())  # the very parameters the converter was given

    # The recording, with the plain mcap reader: flag meanings, units and schemas in its metadata.
    (path,) = sorted(rec_dir.glob("*.mcap"))
    with open(path, "rb") as f:
        reader = make_reader(f)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        channels = {}
        for schema, channel, message in reader.iter_messages():
            if channel.topic not in channels:  # each channel's schema is its payload's schema file
                assert schema.encoding == "jsonschema" and channel.message_encoding == "msgpack"
                name, version = channel.metadata["mntes.schema"], int(channel.metadata["mntes.version"])
                assert json.loads(schema.data) == _schema_file(name, version)
                channels[channel.topic] = (name, version)
            Validator(_schema_file(*channels[channel.topic])).validate(msgpack.unpackb(message.data, raw=False))
    assert {n for n, _ in channels.values()} >= {"mntes.counts", "mntes.hk", "mntes.power", "mntes.status",
                                                  "mntes.provenance"}
    assert meta["mntes.flags"]["bit3"].startswith("env_out_of_range: bath temperature")
    assert meta["mntes.flags"]["bit0"].endswith("(power unusable)")
    assert meta["mntes.units"]["p_opt_w"].startswith("W")
    assert "raw bytes" in meta["mntes.encoding"]["envelope"]
    flags_doc = json.loads(meta["mntes.flags"]["schema"])
    assert flags_doc == json.loads((SCHEMAS / "flags.v1.json").read_text())

    # The HDF5 export, with plain h5py.
    out = tmp_path / "power.h5"
    export_hdf5(path, out)
    with h5py.File(out, "r") as f:
        assert json.loads(f.attrs["flags_schema"])["x-mntes-bits"][3]["name"] == "env_out_of_range"
        groups = [g for name, g in f.items() if name != "provenance"]
        assert groups
        for g in groups:
            a = g["flags"].attrs
            assert str(a["flag_bit3"]).startswith("env_out_of_range:")
            assert [b["name"] for b in json.loads(a["flag_bits_json"])][:3] == ["saturated", "superconducting",
                                                                                  "out_of_table"]
            assert g["tod"].attrs["units"] == "W"
