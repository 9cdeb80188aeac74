"""``ocs-bridge`` live (issue 25 item 2): a real crossbar router, ocs's own fake-data agent, zenoh on loopback.

crossbar comes from its own environment (it pins idna<2.6, see pyproject's ``ocs`` extra): ``$MNTES_CROSSBAR``,
``.crossbar/bin/crossbar`` (what ``.ci/run`` installs) or ``crossbar`` on PATH. The router listens on 127.0.0.1
only; every process is started by the test and stopped by it (each bounded in time).
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

if importlib.util.find_spec("ocs") is None or importlib.util.find_spec("autobahn") is None:
    pytest.skip("the ocs extra (ocs, autobahn) is not installed", allow_module_level=True)
ROOT = Path(__file__).resolve().parent.parent
# .ci/run installs crossbar in the background while the tests run: wait for it when it is on its way.
_deadline = time.monotonic() + 600
while (ROOT / ".crossbar").is_dir() and not any((ROOT / ".crossbar" / m).exists() for m in ("installed", "failed")) \
        and not (ROOT / ".crossbar/bin/crossbar").exists() and time.monotonic() < _deadline:
    time.sleep(2)
CROSSBAR = os.environ.get("MNTES_CROSSBAR") or next(
    (str(p) for p in (ROOT / ".crossbar/bin/crossbar",) if p.exists()), None) or shutil.which("crossbar")
if not CROSSBAR:
    pytest.skip("no crossbar router (.ci/run installs it in .crossbar/; or set MNTES_CROSSBAR)",
                allow_module_level=True)

from mntes_stream.io.messages import decode  # noqa: E402
from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session  # noqa: E402
from mntes_stream.ocs.bridge import OcsBridgeConfig, OcsBridgeService, OcsBridgeSettings  # noqa: E402
from mntes_stream.service.base import StopFlag  # noqa: E402

FEED = "observatory.fake-data1.feeds.false_temperatures"


def crossbar_config(port: int) -> dict:
    """One router, one realm, anonymous agents and clients on ws://127.0.0.1:PORT/ws (as ocs's template, trimmed)."""
    perms = {"uri": "observatory.", "match": "prefix", "cache": True,
             "allow": {"call": True, "register": True, "publish": True, "subscribe": True}}
    return {"version": 2, "workers": [{
        "type": "router",
        "realms": [{"name": "test_realm", "roles": [{"name": "iocs_agent", "permissions": [perms]}]}],
        "transports": [{"type": "web", "endpoint": {"type": "tcp", "port": port, "interface": "127.0.0.1"},
                        "paths": {"ws": {"type": "websocket",
                                         "auth": {"anonymous": {"type": "static", "role": "iocs_agent"}}}}}]}]}


