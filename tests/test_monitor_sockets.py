"""The monitor's sockets are bounded: idle sockets cannot starve the page, nor flood the log.

The issue's case: 1,100 idle sockets under a 1,024-descriptor limit made
``/api/state`` time out and wrote 50,511 tracebacks in 45 s. Here the monitor
runs as a process with RLIMIT_NOFILE lowered to 256 and is sent 300 idle or
half-finished connections (loopback, closed at the end); the page server's
own limit, its header deadline and its keep-alive timeout are checked on the
real aiohttp server, and its log on the real stderr.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import resource
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("aiohttp", reason="the monitor extra (aiohttp) is not installed")

import aiohttp  # noqa: E402

from mntes_stream.io.transport import free_tcp_port, loopback
from mntes_stream.monitor.aggregate import MonitorConfig
from mntes_stream.monitor.server import serve
from mntes_stream.monitor.subscriber import MonitorSubscriber
from mntes_stream.monitor.web_limits import RateLog, WebLimits

NOFILE = 256


def _lower_nofile():
    # The hard limit too: zenoh raises the soft limit to the hard one when its session opens.
    resource.setrlimit(resource.RLIMIT_NOFILE, (NOFILE, NOFILE))


def _state(port: int, timeout_s: float) -> dict:
    with socket.create_connection(("127.0.0.1", port), timeout=timeout_s) as s:
        s.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\nConnection: close\r\n\r\n")
        data = b""
        while chunk := s.recv(65536):
            data += chunk
    head, _, body = data.partition(b"\r\n\r\n")
    assert head.startswith(b"HTTP/1.1 200"), head[:200]
    return json.loads(body)


def _closed(s: socket.socket) -> bool:
    """True once the server closed ``s`` (what it sent before is read and dropped)."""
    try:
        while True:
            if s.recv(65536, socket.MSG_DONTWAIT) == b"":
                return True
    except BlockingIOError:
        return False
    except ConnectionError:
        return True


def test_idle_sockets_beyond_the_descriptor_limit_do_not_starve_the_page_nor_flood_the_log(tmp_path):
    zport = free_tcp_port()
    cfg = tmp_path / "monitor.toml"
    cfg.write_text("[monitor]\nsetup = 'lab'\nport = 0\nupdate_s = 0.2\nduration_s = 40.0\n"
                   "header_timeout_s = 2.0\nidle_timeout_s = 3.0\n")
    proc = subprocess.Popen(
        [sys.executable, "-m", "mntes_stream", "monitor", "--config", str(cfg), "--listen", f"tcp/127.0.0.1:{zport}"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, preexec_fn=_lower_nofile)
    socks: list[socket.socket] = []
    try:
        line = proc.stdout.readline()
        assert "serving http://" in line, (line, proc.stderr.read() if proc.poll() is not None else "")
        port = int(line.split("http://127.0.0.1:")[1].split("/")[0])
        # 300 connections, more than the process may open: 200 send nothing, 100 half a request line.
        for i in range(300):
            s = socket.create_connection(("127.0.0.1", port), timeout=5)
            if i % 3 == 2:
                s.sendall(b"GET /api/sta")
            socks.append(s)
        t0 = time.monotonic()
        state = _state(port, timeout_s=5)
        answered_s = time.monotonic() - t0
        assert answered_s < 2.0, answered_s
        conn = state["web"]["connections"]
        # The limit was capped below the descriptor limit (256 less what is open, a reserve and the backlog).
        assert conn["max_connections"] <= NOFILE - 64 - 64 and conn["peak"] <= conn["max_connections"]
        # Beyond the limit each socket evicted the oldest idle one, or (in a burst accepted before any was
        # connected) was closed at once; an early one may have met its header deadline already.
        assert conn["evicted_idle"] > 0
        assert conn["evicted_idle"] + conn["over_limit"] + conn["header_timeout"] >= 300 - conn["max_connections"]
        # Within the header deadline (2 s) plus a margin every idle or half-sent socket is closed by the server.
        deadline = time.monotonic() + 6
        while time.monotonic() < deadline and not all(_closed(s) for s in socks):
            time.sleep(0.2)
        assert sum(_closed(s) for s in socks) == 300
        conn = _state(port, timeout_s=5)["web"]["connections"]
        assert conn["header_timeout"] >= 1
        assert conn["evicted_idle"] + conn["over_limit"] + conn["header_timeout"] >= 300
        assert conn["open"] <= 2  # the request asking, at most one other
        # A kept-alive connection idle past idle_timeout_s (3 s) is closed too.
        with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
            s.sendall(b"GET /api/state HTTP/1.1\r\nHost: 127.0.0.1\r\n\r\n")
            assert s.recv(65536).startswith(b"HTTP/1.1 200")
            t_idle = time.monotonic()
            while not _closed(s) and time.monotonic() - t_idle < 8:
                time.sleep(0.2)
            assert _closed(s) and 2.0 <= time.monotonic() - t_idle <= 7.0
    finally:
        for s in socks:
            s.close()
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            _, err = proc.communicate(timeout=30)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait(10)
    assert proc.returncode == 0, err
    lines = [x for x in err.splitlines() if x.strip()]
    assert "Traceback" not in err
    assert len(lines) <= 10, err  # one line per cause per interval: here a handful, not one per socket
    assert any("idle connection closed for a new one" in x for x in lines), err
    assert any("at most" in x and "descriptor limit is 256" in x for x in lines), err


class _Server:
    """The page server on a free loopback port in a thread, with the given limits."""

    def __init__(self, limits: WebLimits):
        self.limits = limits
        self.stop = threading.Event()
        self.ready = threading.Event()
        self.port = None
        self.error = None

    def _run(self, sub):
        try:
            serve(sub, "127.0.0.1", 0, 0.2, 60.0, lambda h, p: (setattr(self, "port", p), self.ready.set()),
                  self.stop, limits=self.limits)
        except BaseException as exc:
            self.error = exc

    @contextlib.contextmanager
    def running(self):
        with MonitorSubscriber("lab", loopback(free_tcp_port()), MonitorConfig(history_s=5.0)) as sub:
            t = threading.Thread(target=self._run, args=(sub,), daemon=True)
            t.start()
            try:
                assert self.ready.wait(15), self.error
                yield f"http://127.0.0.1:{self.port}"
            finally:
                self.stop.set()
                t.join(15)
                assert not t.is_alive() and self.error is None, self.error


def test_over_the_limit_with_every_connection_busy_is_refused_at_once_and_logged_once(caplog):
    """Three pages (websockets, never evicted) hold the limit of 3: 40 more connections are closed at once,
    counted, in one log line; once a page leaves, a request is answered again."""
    caplog.set_level(logging.INFO, logger="mntes_stream.monitor")

    async def scenario(base):
        async with aiohttp.ClientSession() as http:
            pages = [await http.ws_connect(base + "/ws") for _ in range(3)]
            refused = 0
            t0 = time.monotonic()
            for _ in range(40):
                try:
                    async with aiohttp.ClientSession() as other, other.get(base + "/api/state") as r:
                        await r.read()
                except aiohttp.ClientError:
                    refused += 1
            assert refused == 40 and time.monotonic() - t0 < 10  # closed at once, not after a timeout
            await pages[0].close()
            await asyncio.sleep(0.2)
            async with aiohttp.ClientSession() as other, other.get(base + "/api/state") as r:
                conn = (await r.json())["web"]["connections"]
            # aiohttp's client retries a GET once on a closed connection: each of the 40 is refused once or twice
            assert 40 <= conn["over_limit"] <= 80 and conn["max_connections"] == 3 and conn["evicted_idle"] == 0
            for ws in pages[1:]:
                await ws.close()

    with _Server(WebLimits(max_connections=3)).running() as base:
        asyncio.run(scenario(base))
    over = [r for r in caplog.records if "connection refused" in r.getMessage()]
    assert len(over) == 1 and not any(r.exc_info for r in caplog.records)


def test_rate_log_says_each_cause_once_per_interval_with_its_count(caplog):
    now = [0.0]
    log = logging.getLogger("test.ratelog")
    rl = RateLog(log, 10.0, clock=lambda: now[0])
    with caplog.at_level(logging.INFO, logger="test.ratelog"):
        for i in range(1034):
            now[0] = i * 0.01  # 1,034 events over 10.3 s
            rl.note("over_limit", "connection refused over the limit")
        rl.note("other", "something else")
        now[0] = 25.0
        rl.flush()
    msgs = [r.getMessage() for r in caplog.records]
    assert msgs[0].startswith("monitor: connection refused over the limit (repeats are counted")
    # The first at once, then the 1,000 of the next 10 s in one line, then the rest at the next flush.
    assert msgs[1] == "monitor: 1,000 x connection refused over the limit in the last 10 s"
    assert msgs[2].startswith("monitor: something else")
    assert msgs[3] == "monitor: 33 x connection refused over the limit in the last 15 s"
    assert len(msgs) == 4 and rl.counts == {"over_limit": 1034, "other": 1}


def test_other_libraries_errors_become_counted_lines_without_tracebacks(caplog):
    rl = RateLog(logging.getLogger("test.ratelog2"), 10.0)
    lib = logging.getLogger("test.somelib")
    lib.addFilter(rl.filter)
    try:
        with caplog.at_level(logging.INFO):
            for _ in range(500):
                try:
                    raise OSError(24, "Too many open files")
                except OSError:
                    lib.exception("Error handling request")
    finally:
        lib.removeFilter(rl.filter)
    assert [r.name for r in caplog.records] == ["test.ratelog2"]
    assert "Error handling request (OSError: [Errno 24] Too many open files)" in caplog.records[0].getMessage()
    assert caplog.records[0].exc_info is None
    assert rl.counts[next(iter(rl.counts))] == 500


@pytest.mark.parametrize("bad", [{"max_connections": 1}, {"header_timeout_s": 0}, {"idle_timeout_s": -1}])
def test_limits_are_checked_settings(bad):
    from mntes_stream.errors import ConfigError

    with pytest.raises(ConfigError):
        WebLimits(**bad)
