"""services/README.md's walk-through, run command for command (loopback, bounded, stops by itself).

The README's commands are read from its code blocks and run as written, from a
copy of services/ in a temporary directory (the converter's port is moved to a
free one, so parallel runs cannot collide): the monitor must show the source's
housekeeping, the recording must hold counts, housekeeping and power, a replay
of it must come out of a second converter as power, and the array simulator
must feed a converter that uses its truth parameters.
"""

from __future__ import annotations

import queue
import re
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from mntes_stream.io.transport import QueueSubscriber, ZenohSettings, free_tcp_port, open_session

ROOT = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _blocks() -> list[list[str]]:
    text = (ROOT / "services" / "README.md").read_text()
    section = text.split("## Walk-through on one machine", 1)[1].split("\n## ", 1)[0]
    blocks = re.findall(r"```\n(.*?)```", section, re.S)
    return [[line for line in b.splitlines() if line.strip()] for b in blocks]


class Proc:
    """A walk-through command in the background, its output read by threads (every wait has a deadline)."""

    def __init__(self, command: str, cwd: Path):
        argv = shlex.split(command)
        assert argv[0] == "mntes-stream", command
        self.command = command
        self.p = subprocess.Popen([sys.executable, "-m", "mntes_stream", *argv[1:]], cwd=cwd, text=True,
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE)
        self.lines: queue.Queue = queue.Queue()
        self.seen: list[str] = []
        self.stdout: list[str] = []  # stdout alone (a --json document without the log lines of stderr)
        for stream in (self.p.stdout, self.p.stderr):
            threading.Thread(target=self._pump, args=(stream,), daemon=True).start()

    def _pump(self, stream) -> None:
        for line in stream:
            if stream is self.p.stdout:
                self.stdout.append(line)
            self.lines.put(line)

    def wait_for(self, pattern: str, timeout_s: float = 90.0) -> str:
        deadline = time.monotonic() + timeout_s
        rx = re.compile(pattern)
        while time.monotonic() < deadline:
            try:
                line = self.lines.get(timeout=0.2)
            except queue.Empty:
                assert self.p.poll() is None, f"{self.command} ended: {''.join(self.seen)}"
                continue
            self.seen.append(line)
            if rx.search(line):
                return line
        raise AssertionError(f"{self.command}: no {pattern!r} within {timeout_s} s: {''.join(self.seen[-30:])}")

    def interrupt(self, timeout_s: float = 60.0) -> int:
        """SIGINT, then the exit code. Any code but 0 or 130 prints the command's last output, which pytest shows
        with a failed check of it (test_shards_recipe once read -2, which is how Python exits when a
        KeyboardInterrupt escapes: where it came from was never seen)."""
        if self.p.poll() is None:
            self.p.send_signal(signal.SIGINT)
        try:
            rc = self.p.wait(timeout=timeout_s)
        finally:
            if self.p.poll() is None:
                self.p.kill()
                self.p.wait()
        if rc not in (0, 130):
            time.sleep(0.5)  # the pump threads read what is left
            while not self.lines.empty():
                self.seen.append(self.lines.get_nowait())
            print(f"{self.command} exited with {rc}; its last output:\n{''.join(self.seen[-40:])}")
        return rc


def _power_counter(port: int):
    """A test-side subscriber to power on the converter's port: how much power came out."""
    session = open_session(ZenohSettings(connect=(f"tcp/127.0.0.1:{port}",)))
    return session, QueueSubscriber(session, ["mntes/lab/power/**"])


def _drain_count(sub, seconds: float) -> int:
    n = 0
    deadline = time.monotonic() + seconds
    while time.monotonic() < deadline:
        if sub.get(timeout_s=0.1) is not None:
            n += 1
    return n


