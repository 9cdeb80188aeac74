"""Crash-only services (issue 22, item 4): real processes on loopback, each test bounded.

- A recorder and a converter started as clients of a router that is not
  there yet wait for it (saying so in their log and heartbeat), and once a
  router comes up on that port they record and convert what is published.
- ``up`` restarts a converter killed with SIGKILL, says so, and power flows again.
"""

from __future__ import annotations

import dataclasses
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
from mntes_stream.service.base import Service
from mntes_stream.service.supervise import RestartBudget, Services, exit_reason

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


@dataclasses.dataclass(frozen=True)
class _DiesConfig:
    after_s: float = 0.3


class _Dies(Service):
    """Ready at once, then the process dies (as a SIGKILLed one does: no result, no clean stop)."""

    name = "dies"
    Config = _DiesConfig

    def step(self, ctx) -> bool:  # ready once setup (none) returned
        time.sleep(self.config.after_s)
        os._exit(3)


def test_services_restart_a_dying_child_until_the_budget_is_spent():
    from mntes_stream.cli.up import _restart_dead

    services, said = Services(), []
    budget = RestartBudget(2)
    services.start("dies", _Dies, _DiesConfig())
    try:
        give_up = None
        deadline = time.monotonic() + 30
        while give_up is None and time.monotonic() < deadline:
            time.sleep(0.1)
            give_up = _restart_dead(services, budget, None, lambda line, err=False: said.append(line))
    finally:
        services.stop("dies", 5)
    assert services.restarts["dies"] == 2 and services.deaths["dies"] == ["exit code 3", "exit code 3"]
    assert said[0] == "  dies died (exit code 3); restarting it (restart 1)" and len(said) == 4, said
    assert give_up == "dies died (exit code 3) after 2 restart(s), more than 2 within a minute (--restarts); giving up"


def test_ctrl_c_ends_the_wait_for_a_router_with_one_line(tmp_path):
    port = free_tcp_port()
    rec = Proc(f"mntes-stream record --dir rec -m client -e tcp/127.0.0.1:{port}", tmp_path)
    try:
        rec.wait_for(r"waiting for router tcp/127\.0\.0\.1:\d+: unreachable \(1 attempt", 60)
    finally:
        t0 = time.monotonic()
        rc, out = _finish(rec)
    assert time.monotonic() - t0 < 5 and rc == 2, out
    assert re.search(r"mntes-stream: error: stopped while waiting for router tcp/127\.0\.0\.1:\d+ \(\d+ attempts? "
                     r"in \d+ s; never connected\)", out), out
    assert "Traceback" not in out


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
    # Each --json document from its stdout alone: a log line on stderr may come between its lines.
    published, rec_stats, conv_stats = (_json_in("".join(p.stdout)) for p in (src, rec, conv))
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
    return json.JSONDecoder().raw_decode(text[text.index("{\n"):])[0]


def _pid_of(service: str, port: int) -> int:
    """A service's pid, from its heartbeat (``ps`` reads the same), over a peer link to its port."""
    with open_session(ZenohSettings(mode="peer", connect=(f"tcp/127.0.0.1:{port}",))) as s:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            found = [b for b in list_services(s, "lab", 1.0) if b["service"] == service and "pid" in b]
            if found:
                return int(found[0]["pid"])
        raise AssertionError(f"no {service} heartbeat")


def _up_killing(victim: str, tmp_path: Path, duration_s: float) -> tuple[int, dict, str]:
    """``up --json`` with ``victim`` SIGKILLed once the converter's uptime passes 2 s: (rc, JSON, stderr)."""
    cmd = [sys.executable, "-m", "mntes_stream", "up", "--duration", str(duration_s), "--modules", "1",
           "--channels", "8", "--minimal", "--out", str(tmp_path / "up"), "--json"]
    p = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        err: list[str] = []
        port = None
        while True:  # up's progress lines go to stderr with --json
            line = p.stderr.readline()
            assert line, "".join(err)
            err.append(line)
            if m := re.search(rf"{victim} :(\d+)", line):
                port = int(m.group(1))
            if re.search(r"t=\s+[2-9]\.\d s  power chunks", line):
                break
        os.kill(_pid_of(victim, port), signal.SIGKILL)
        out, rest = p.communicate(timeout=90)
    finally:
        if p.poll() is None:
            p.kill()
            p.wait()
    return p.returncode, json.loads(out), "".join(err) + rest


