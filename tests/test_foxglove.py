"""The Foxglove bridge live (a real foxglove.websocket.v1 client) and its json channels (jsonschema).

A source and a converter run over real zenoh sessions on 127.0.0.1; the
``foxglove`` service serves them; a plain WebSocket client (websocket-client,
no project code on the wire side) negotiates ``foxglove.websocket.v1``, reads
the advertised channels, subscribes, and decodes binary message-data frames;
the power values equal what the converter published, sample for sample.
"""

from __future__ import annotations

import contextlib
import json
import re
import struct
import threading
import time

import jsonschema
import numpy as np
import pytest

from mntes_stream.io.messages import PowerChunk, decode
from mntes_stream.io.paramfile import dump_params
from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session
from mntes_stream.service.converter import ConverterConfig, ConverterService
from mntes_stream.service.metrics import MetricsSettings
from mntes_stream.service.source import MinimalSource, SourceConfig, SourceService, SourceServiceConfig

pytest.importorskip("foxglove")
websocket = pytest.importorskip("websocket")

SRC = SourceConfig(modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1)


@contextlib.contextmanager
def running(service):
    """``service.start`` in a thread until the block ends."""
    stop, ready = threading.Event(), threading.Event()
    errors: list = []

    def main():
        try:
            service.start(stop, ready)
        except BaseException as exc:  # shown by the test
            errors.append(exc)
            ready.set()

    thread = threading.Thread(target=main, daemon=True)
    thread.start()
    try:
        assert ready.wait(60) and not errors, f"{service.name} did not start: {errors}"
        yield service
    finally:
        stop.set()
        thread.join(20)
    assert not thread.is_alive(), f"{service.name} did not stop"
    assert not errors, errors


@contextlib.contextmanager
def live_setup(tmp_path, **converter_kw):
    """Converter (listening) + source (connected to it) on loopback; yields the converter's zenoh port."""
    params = tmp_path / "params.toml"
    dump_params(MinimalSource(SRC).params, params)
    port = free_tcp_port()
    conv = ConverterService(ConverterConfig(params=str(params), kind="table", table_cache="", zenoh=loopback(port),
                                            **converter_kw))
    src = SourceService(SourceServiceConfig(source=SRC, params=str(params), linger_s=0.0,
                                            zenoh=loopback(None, [port])))
    with running(conv), running(src):
        yield port


def _recv_text_until(ws, pred, timeout_s=20.0):
    deadline = time.monotonic() + timeout_s
    seen = []
    while time.monotonic() < deadline:
        ws.settimeout(max(deadline - time.monotonic(), 0.01))
        op, data = ws.recv_data()
        if op == websocket.ABNF.OPCODE_TEXT:
            msg = json.loads(data)
            seen.append(msg)
            if pred(seen):
                return seen
    pytest.fail(f"timed out; text messages seen: {[m.get('op') for m in seen]}")


