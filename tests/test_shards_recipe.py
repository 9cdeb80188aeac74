"""services/README.md's converter-shard recipe, run command for command (loopback, bounded, stops by itself).

Two converters split the example array's two modules, a hot standby claims
both, then the first converter is killed: the standby publishes its module.
The router's port 7447 is moved to a free one, as in test_router_recipes.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
import time
from pathlib import Path

import pytest
from test_router_recipes import _copy_services, _section_blocks
from test_services_walkthrough import Proc

from mntes_stream.io.transport import free_tcp_port

pytestmark = pytest.mark.slow


def _ps(cwd: Path) -> dict:
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "ps", "--json", "--interval", "0", "-c",
                          "services/zenoh-client.json5"], cwd=cwd, capture_output=True, text=True, timeout=60)
    assert res.returncode == 0, res.stderr
    return {s["name"]: s for s in json.loads(res.stdout)["services"]}


def test_shard_recipe_split_and_standby_takeover(tmp_path):
    (commands,) = _section_blocks("Converter shards and a hot standby")
    router_cmd, conv_a, conv_b, standby_cmd, rec_cmd, src_cmd, ps_cmd = commands
    port = free_tcp_port()
    _copy_services(tmp_path, port)
    procs: list[Proc] = []
    try:
        router = Proc(f"{router_cmd} -l tcp/127.0.0.1:{port}", tmp_path)
        procs.append(router)
        router.wait_for(r"router router: zenoh id")
        a, b = Proc(conv_a, tmp_path), Proc(conv_b, tmp_path)
        procs += [a, b]
        a.wait_for(r"converter conv-a: 16 detectors.*boards/modules: 1 stream")
        b.wait_for(r"converter conv-b: 16 detectors.*boards/modules: 1 stream")
        standby = Proc(standby_cmd, tmp_path)
        procs.append(standby)
        standby.wait_for(r"converter standby: 32 detectors")
        rec = Proc(rec_cmd, tmp_path)
        procs.append(rec)
        rec.wait_for(r"recording mntes/lab/\*\* into")
        src = Proc(src_cmd, tmp_path)
        procs.append(src)
        # ps, as written: who owns what; the standby holds both streams back, no conflict anywhere.
        deadline = time.monotonic() + 60
        while True:
            res = subprocess.run([sys.executable, "-m", "mntes_stream", *ps_cmd.split()[1:]], cwd=tmp_path,
                                 capture_output=True, text=True, timeout=60)
            assert res.returncode == 0, res.stderr
            if all(re.search(p, res.stdout) for p in (r"conv-a .* modules=\[0\] streams=1 publishing=1",
                                                      r"conv-b .* modules=\[1\] streams=1 publishing=1",
                                                      r"standby .* streams=2 publishing=0 held=2 \(standby\)")):
                break
            assert time.monotonic() < deadline, res.stdout
        assert "CONFLICT" not in res.stdout
        by = _ps(tmp_path)
        assert by["standby"]["owns"]["claimed_also_by"] == ["0/0:conv-a", "0/1:conv-b"]
        # conv-a dies: the standby publishes module 0 (and still holds module 1 back for conv-b).
        a.p.kill()
        a.p.wait(30)
        standby.wait_for(r"took over stream 0/0", 10)
        deadline = time.monotonic() + 10
        while (owns := _ps(tmp_path)["standby"]["owns"])["publishing"] != 1:
            assert time.monotonic() < deadline, owns
        assert owns["held"] == ["0/1"] and owns["takeovers"] == 1
        for p in (src, rec, b, standby, router):
            assert p.interrupt(30) in (0, 130)
        for p in (src, rec, b, standby, router):
            assert not any("Traceback" in line for line in p.seen), "".join(p.seen)
    finally:
        for p in procs:
            if p.p.poll() is None:
                p.p.kill()
                p.p.wait()