def test_up_restarts_a_killed_converter_and_power_flows_again(tmp_path):
    rc, doc, err_text = _up_killing("converter", tmp_path, 14)
    assert rc == 0, err_text
    assert "converter died (killed by SIGKILL); restarting it (restart 1)" in err_text
    assert re.search(r"converter restarted in [\d.]+ s", err_text)
    after = err_text.split("restarted in", 1)[1]
    lines = re.findall(r"power chunks\s+(\d+) .*restarts converter 1", after)
    assert lines and int(lines[-1]) > 20, after  # the new converter's own count, growing
    assert "restarted converter 1 time(s) (killed by SIGKILL)" in err_text
    assert doc["restarts"] == {"converter": 1} and doc["deaths"] == {"converter": ["killed by SIGKILL"]}
    assert doc["ok"] is True
    conv = doc["services"]["converter"]
    # The new converter continued from the checkpoint, and what was published while none ran came from the
    # source's history (io/history.py): converted, nothing missed; what the first had converted (before its
    # checkpoint) came again and was dropped as a duplicate.
    whole = Ledger.from_dict(conv["ledger"]).totals()
    rec = doc["services"]["recorder"]
    counts = rec["by_kind"]["counts"]
    assert conv["chunks_converted"] > 20 and whole.pending == 0, conv
    if conv["chunks_lost"]:
        # Why a restart loses chunks (seen once at load ~6): the new converter continues from its checkpoint
        # (written with each status, 1 s), and the source keeps 10 s of history; a restart that outlives it
        # (start, imports, snapshot, kernels, on a busy machine) finds the oldest chunks gone. So a loss needs
        # the restart to have taken about the history plus the chunks lost (death noticed and the checkpoint's
        # age: up to 2 s more); a quicker restart that loses chunks is a bug. The hole is stated: never
        # received by the converter, counts without power in the recording (what offline convert fills).
        restart_s = float(re.search(r"converter restarted in ([\d.]+) s", err_text)[1])
        lost_s = conv["chunks_lost"] * 0.1  # up's chunks: --chunk-s 0.1
        assert restart_s + 2.0 >= 10.0 + lost_s - 1.0, (restart_s, conv["chunks_lost"], conv["ledger"])
        assert whole.missing == conv["chunks_lost"], conv["ledger"]
        assert "recorded without power" in rec.get("ledger_note", ""), rec
        assert rec["ledger_note"] in err_text
    else:  # the ledger covers both converter processes: every counts chunk the recorder has was converted, and
        # once (the chunks the new one took again from its checkpoint's floor were converted by both processes)
        assert whole.missing == 0 and whole.done + whole.late == counts, (conv["ledger_line"], counts)
    # The ledger over both processes holds the new one's and what the killed one converted that did not come
    # again (all of it came again when the kill followed its first status: then the two are equal).
    assert whole.done >= conv["chunks_converted"], conv["ledger"]
    assert re.search(r"\(over 2 converter processes(; \d+ chunk\(s\) converted again after a restart, counted once)?\)$",
                     conv["ledger_line"]), conv["ledger_line"]
    assert err_text.rstrip().splitlines()[-1] == f"  converter: {conv['ledger_line']}"


def test_up_restarts_a_killed_recorder_and_its_ledger_shows_the_gap(tmp_path):
    rc, doc, err_text = _up_killing("recorder", tmp_path, 10)
    assert rc == 0, err_text
    assert "recorder died (killed by SIGKILL); restarting it (restart 1)" in err_text
    assert doc["restarts"] == {"recorder": 1} and doc["ok"] is True
    rec, conv = doc["services"]["recorder"], doc["services"]["converter"]
    assert len(rec["files"]) == 1 and len(list((tmp_path / "up" / "recordings").glob("*.mcap"))) == 2
    # The recorder's ledger spans both files, not the last process's alone: what neither process wrote
    # (its downtime, the killed file's unflushed end) is never received, not hidden (a source that keeps
    # history, io/history.py, lets the new recorder fetch it again: then duplicates instead); with what
    # was recorded it is every chunk the converter (never restarted) received.
    assert rec["ledger_line"].endswith("(over 2 recorder processes, recomputed from the files)"), rec["ledger_line"]
    recorded, converted = Ledger.from_dict(rec["ledger"]).totals(), Ledger.from_dict(conv["ledger"]).totals()
    assert recorded.done > rec["by_kind"]["counts"] - recorded.duplicate, (rec["ledger"], rec["by_kind"])
    assert recorded.done + recorded.missing == converted.received + converted.missing, (rec["ledger"], conv["ledger"])
    assert recorded.pending == 0 and (recorded.missing > 0 or recorded.duplicate > 0)
    # (with what the recording lacks, if anything: counts recorded without power, io/mcap/ledger.py)
    assert f"  recorder counts: {rec['ledger_line']}{rec.get('ledger_note', '')}" in err_text.splitlines()


def test_a_recorder_keeps_recording_across_a_router_killed_and_restarted(tmp_path):
    port = free_tcp_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("recordings", "*-params.toml"))
    procs: list[Proc] = []
    try:
        procs.append(router := Proc(f"mntes-stream router -l {endpoint}", tmp_path))
        router.wait_for(r"router router: zenoh id")
        procs.append(rec := Proc(f"mntes-stream record --dir rec --json -m client -e {endpoint}", tmp_path))
        rec.wait_for(r"recording mntes/lab/\*\* into", 60)
        router.p.kill()  # kill -9: no goodbye to the recorder
        router.p.wait(10)
        time.sleep(1.0)
        procs.append(router := Proc(f"mntes-stream router -l {endpoint}", tmp_path))
        router.wait_for(r"router router: zenoh id")
        # zenoh's client re-dials (connect/retry: 1 s, growing to 4 s): the recorder is seen through the new router.
        with open_session(ZenohSettings(mode="client", connect=(endpoint,))) as s:
            deadline = time.monotonic() + 20
            while not any(b["service"] == "recorder" for b in list_services(s, "lab", 0.5)):
                assert time.monotonic() < deadline, "the recorder did not come back through the new router"
        src = Proc(f"mntes-stream serve --config services/source.toml --duration 2 --json -m client -e {endpoint}",
                   tmp_path)
        procs.append(src)
        assert src.p.wait(timeout=60) == 0, "".join(src.seen)
        _finish(src)
        time.sleep(1.0)
        rc, rec_out = _finish(rec)
        assert rc == 0, rec_out
    finally:
        for p in reversed(procs):
            p.interrupt(30)
    published, by_kind = _json_in("".join(src.seen)), _json_in(rec_out)["by_kind"]
    assert by_kind.get("counts", 0) >= 2 * 19 and by_kind["counts"] + by_kind.get("hk", 0) == published["messages"], \
        (published, by_kind)
