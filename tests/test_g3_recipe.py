"""docs/g3-recipe.md, command for command: a G3 run (and a DAQ's G3NetworkSender) to power, CLI only.

The page's code blocks are run as written, in a temporary directory holding
a copy of services/. Two substitutions only: the converter's zenoh port 7447
becomes a free one, and the DAQ's tee ``tcp://daq:5353`` becomes a loopback
relay fed by a real spt3g G3NetworkSender in another process (its listen
mode binds every interface, so it connects to the relay instead: the bytes
the bridge reads are the sender's own). The one-shot commands run in this
process through ``mntes_stream.cli.main`` (what the console script calls),
the services in processes of their own. Loopback only; every wait bounded.
"""

from __future__ import annotations

import re
import shlex
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("spt3g.core", reason="the g3 extra (spt3g) is not installed")

from test_g3_live import SENDER, Relay  # noqa: E402

from mntes_stream.io.transport import free_tcp_port  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow  # processes end to end (CI runs it; the fast subset does not)
DOC = ROOT / "docs" / "g3-recipe.md"


def _blocks() -> list[list[str]]:
    blocks = re.findall(r"```\n(.*?)```", DOC.read_text(), re.S)
    return [[line for line in b.splitlines() if line.strip()] for b in blocks]


def _argv(command: str) -> list[str]:
    argv = shlex.split(command)
    assert argv[0] == "mntes-stream", command
    return [sys.executable, "-m", "mntes_stream", *argv[1:]]


def _run(command: str, cwd: Path, capsys) -> str:
    """A one-shot command of the page, in this process (the real ``main``, as the console script calls it)."""
    import os

    from mntes_stream.cli import main

    argv = shlex.split(command)
    assert argv[0] == "mntes-stream", command
    here = os.getcwd()
    os.chdir(cwd)
    try:
        rc = main(argv[1:])
    finally:
        os.chdir(here)
    out = capsys.readouterr()
    assert rc == 0, f"{command}: {out.err[-3000:]}"
    return out.out


def _topic_counts(inspect_stdout: str) -> dict[str, int]:
    return {m.group(2): int(m.group(1)) for m in re.finditer(r"^\s+(\d+)\s+(mntes/\S+)$", inspect_stdout, re.M)}


class _Background:
    """A long-running command of the page; its log in a file (read when it is stopped)."""

    def __init__(self, command: str, cwd: Path, log: Path):
        self.log = log
        self.out = open(log, "w")
        self.p = subprocess.Popen(_argv(command), cwd=cwd, stdout=self.out, stderr=subprocess.STDOUT, text=True)

    def wait_for(self, pattern: str, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if re.search(pattern, self.log.read_text()):
                return
            assert self.p.poll() is None, self.log.read_text()[-3000:]
            time.sleep(0.2)
        raise AssertionError(f"no {pattern!r} within {timeout_s} s: {self.log.read_text()[-3000:]}")

    def stop(self) -> int:
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
        try:
            return self.p.wait(timeout=60)
        finally:
            if self.p.poll() is None:
                self.p.kill()
                self.p.wait()
            self.out.close()


def test_g3_recipe_as_written(tmp_path, capsys):
    blocks = _blocks()
    assert [len(b) for b in blocks] == [1, 1, 3, 3, 1], blocks
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("recordings"))
    port = free_tcp_port()
    for name in ("zenoh-converter.json5", "zenoh-local.json5"):
        f = tmp_path / "services" / name
        f.write_text(f.read_text().replace("7447", str(port)))

    # 1-2: a run and the converter's parameter file.
    _run(blocks[0][0], tmp_path, capsys)
    assert {"run.g3", "run.params.toml", "run.bolometer-params.toml"} <= {p.name for p in tmp_path.iterdir()}
    _run(blocks[1][0], tmp_path, capsys)
    other = tmp_path / "other-names.toml"  # a list naming other bolometers: one line, exit code 2
    other.write_text((tmp_path / "run.bolometer-params.toml").read_text().replace('"Sim', '"Other'))
    from mntes_stream.cli import main

    bad = shlex.split(blocks[1][0].replace("run.bolometer-params.toml", str(other))
                      .replace("converter-params.toml", str(tmp_path / "x.toml")).replace("run.g3", str(tmp_path / "run.g3")))
    assert main(bad[1:]) == 2
    assert "no wired bolometer has parameters" in capsys.readouterr().err.strip().splitlines()[-1]

    # 3: offline.
    convert, inspect, export = blocks[2]
    _run(convert, tmp_path, capsys)
    counts = _topic_counts(_run(inspect, tmp_path, capsys))
    n_counts = sum(n for t, n in counts.items() if "/counts/" in t)
    assert n_counts > 0 and sum(n for t, n in counts.items() if "/power/" in t) == n_counts, counts
    _run(export, tmp_path, capsys)
    assert (tmp_path / "power.h5").stat().st_size > 0

    # 4: live, the DAQ's tee (a G3NetworkSender) -> bridge -> converter -> recorder.
    conv_cmd, rec_cmd, bridge_cmd = blocks[3]
    relay = Relay()
    procs = []
    try:
        conv = _Background(conv_cmd, tmp_path, tmp_path / "converter.log")
        procs.append(conv)
        conv.wait_for(r"converter converter: \d+ detectors")
        rec = _Background(rec_cmd, tmp_path, tmp_path / "recorder.log")
        procs.append(rec)
        rec.wait_for(r"recording mntes/lab/\*\* into")
        assert "tcp://daq:5353" in bridge_cmd
        bridge = _Background(bridge_cmd.replace("tcp://daq:5353", f"tcp://127.0.0.1:{relay.down_port}"), tmp_path,
                             tmp_path / "bridge.log")
        procs.append(bridge)
        sender = subprocess.run([sys.executable, "-c", SENDER, str(tmp_path / "run.g3"), str(relay.up_port), "0",
                                 str(10**9)], capture_output=True, text=True, timeout=120)
        assert sender.returncode == 0, sender.stderr[-2000:]
        deadline = time.monotonic() + 60
        while relay.rounds < 1 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert relay.rounds == 1
        time.sleep(3.0)  # the last chunks through the converter to the recorder (flush cadence 1 s)
        assert bridge.stop() in (0, 130)
        assert conv.stop() in (0, 130)
        assert rec.stop() in (0, 130)
    finally:
        for p in procs:
            p.stop()
        relay.close()
    for p in procs:
        assert "Traceback" not in p.log.read_text(), p.log.read_text()[-3000:]
    live = _topic_counts(_run(blocks[4][0], tmp_path, capsys))
    live_counts = sum(n for t, n in live.items() if "/counts/" in t)
    assert live_counts == n_counts, (live, counts)  # every chunk of the run came through the tee
    assert sum(n for t, n in live.items() if "/power/" in t) == live_counts, live