def test_live_bridge_serves_advertised_channels_and_the_converters_power(tmp_path):
    from mntes_stream.service.foxglove import FoxgloveConfig, FoxgloveService

    ws_port = free_tcp_port()
    with live_setup(tmp_path) as zport, open_session(loopback(None, [zport])) as session:
        published = QueueSubscriber(session, ["mntes/lab/power/0/0"])
        metrics_port = free_tcp_port()
        fox = FoxgloveService(FoxgloveConfig(port=ws_port, per_module=2, max_rate_hz=0.0, zenoh=loopback(None, [zport]),
                                             metrics=MetricsSettings(port=metrics_port)))
        with running(fox):
            # foxglove-sdk 0.30 accepts only the protocol's current name, foxglove.sdk.v1 (the same
            # ops and frames as foxglove.websocket.v1); a client offers both, as the Foxglove app does.
            ws = websocket.create_connection(f"ws://127.0.0.1:{ws_port}", timeout=20,
                                             subprotocols=["foxglove.websocket.v1", "foxglove.sdk.v1"])
            try:
                assert ws.getsubprotocol() in ("foxglove.websocket.v1", "foxglove.sdk.v1")
                channels: dict[str, dict] = {}

                def advertised(seen):
                    for m in seen:
                        if m.get("op") == "advertise":
                            channels.update({c["topic"]: c for c in m["channels"]})
                    return {"/mntes/lab/power/0/0", "/mntes/lab/status/converter"} <= set(channels)

                seen = _recv_text_until(ws, advertised)
                assert seen[0]["op"] == "serverInfo"
                power_ch = channels["/mntes/lab/power/0/0"]
                assert power_ch["encoding"] == "json" and power_ch["schemaEncoding"] == "jsonschema"
                assert power_ch["schemaName"] == "mntes.foxglove.power"
                schema = json.loads(power_ch["schema"])
                ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": power_ch["id"]}]}))
                got = []
                deadline = time.monotonic() + 20
                while len(got) < 30 and time.monotonic() < deadline:
                    op, data = ws.recv_data()
                    if op != websocket.ABNF.OPCODE_BINARY:
                        continue
                    assert data[0] == 0x01  # message data
                    sub_id, log_time = struct.unpack_from("<IQ", data, 1)
                    assert sub_id == 7
                    msg = json.loads(data[13:])
                    assert msg["t_ns"] == log_time
                    jsonschema.validate(msg, schema)
                    got.append(msg)
                assert len(got) >= 30
                # Its Prometheus endpoint (a real GET): what it received, dropped and logged.
                import urllib.request

                def scrape() -> dict:
                    with urllib.request.urlopen(f"http://127.0.0.1:{metrics_port}/metrics", timeout=10) as r:
                        text = r.read().decode()
                    return dict(re.findall(r'^mntes_service_counter\{counter="(\w+)",name="foxglove",'
                                           r'service="foxglove"\} (\S+)$', text, re.M))

                # The heartbeat carries the counters every 0.5 s: a scrape may see the beat before the traffic.
                deadline = time.monotonic() + 10
                while (float((counters := scrape()).get("received", 0)) == 0 or float(counters["logged"]) < 30) \
                        and time.monotonic() < deadline:
                    time.sleep(0.2)
                assert float(counters["received"]) > 0 and float(counters["logged"]) >= 30
                assert "dropped" in counters and "queue_depth" in counters
            finally:
                ws.close()
        # Every json sample is a value the converter published (same chunk seq, same sample time).
        chunks: dict[int, PowerChunk] = {}
        for _, payload, _ in published.drain():
            c = decode(payload)
            chunks[c.seq] = c
        published.close()
    matched = 0
    for msg in got:
        chunk = chunks.get(msg["seq"])
        if chunk is None:
            continue
        k = int(np.flatnonzero(chunk.times_ns() == msg["t_ns"])[0])
        assert set(msg["p_opt_pw"]) == set(chunk.detector_ids[:2])
        for row, det in enumerate(chunk.detector_ids[:2]):
            assert msg["p_opt_pw"][det] == pytest.approx(chunk.p_opt_w[row, k] * 1e12, rel=1e-12)
            assert msg["flags"][det] == int(chunk.flags[row, k])
        matched += 1
    assert matched >= 20
    assert 0.1 < np.median([v for m in got for v in m["p_opt_pw"].values()]) < 5  # pW: a plausible optical load


def _validate_json_channels(path) -> dict[str, int]:
    """Every json message of ``path`` against its channel's JSON Schema, with the plain mcap reader; counts per topic."""
    from mcap.reader import make_reader

    counts: dict[str, int] = {}
    validators: dict[int, jsonschema.Draft202012Validator] = {}
    with open(path, "rb") as f:
        for schema, channel, message in make_reader(f).iter_messages():
            if channel.message_encoding != "json":
                assert channel.message_encoding == "msgpack"
                continue
            assert schema.encoding == "jsonschema" and schema.name.startswith("mntes.foxglove.")
            v = validators.get(schema.id)
            if v is None:
                doc = json.loads(schema.data)
                jsonschema.Draft202012Validator.check_schema(doc)
                v = validators[schema.id] = jsonschema.Draft202012Validator(doc)
            v.validate(json.loads(message.data))  # raises on the first message that does not fit
            counts[channel.topic] = counts.get(channel.topic, 0) + 1
    return counts


def test_recorder_foxglove_channels_and_transcode_validate_with_an_independent_reader(tmp_path):
    import dataclasses
    import subprocess
    import sys

    from mntes_stream.io.mcap import Session
    from mntes_stream.service.recorder import RecorderConfig, RecorderService

    rec_dir = tmp_path / "rec"
    with live_setup(tmp_path) as zport:
        rec = RecorderService(RecorderConfig(directory=str(rec_dir), foxglove_channels=True,
                                             zenoh=dataclasses.replace(loopback(None, [zport]), gossip=True)))
        with running(rec):
            time.sleep(2.5)
    (recorded,) = sorted(rec_dir.glob("*.mcap"))
    live_counts = _validate_json_channels(recorded)
    assert any(t.startswith("/mntes/lab/power/") for t in live_counts), live_counts
    assert "/mntes/lab/status/converter" in live_counts and "/mntes/lab/flag_rates/converter" in live_counts
    print(live_counts)

    # The same recording's msgpack originals only, transcoded by the command line.
    plain = tmp_path / "plain.mcap"
    from mntes_stream.foxglove.transcode import transcode

    transcode(recorded, plain, foxglove=False)
    assert _validate_json_channels(plain) == {}
    out = tmp_path / "fox.mcap"
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "transcode", str(plain), str(out), "--foxglove",
                          "--per-module", "0"], capture_output=True, text=True, timeout=120)
    assert res.returncode == 0, res.stderr
    counts = _validate_json_channels(out)
    before, after = Session(plain).message_counts(), Session(out).message_counts()
    assert {t: n for t, n in after.items() if not t.startswith("/")} == before  # originals all kept
    n_power = sum(n for t, n in before.items() if "/power/" in t)
    # Every power sample of every detector is a json value (--per-module 0, no rate limit).
    power_json = sum(n for t, n in counts.items() if "/power/" in t)
    assert n_power > 0 and power_json == n_power * SRC.chunk_samples
    assert "/mntes/lab/flag_rates/converter" in counts
    # Units and flag names travel with the json schema; a person reads them without project code.
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "transcode", str(plain), str(out), "--foxglove"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode != 0 and "Traceback" not in res.stderr and len(res.stderr.strip().splitlines()) == 1