def wait_port(port: int, proc, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        assert proc.poll() is None, f"exited {proc.returncode}"
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return
        time.sleep(0.2)
    raise AssertionError(f"nothing listens on {port} after {timeout_s} s")


def stop(proc) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait(10)


@pytest.fixture
def router(tmp_path):
    port = free_tcp_port()
    (tmp_path / "cb").mkdir()
    (tmp_path / "cb/config.json").write_text(json.dumps(crossbar_config(port)))
    log = open(tmp_path / "crossbar.log", "w")
    proc = subprocess.Popen([CROSSBAR, "start", "--cbdir", str(tmp_path / "cb")], stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        wait_port(port, proc, 60)
        yield port
    finally:
        stop(proc)
        log.close()


def start_agent(tmp_path, port: int):
    """ocs's FakeDataAgent: 2 channels at 10 Hz around 0.1 (K), published every second."""
    (tmp_path / "logs").mkdir(exist_ok=True)
    (tmp_path / "scf.yaml").write_text(f"""hub:
  wamp_server: ws://127.0.0.1:{port}/ws
  wamp_http: http://127.0.0.1:{port}/call
  wamp_realm: test_realm
  address_root: observatory
hosts:
  testhost:
    log-dir: {tmp_path / 'logs'}
    agent-instances:
      - agent-class: FakeDataAgent
        instance-id: fake-data1
        arguments: [--mode, acq, --num-channels, 2, --sample-rate, 10]
""")
    return subprocess.Popen([sys.executable, "-m", "ocs.agents.fake_data.agent", "--site-file", str(tmp_path / "scf.yaml"),
                             "--site-host", "testhost", "--instance-id", "fake-data1"],
                            stdout=open(tmp_path / "agent.log", "w"), stderr=subprocess.STDOUT, start_new_session=True)


def test_bridge_publishes_the_agents_feed_as_t_bath_and_says_when_it_goes_stale(router, tmp_path):
    zport = free_tcp_port()
    cfg = OcsBridgeConfig(bridge=OcsBridgeSettings(
        router=f"ws://127.0.0.1:{router}/ws", setup="lab", stale_s=1.5, duration_s=25.0, reconnect_s=0.2,
        t_bath_field=f"{FEED}.channel_00", b_field_field=f"{FEED}.channel_01", b_field_unit="mT"),
        zenoh=loopback(connect_ports=[zport]))
    svc, flag, result, got = OcsBridgeService(cfg), StopFlag(), {}, {"t_bath": [], "b_field": []}
    agent = start_agent(tmp_path, router)
    try:
        with open_session(loopback(zport)) as z:
            sub = QueueSubscriber(z, ["mntes/lab/hk/**"])
            th = threading.Thread(target=lambda: result.update(svc.start(stop=flag)), daemon=True)
            th.start()
            deadline = time.monotonic() + 40
            while len(got["t_bath"]) < 2 and time.monotonic() < deadline:  # two publications (1 s apart)
                item = sub.get(timeout_s=0.2)
                if item is not None:
                    msg = decode(item[1])
                    got[msg.sensor].append(msg)
            stop(agent)  # the thermometer goes away: the bridge says its sensors are stale
            deadline = time.monotonic() + 10
            while "t_bath" not in svc.status().get("stale", []) and time.monotonic() < deadline:
                time.sleep(0.1)
            flag.set()
            th.join(30)
            for _key, payload, _ in sub.drain():
                msg = decode(payload)
                got[msg.sensor].append(msg)
            sub.close()
    finally:
        stop(agent)
    assert len(got["t_bath"]) >= 2, (tmp_path / "agent.log").read_text()[-2000:]
    t = np.concatenate([m.t_ns for m in got["t_bath"]])
    v = np.concatenate([m.value for m in got["t_bath"]])
    assert [m.seq for m in got["t_bath"]] == list(range(len(got["t_bath"])))  # every message, in order
    assert np.all(np.diff(t) > 0) and abs(t[-1] / 1e9 - time.time()) < 60  # the readings' own (recent) times
    assert np.allclose(np.diff(t), 1e8, atol=1e3)  # 10 Hz, as the agent samples
    assert np.all((v > 0.05) & (v < 0.15)) and {m.unit for m in got["t_bath"]} == {"K"}
    b = np.concatenate([m.value for m in got["b_field"]])
    assert np.all((b > 0.5e-4) & (b < 1.5e-4)) and {m.unit for m in got["b_field"]} == {"T"}  # 0.1 "mT" -> T
    s = result["sensors"]["t_bath"]
    assert s["readings"] == t.size and s["messages"] == len(got["t_bath"]) and s["out_of_order"] == s["bad"] == 0
    assert result["stale"] == ["b_field", "t_bath"] and result["connections"] == 1
    assert any("t_bath" in w and "stale" in w for w in svc.status().get("warnings", [])), svc.status()


def test_an_unreachable_router_is_counted_and_the_cli_needs_a_field(tmp_path):
    port = free_tcp_port()  # nothing listens there
    cfg = OcsBridgeConfig(bridge=OcsBridgeSettings(router=f"ws://127.0.0.1:{port}/ws", duration_s=1.5,
                                                   reconnect_s=0.2, t_bath_field=f"{FEED}.channel_00"),
                          zenoh=loopback())
    result = OcsBridgeService(cfg).start(stop=StopFlag())
    assert result["router_state"] == "unreachable" and result["connect_failures"] >= 2 and result["connections"] == 0
    p = subprocess.run([sys.executable, "-m", "mntes_stream", "ocs-bridge", "--duration", "1"], capture_output=True,
                       text=True, timeout=60)
    assert p.returncode == 2 and p.stderr.count("\n") == 1 and "name at least one field" in p.stderr, p.stderr
