"""services/README.md's router recipes, run command for command; liveliness and ``ps`` (loopback, bounded).

The commands are read from the README's code blocks and run as written from a
copy of services/ in a temporary directory; the router's port 7447 is moved to
a free one (in zenoh-client.json5, and as ``-l`` on the router's line) so
parallel runs cannot collide.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from test_services_walkthrough import Proc

from mntes_stream.io.presence import list_services
from mntes_stream.io.transport import QueueSubscriber, ZenohSettings, free_tcp_port, open_session
from mntes_stream.service.router import RouterConfig, RouterService

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _section_blocks(title: str) -> list[list[str]]:
    text = (ROOT / "services" / "README.md").read_text()
    section = text.split(f"## {title}", 1)[1].split("\n## ", 1)[0]
    return [[ln for ln in b.splitlines() if ln.strip()] for b in re.findall(r"```\n(.*?)```", section, re.S)]


def _ps(cwd: Path, *args: str) -> dict:
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "ps", "--json", *args], cwd=cwd, capture_output=True,
                         text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return json.loads(res.stdout)


def _client(port: int) -> ZenohSettings:
    return ZenohSettings(mode="client", connect=(f"tcp/127.0.0.1:{port}",))


def _copy_services(tmp_path: Path, port: int) -> None:
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("recordings", "*-params.toml"))
    f = tmp_path / "services" / "zenoh-client.json5"
    f.write_text(f.read_text().replace("7447", str(port)))


def test_router_recipe_every_service_a_client(tmp_path):
    (router_cmd, conv_cmd, rec_cmd, src_cmd, mon_cmd, ps_cmd), _two_hosts = _section_blocks("A router, every service a client")
    port = free_tcp_port()
    _copy_services(tmp_path, port)
    procs: list[Proc] = []
    try:
        router = Proc(f"{router_cmd} -l tcp/127.0.0.1:{port}", tmp_path)
        procs.append(router)
        router.wait_for(r"router router: zenoh id")
        conv = Proc(conv_cmd, tmp_path)
        procs.append(conv)
        conv.wait_for(r"converter converter: \d+ detectors")
        rec = Proc(rec_cmd, tmp_path)
        procs.append(rec)
        rec.wait_for(r"recording mntes/lab/\*\* into")
        src = Proc(src_cmd, tmp_path)
        procs.append(src)
        mon = Proc(mon_cmd, tmp_path)
        procs.append(mon)
        # No gossip anywhere: the router alone brings the source's housekeeping and the converter's status.
        mon.wait_for(r"housekeeping: t_bath \d+\.\d+ mK \(age [\d.]+ s\)\s+b_field -?\d+\.\d+ uT", 120)
        mon.wait_for(r"^converter\s+\d+\.\d", 60)

        # ps, as written: every service of the recipe is alive, the converter with a rate and what it owns.
        res = subprocess.run([sys.executable, "-m", "mntes_stream", *shlex.split(ps_cmd)[1:]], cwd=tmp_path,
                             capture_output=True, text=True, timeout=60)
        assert res.returncode == 0 and "Traceback" not in res.stderr, res.stderr
        for service in ("router", "converter", "recorder", "source", "monitor"):
            assert re.search(rf"^{service}\s", res.stdout, re.M), res.stdout
        doc = _ps(tmp_path, "-c", "services/zenoh-client.json5")
        by = {s["service"]: s for s in doc["services"]}
        assert set(by) == {"router", "converter", "recorder", "source", "monitor"}, by
        assert by["converter"]["state"] == "running" and by["converter"]["owns"]["boards"] == "*"
        assert by["converter"]["owns"]["shard"] == "0/1" and by["converter"]["owns"]["publishing"] == 2
        assert by["converter"]["rate_per_s"] > 0 and by["converter"]["pid"] == conv.p.pid

        # A killed service is gone from ps within 5 s (zenoh drops its token with the process).
        conv.p.kill()
        conv.p.wait(30)
        t_kill = time.monotonic()
        while True:
            names = {s["service"] for s in _ps(tmp_path, "-c", "services/zenoh-client.json5", "--interval", "0")["services"]}
            if "converter" not in names:
                break
            assert time.monotonic() - t_kill < 5.0, names
        assert {"router", "recorder", "source", "monitor"} <= names

        assert mon.interrupt() in (0, 130)
        assert src.interrupt() in (0, 130)
        assert rec.interrupt() in (0, 130)
        for p in (src, rec, router):
            assert not any("Traceback" in line for line in p.seen), "".join(p.seen)
        res = subprocess.run([sys.executable, "-m", "mntes_stream", "inspect", "services/recordings/"], cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        counts = {m.group(2): int(m.group(1)) for m in re.finditer(r"^\s+(\d+)\s+(\S+)$", res.stdout, re.M)}
        assert sum(n for t, n in counts.items() if "/counts/" in t) > 0
        assert sum(n for t, n in counts.items() if "/power/" in t) > 0  # through the router, no gossip
        assert router.interrupt() in (0, 130)
    finally:
        for p in procs:
            if p.p.poll() is None:
                p.p.kill()
                p.p.wait()


def test_two_routers_bridge_two_hosts(tmp_path):
    """The README's two-host layout on loopback: readout clients on router A, analysis clients on router B."""
    _, two_hosts = _section_blocks("A router, every service a client")
    router_a, router_b = (ln for ln in two_hosts if not ln.startswith("#"))
    port_a, port_b = free_tcp_port(), free_tcp_port()
    router_a = router_a.replace("192.168.1.10:7447", f"127.0.0.1:{port_a}")
    router_b = router_b.replace("192.168.1.10:7447", f"127.0.0.1:{port_a}") + f" -l tcp/127.0.0.1:{port_b}"
    procs = []
    try:
        for cmd in (router_a, router_b):
            procs.append(Proc(cmd, tmp_path))
            procs[-1].wait_for(r"router router: zenoh id")
        with open_session(_client(port_b)) as analysis, open_session(_client(port_a)) as readout:
            sub = QueueSubscriber(analysis, ["mntes/lab/counts/**"])
            time.sleep(1.0)  # routers exchange the subscription
            got = []
            for i in range(20):
                readout.put("mntes/lab/counts/0/0", i.to_bytes(2, "little"))
                item = sub.get(timeout_s=0.5)
                if item is not None:
                    got.append(int.from_bytes(item[1], "little"))
            while (item := sub.get(timeout_s=0.5)) is not None:
                got.append(int.from_bytes(item[1], "little"))
            sub.close()
            assert got == list(range(20))
            # ps from the analysis host sees both routers.
            assert sorted(s["service"] for s in list_services(analysis, "lab")) == ["router", "router"]
    finally:
        for p in procs:
            p.interrupt()


