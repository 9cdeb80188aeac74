"""The live G3 bridge: a real spt3g G3NetworkSender -> g3-bridge -> zenoh, on loopback only.

G3NetworkSender's listen mode binds every interface, so the DAQ side runs it
in connect mode towards a loopback relay (127.0.0.1), which the bridge's
G3Reader reads as it would the DAQ's tee: the bytes on the wire are the
sender's own. The DAQ "restarts" halfway (a second sender process, 5
Timepoints later): the bridge reconnects, counts the gap, and every count it
publishes equals what the file ingest gives for that sample.
"""

from __future__ import annotations

import socket
import subprocess
import sys
import threading
import time

import pytest

pytest.importorskip("spt3g.core")

from test_g3 import LAYOUT, N_SAMP, messages_by_detector, raw_frames, write  # noqa: E402

from mntes_stream.io.messages import decode  # noqa: E402
from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session  # noqa: E402

SENDER = r"""
import sys, time
from spt3g import core
path, port, first, last = sys.argv[1], int(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4])
s = core.G3NetworkSender(hostname="127.0.0.1", port=port)
k = 0
for f in core.G3File(path):
    if f.type == core.G3FrameType.Timepoint:
        k += 1
        if not first <= k - 1 < last:
            continue
    s(f)
s(core.G3Frame(core.G3FrameType.EndProcessing))
s.Close()
"""


class Relay:
    """Loopback relay: each DAQ connection (upstream) is piped to the next reader connection (downstream)."""

    def __init__(self):
        self.up = socket.create_server(("127.0.0.1", 0))
        self.down = socket.create_server(("127.0.0.1", 0))
        self.up.settimeout(20)
        self.down.settimeout(20)
        self.up_port, self.down_port = self.up.getsockname()[1], self.down.getsockname()[1]
        self.rounds = 0
        self.thread = threading.Thread(target=self._run, args=(2,), daemon=True)
        self.thread.start()

    def _run(self, rounds):
        for _ in range(rounds):
            try:
                u, _ = self.up.accept()
                d, _ = self.down.accept()
            except OSError:
                return
            with u, d:
                while chunk := u.recv(1 << 16):
                    d.sendall(chunk)
            self.rounds += 1

    def close(self):
        self.up.close()
        self.down.close()


def test_live_bridge_equals_file_ingest_and_counts_the_gap(tmp_path):
    from mntes_stream.g3.bridge import BridgeSettings, G3BridgeConfig, G3BridgeService
    from mntes_stream.service.base import StopFlag

    raw = write(raw_frames(), tmp_path / "raw.g3")
    file_counts, _ = messages_by_detector(raw)
    relay = Relay()
    port = free_tcp_port()
    skipped = range(30, 35)  # the DAQ restarts: these 5 Timepoints are never sent
    cfg = G3BridgeConfig(bridge=BridgeSettings(source=f"tcp://127.0.0.1:{relay.down_port}", setup="lab",
                                               reconnect_s=0.2, timeout_s=5.0, wait_subscribers_s=5.0),
                         zenoh=loopback(connect_ports=[port]))
    svc = G3BridgeService(cfg)
    stop = StopFlag()
    result = {}
    live: dict = {}
    with open_session(loopback(port)) as z:
        sub = QueueSubscriber(z, ["mntes/lab/**"])
        th = threading.Thread(target=lambda: result.update(svc.start(stop=stop)), daemon=True)
        th.start()
        try:
            for first, last in ((0, skipped.start), (skipped.stop, N_SAMP)):
                p = subprocess.run([sys.executable, "-c", SENDER, str(raw), str(relay.up_port), str(first), str(last)],
                                   timeout=60, capture_output=True)
                assert p.returncode == 0, p.stderr.decode()[-2000:]
                deadline = time.monotonic() + 20
                while relay.rounds < (1 if first == 0 else 2) and time.monotonic() < deadline:
                    time.sleep(0.05)
            want = len(LAYOUT) * (N_SAMP - len(skipped))
            deadline = time.monotonic() + 20
            while len(live) < want and time.monotonic() < deadline:
                item = sub.get(timeout_s=0.2)
                if item is None:
                    continue
                key, payload, _ = item
                if "/counts/" in key:
                    msg = decode(payload)
                    for row, ch in enumerate(msg.channels):
                        d = f"b{msg.board}m{msg.module}c{ch:03d}"
                        for t, i, q in zip(msg.times_ns(), msg.counts_i[row], msg.counts_q[row]):
                            live[(d, int(t))] = (int(i), int(q))
        finally:
            stop.set()
            th.join(30)
            sub.close()
            relay.close()
    assert len(live) == len(LAYOUT) * (N_SAMP - len(skipped))
    assert all(file_counts[k] == v for k, v in live.items())
    assert result["connections"] == 2 and result["reconnects"] == 1
    assert result["gap_samples"] == len(skipped)
    # the ledger: the gap is never received in each module's stream (5 samples, one chunk of 16), nothing rejected
    assert {k: v.get("missing", 0) for k, v in result["ledger"].items()} == {"1234/2": 1, "1234/5": 1}
    assert result["lost"] == 2 and result["rejected_frames"] == 0
