"""Crash-only services (issue 22, item 4): real processes on loopback, each test bounded.

- A recorder and a converter started as clients of a router that is not
  there yet wait for it (saying so in their log and heartbeat), and once a
  router comes up on that port they record and convert what is published.
- ``up`` restarts a converter killed with SIGKILL, says so, and power flows again.
"""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

from test_services_walkthrough import Proc

from mntes_stream.core.ledger import Ledger
from mntes_stream.io.presence import list_services
from mntes_stream.io.reconnect import Backoff
from mntes_stream.io.transport import ZenohSettings, free_tcp_port, open_session
from mntes_stream.service.supervise import RestartBudget, exit_reason

ROOT = Path(__file__).resolve().parents[1]


def test_backoff_is_bounded_and_the_restart_budget_is_per_minute():
    b = Backoff(0.5, 8.0)
    assert [b.next_s() for _ in range(7)] == [0.5, 1.0, 2.0, 4.0, 8.0, 8.0, 8.0]
    budget = RestartBudget(2)
    assert [budget.take("converter", t) for t in (0.0, 1.0, 2.0)] == [True, True, False]
    assert budget.take("source", 2.0)  # per service
    assert budget.take("converter", 60.5)  # the first restart has left the minute
    assert not RestartBudget(0).take("converter", 0.0)
    assert exit_reason(-signal.SIGKILL) == "killed by SIGKILL" and exit_reason(1) == "exit code 1"


def _finish(proc: Proc, timeout_s: float = 30.0) -> tuple[int, str]:
    """SIGINT, wait, and everything the process wrote (stdout and stderr, interleaved by line)."""
    rc = proc.interrupt(timeout_s)
    time.sleep(0.2)  # the reader threads take the last lines
    while not proc.lines.empty():
        proc.seen.append(proc.lines.get())
    return rc, "".join(proc.seen)


def test_recorder_and_converter_wait_for_a_router_that_comes_up_later(tmp_path):
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("recordings", "*-params.toml"))
    client = f"-m client -e {endpoint}"
    procs: list[Proc] = []
    try:
        # Nothing listens on the port: before, both exited with code 2 at once.
        procs.append(rec := Proc(f"mntes-stream record --dir rec --json {client}", tmp_path))
        procs.append(conv := Proc(f"mntes-stream serve --config services/converter.toml --heartbeat-s 1 --json {client}",
                                  tmp_path))
        for p in (rec, conv):
            p.wait_for(rf"waiting for router {re.escape(endpoint)}: unreachable \(1 attempt", 60)
            p.wait_for(r"unreachable \(2 attempts", 30)
        # The heartbeat says so too (serve logs it every --heartbeat-s).
        conv.wait_for(rf"converter converter: waiting for router {re.escape(endpoint)}: unreachable \(\d+ attempts", 30)
        assert rec.p.poll() is None and conv.p.poll() is None

        procs.append(router := Proc(f"mntes-stream router -l {endpoint}", tmp_path))
        router.wait_for(r"router router: zenoh id")
        rec.wait_for(r"recording mntes/lab/\*\* into", 30)
        conv.wait_for(r"converter converter: \d+ detectors", 90)

        # Then a source (also a client of the router) publishes 2 s of data, and ends.
        src = Proc(f"mntes-stream serve --config services/source.toml --duration 2 --json {client}", tmp_path)
        procs.append(src)
        assert src.p.wait(timeout=60) == 0, "".join(src.seen)
        _finish(src)
        time.sleep(2.0)  # the converter's last power reaches the recorder
        rc_conv, conv_out = _finish(conv)
        rc_rec, rec_out = _finish(rec)
        assert rc_conv == 0 and rc_rec == 0, conv_out + rec_out
    finally:
        for p in reversed(procs):
            p.interrupt(30)
    published, rec_stats, conv_stats = (_json_in("".join(src.seen)), _json_in(rec_out), _json_in(conv_out))
    by_kind = rec_stats["by_kind"]
    # Everything the source published after the router came up is recorded: 2 s of 0.1 s counts
    # chunks from 2 modules, and the housekeeping, ...
    assert by_kind.get("counts", 0) >= 2 * 19, by_kind
    assert by_kind["counts"] + by_kind.get("hk", 0) == published["messages"], (published, by_kind)
    # ... and every counts chunk is converted, its power recorded.
    assert conv_stats["chunks_converted"] == by_kind["counts"], conv_stats
    assert by_kind.get("power", 0) == by_kind["counts"], by_kind


def _json_in(text: str) -> dict:
    """The JSON document (``--json``) in a command's output, among its log lines."""
    return json.loads(text[text.index("{\n"):text.rindex("}") + 1])


def _converter_pid(port: int) -> int:
    """The converter's pid, from its heartbeat (``ps`` reads the same), over a peer link to its port."""
    with open_session(ZenohSettings(mode="peer", connect=(f"tcp/127.0.0.1:{port}",))) as s:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            found = [b for b in list_services(s, "lab", 1.0) if b["service"] == "converter" and "pid" in b]
            if found:
                return int(found[0]["pid"])
        raise AssertionError("no converter heartbeat")


def test_up_restarts_a_killed_converter_and_power_flows_again(tmp_path):
    cmd = [sys.executable, "-m", "mntes_stream", "up", "--duration", "14", "--modules", "1", "--channels", "8",
           "--minimal", "--out", str(tmp_path / "up"), "--json"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        err: list[str] = []
        port = None
        while True:  # up's progress lines go to stderr with --json
            line = p.stderr.readline()
            assert line, "".join(err)
            err.append(line)
            if m := re.search(r"converter :(\d+)", line):
                port = int(m.group(1))
            if re.search(r"t=\s+2\.\d s  power chunks", line):
                break
        pid = _converter_pid(port)
        os.kill(pid, signal.SIGKILL)
        out, rest = p.communicate(timeout=90)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    err_text = "".join(err) + rest
    assert p.returncode == 0, err_text
    assert "converter died (killed by SIGKILL); restarting it (restart 1)" in err_text
    assert re.search(r"converter restarted in [\d.]+ s", err_text)
    after = rest.split("restarted in", 1)[1]
    lines = re.findall(r"power chunks\s+(\d+) .*restarts converter 1", after)
    assert lines and int(lines[-1]) > 20, after  # the new converter's own count, growing
    assert "restarted converter 1 time(s) (killed by SIGKILL)" in err_text
    doc = json.loads(out)
    assert doc["restarts"] == {"converter": 1} and doc["deaths"] == {"converter": ["killed by SIGKILL"]}
    assert doc["ok"] is True
    conv = doc["services"]["converter"]
    # The new converter continued from the checkpoint: what was published while none ran is counted, not hidden.
    assert conv["chunks_converted"] > 20 and conv["chunks_lost"] > 0, conv
    # The ledger covers both converter processes: every counts chunk the recorder has is in it exactly once
    # (converted by the first or the second, or never received while none ran).
    whole = Ledger.from_dict(conv["ledger"]).totals()
    counts = doc["services"]["recorder"]["by_kind"]["counts"]
    assert whole.received + whole.missing == counts and whole.pending == 0, (conv["ledger"], counts)
    assert whole.done > conv["chunks_converted"] and whole.missing > 0
    assert conv["ledger_line"].endswith("(over 2 converter processes)")
    assert err_text.rstrip().splitlines()[-1] == f"  converter: {conv['ledger_line']}"