def test_a_dead_connect_endpoint_is_reported_once_in_status_and_log(caplog):
    port, dead = free_tcp_port(), free_tcp_port()
    cfg = RouterConfig(name="r1", duration_s=20,
                       zenoh=ZenohSettings(listen=(f"tcp/127.0.0.1:{port}",), connect=(f"tcp/127.0.0.1:{dead}",)))
    svc = RouterService(cfg)
    stop = threading.Event()
    t = threading.Thread(target=svc.start, args=(stop,), daemon=True)
    with caplog.at_level("WARNING", logger="mntes_stream.io.presence"):
        t.start()
        try:
            deadline = time.monotonic() + 15
            while not svc.status()["warnings"]:
                assert time.monotonic() < deadline, svc.status()
                time.sleep(0.1)
            assert svc.status()["warnings"] == [f"connect endpoint tcp/127.0.0.1:{dead} unreachable for 5 s"]
            # Others see it too, through the heartbeat.
            with open_session(_client(port)) as s:
                (mine,) = [b for b in list_services(s, "lab") if b["name"] == "r1"]
            assert mine["warnings"] == svc.status()["warnings"]
            time.sleep(1.0)  # still dead: not said again
            assert len([r for r in caplog.records if "unreachable" in r.getMessage()]) == 1
        finally:
            stop.set()
            t.join(30)