def test_services_readme_walkthrough(tmp_path):
    blocks = _blocks()
    assert len(blocks) == 3 and len(blocks[0]) == 5 and len(blocks[1]) == 2 and len(blocks[2]) == 2, blocks
    shutil.copytree(ROOT / "services", tmp_path / "services", ignore=shutil.ignore_patterns("recordings", "*-params.toml"))
    port = free_tcp_port()
    for name in ("zenoh-converter.json5", "zenoh-local.json5"):
        f = tmp_path / "services" / name
        f.write_text(f.read_text().replace("7447", str(port)))
    conv_cmd, rec_cmd, src_cmd, mon_cmd, inspect_cmd = blocks[0]
    procs: list[Proc] = []
    try:
        # --- block 1: converter, recorder, source, monitor; then inspect the recording.
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
        # The monitor sees the converter (a service row with a rate) and the source's housekeeping.
        mon.wait_for(r"housekeeping: t_bath \d+\.\d+ mK \(age [\d.]+ s\)\s+b_field -?\d+\.\d+ uT", 120)
        mon.wait_for(r"^converter\s+\d+\.\d", 60)
        assert mon.interrupt() in (0, 130)
        assert src.interrupt() in (0, 130)
        assert conv.interrupt() in (0, 130)
        assert rec.interrupt() in (0, 130)
        for p in (src, conv, rec):
            assert not any("Traceback" in line for line in p.seen), "".join(p.seen)
        res = subprocess.run([sys.executable, "-m", "mntes_stream", *shlex.split(inspect_cmd)[1:]], cwd=tmp_path,
                             capture_output=True, text=True, timeout=120)
        assert res.returncode == 0, res.stderr
        assert ", complete" in res.stdout
        counts = {m.group(2): int(m.group(1)) for m in re.finditer(r"^\s+(\d+)\s+(\S+)$", res.stdout, re.M)}
        n_counts = sum(n for t, n in counts.items() if "/counts/" in t)
        n_power = sum(n for t, n in counts.items() if "/power/" in t)
        assert n_counts > 0 and n_power == n_counts, counts  # everything sent was converted and recorded
        assert any("/hk/t_bath" in t for t in counts) and any(t.endswith("/provenance") for t in counts)

        # --- block 2: a converter and the replay of that recording: power comes out again.
        conv2_cmd, replay_cmd = blocks[1]
        conv2 = Proc(conv2_cmd, tmp_path)
        procs.append(conv2)
        conv2.wait_for(r"converter converter: \d+ detectors")
        session, sub = _power_counter(port)
        try:
            replay = Proc(replay_cmd, tmp_path)
            procs.append(replay)
            assert replay.p.wait(timeout=180) == 0, "".join(replay.seen)
            assert _drain_count(sub, 3.0) == n_power  # the replayed counts, each converted once
        finally:
            sub.close()
            session.close()
        assert conv2.interrupt() in (0, 130)

        # --- block 3: the array simulator, and a converter calibrated with its truth.
        sim_cmd, conv3_cmd = blocks[2]
        sim = Proc(sim_cmd, tmp_path)
        procs.append(sim)
        deadline = time.monotonic() + 90
        while not (tmp_path / "services" / "simulator-params.toml").exists():
            assert time.monotonic() < deadline and sim.p.poll() is None, "".join(sim.seen)
            time.sleep(0.1)
        conv3 = Proc(conv3_cmd, tmp_path)
        procs.append(conv3)
        conv3.wait_for(r"converter converter: 128 detectors")
        session, sub = _power_counter(port)
        try:
            # The simulator started first: its session re-dials the converter every 0.5 s doubling to
            # 4 s, so power may start up to ~4 s (more under load) after the converter is up.
            assert sub.get(timeout_s=30.0) is not None, "no power from the simulator's counts within 30 s"
            assert _drain_count(sub, 4.0) > 10
        finally:
            sub.close()
            session.close()
        assert sim.interrupt() in (0, 130) and conv3.interrupt() in (0, 130)
    finally:
        for p in procs:
            if p.p.poll() is None:
                p.p.kill()
                p.p.wait()