def test_up_plus_foxglove_commands_reach_a_websocket_client(tmp_path):
    """The acceptance run, as a person types it: `mntes-stream up`, then `mntes-stream foxglove` joining its
    converter; a plain WebSocket client gets the advertised channels and power equal to what the converter
    published (read with zenoh's own API)."""
    import subprocess
    import sys

    import zenoh

    up = subprocess.Popen([sys.executable, "-m", "mntes_stream", "up", "--duration", "90", "--out", str(tmp_path),
                           "--modules", "2", "--channels", "8"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                          text=True)
    lines: list[str] = []
    threading.Thread(target=lambda: lines.extend(up.stdout), daemon=True).start()
    fox = ws = None
    try:
        deadline = time.monotonic() + 120
        while "power chunks" not in "".join(lines):  # every service ready, data flowing
            assert up.poll() is None and time.monotonic() < deadline, "".join(lines)
            time.sleep(0.1)
        conv = int(re.search(r"converter :(\d+)", "".join(lines))[1])
        ws_port = free_tcp_port()
        fox = subprocess.Popen([sys.executable, "-m", "mntes_stream", "foxglove", "--port", str(ws_port),
                                "--per-module", "3", "--max-rate-hz", "0", "-e", f"tcp/127.0.0.1:{conv}"],
                               stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        assert "serving ws://127.0.0.1:" in fox.stdout.readline()
        conf = zenoh.Config.from_json5(json.dumps({
            "mode": "peer", "connect": {"endpoints": [f"tcp/127.0.0.1:{conv}"]},
            "listen": {"endpoints": [f"tcp/127.0.0.1:{free_tcp_port()}"]},
            "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}}}))
        published: dict[int, bytes] = {}
        with zenoh.open(conf) as z:
            sub = z.declare_subscriber("mntes/lab/power/0/1",
                                       lambda s: published.__setitem__(len(published), s.payload.to_bytes()))
            ws = websocket.create_connection(f"ws://127.0.0.1:{ws_port}", timeout=20,
                                             subprotocols=["foxglove.websocket.v1", "foxglove.sdk.v1"])
            channels: dict[str, dict] = {}

            def advertised(seen):
                for msg in seen:
                    if msg.get("op") == "advertise":
                        channels.update({c["topic"]: c for c in msg["channels"]})
                return {"/mntes/lab/power/0/0", "/mntes/lab/power/0/1", "/mntes/lab/status/converter",
                        "/mntes/lab/flag_rates/converter"} <= set(channels)

            _recv_text_until(ws, advertised, timeout_s=60)
            ch = channels["/mntes/lab/power/0/1"]
            ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": ch["id"]}]}))
            got = []
            deadline = time.monotonic() + 30
            while len(got) < 40 and time.monotonic() < deadline:
                op, data = ws.recv_data()
                if op == websocket.ABNF.OPCODE_BINARY and data[0] == 0x01:
                    got.append(json.loads(data[13:]))
            time.sleep(0.5)
            sub.undeclare()
    finally:
        if ws is not None:
            ws.close()
        for proc in (fox, up):
            if proc is not None:
                proc.terminate()
                proc.wait(60)
    chunks = {c.seq: c for c in (decode(p) for p in published.values())}
    matched = 0
    for msg in got:
        chunk = chunks.get(msg["seq"])
        if chunk is None:
            continue
        k = int(np.flatnonzero(chunk.times_ns() == msg["t_ns"])[0])
        assert list(msg["p_opt_pw"]) == list(chunk.detector_ids[:3])
        for row, det in enumerate(chunk.detector_ids[:3]):
            want = chunk.p_opt_w[row, k] * 1e12
            assert (msg["p_opt_pw"][det] is None) if np.isnan(want) else msg["p_opt_pw"][det] == pytest.approx(want, rel=1e-12)
            assert msg["flags"][det] == int(chunk.flags[row, k])
        matched += 1
    assert matched >= 30, (len(got), len(chunks))


@pytest.mark.parametrize("argv", [["foxglove", "--duration", "1"],
                                  ["serve", "--config", "services/foxglove.toml", "--duration", "1"]])
def test_missing_foxglove_sdk_is_one_line_naming_the_extra(argv):
    import subprocess
    import sys
    from pathlib import Path

    code = ("import sys; sys.modules['foxglove'] = None\n"
            f"from mntes_stream.cli import main\nsys.exit(main({argv!r}))")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120,
                         cwd=Path(__file__).resolve().parents[1])
    assert res.returncode == 2, res.stderr
    err = res.stderr.strip().splitlines()
    assert len(err) == 1 and "pip install 'mntes-stream[foxglove]'" in err[0], res.stderr
