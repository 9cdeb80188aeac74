"""``mntes-stream bench g3``: the G3 bridge's throughput (detector-samples per second), file and live.

A raw DAQ run (Wiring, DfMux housekeeping, GcpSlow, then one Timepoint frame
per sample with random int32 counts for ``--boards`` x ``--modules`` x
``--channels`` detectors at the DfMux rate) is written with spt3g's classes
into a temporary directory (not timed). Then:

- ``translate``: G3 file read + :class:`~mntes_stream.g3.translate.FrameTranslator`
  (frames -> encoded counts/housekeeping messages), no zenoh, from the first
  counts message on; ``housekeeping_frame_s``: one DfMux housekeeping frame
  through spt3g's conversion functions for every bolometer (once per
  housekeeping frame, ~100 s apart at a DAQ);
- ``file``: the ``g3-bridge`` service on the file, publishing on zenoh
  (loopback) to a subscriber that drains every message;
- ``live``: a real spt3g ``G3NetworkSender`` in another process streams the
  run as fast as it can (connect mode, through a 127.0.0.1 relay: its listen
  mode binds every interface) to the bridge's ``G3Reader``, and on to zenoh
  as above; timed from the bridge's first to its last counts message.

A 16,000-detector SPT-3G array at 152.587890625 Hz is 2.44 M detector-samples
per second: the result says whether one bridge keeps up, or how many bridges
(one per group of boards) it takes.
"""

from __future__ import annotations

import math
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ, DFMUX_TICKS_PER_SAMPLE, G3_TICK_NS

HELP = "G3 bridge throughput: raw DfMux Timepoints -> counts messages, file and live (samples per second)"
SPT3G_ARRAY_DETECTORS = 16_000
SPT3G_RATE = SPT3G_ARRAY_DETECTORS * DFMUX_SAMPLE_RATE_HZ

_SENDER = r"""
import sys
from spt3g import core
path, port = sys.argv[1], int(sys.argv[2])
s = core.G3NetworkSender(hostname="127.0.0.1", port=port)
for f in core.G3File(path):
    s(f)
s(core.G3Frame(core.G3FrameType.EndProcessing))
s.Close()
"""


def add_arguments(p) -> None:
    p.add_argument("--boards", type=int, default=4, help="IceBoards (default 4)")
    p.add_argument("--modules", type=int, default=8, help="modules per board (max 8)")
    p.add_argument("--channels", type=int, default=64, help="channels per module (DfMux: 64 or 128)")
    p.add_argument("--seconds", type=float, default=10.0, help="stream time in the run")
    p.add_argument("--chunk-samples", type=int, default=16, help="Timepoints per counts chunk")
    p.add_argument("--no-live", action="store_true", help="skip the G3NetworkSender run")


def write_run(path: Path, boards: int, modules: int, channels: int, n_samples: int, seed: int = 0) -> int:
    """A raw DAQ run with random counts; returns the detector-samples in it."""
    from mntes_stream.g3 import frames as F
    from mntes_stream.g3 import spt3g

    core, _ = spt3g()
    rng = np.random.default_rng(seed)
    t0 = 1_700_000_000 * 10**9
    layout = {f"B{b}.{m}.{c}": (b, m, c) for b in range(boards) for m in range(modules) for c in range(channels)}
    w = core.G3Writer(filename=str(path))
    w(F.wiring_frame(layout))
    w(F.housekeeping_frame(t0 - 10, {b: {m: F.ModuleHk(2, 3, np.full(channels, 0.1), 1.6e6 + 4e4 * np.arange(channels))
                                         for m in range(modules)} for b in range(boards)}))
    w(F.gcpslow_frame(t0, 0.1))
    pool = rng.integers(-2**22, 2**22, size=(64, boards * modules, 2, channels), dtype=np.int32)
    for k in range(n_samples):
        block = pool[k % 64]
        samples = {(b, m): (block[b * modules + m, 0], block[b * modules + m, 1])
                   for b in range(boards) for m in range(modules)}
        w(F.timepoint_frame(t0 + k * DFMUX_TICKS_PER_SAMPLE * G3_TICK_NS, samples, channels))
    w(core.G3Frame(core.G3FrameType.EndProcessing))
    return n_samples * len(layout)


class _Relay:
    """127.0.0.1 relay: the sender's connection piped to the bridge's."""

    def __init__(self):
        self.up = socket.create_server(("127.0.0.1", 0))
        self.down = socket.create_server(("127.0.0.1", 0))
        self.up.settimeout(60)
        self.down.settimeout(60)
        self.up_port, self.down_port = self.up.getsockname()[1], self.down.getsockname()[1]
        self.thread = threading.Thread(target=self._run, daemon=True)
        self.thread.start()

    def _run(self):
        try:
            u, _ = self.up.accept()
            d, _ = self.down.accept()
        except OSError:
            return
        with u, d:
            while chunk := u.recv(1 << 20):
                d.sendall(chunk)

    def close(self):
        self.up.close()
        self.down.close()


def _bridge(source: str, samples: int, chunk_samples: int, start_sender=None, before_stop=None) -> dict:
    """Run the bridge on ``source`` until ``samples`` detector-samples were published; rate over its counts."""
    from mntes_stream.g3.bridge import BridgeSettings, G3BridgeConfig, G3BridgeService
    from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session
    from mntes_stream.service.base import StopFlag

    port = free_tcp_port()
    svc = G3BridgeService(G3BridgeConfig(
        bridge=BridgeSettings(source=source, chunk_samples=chunk_samples, wait_subscribers_s=10.0, reconnect_s=0.05,
                              timeout_s=30.0), zenoh=loopback(connect_ports=[port])))
    stop = StopFlag()
    out: dict = {}
    times: list[float] = []
    with open_session(loopback(port)) as z:
        sub = QueueSubscriber(z, ["mntes/lab/**"], maxsize=1 << 16)
        th = threading.Thread(target=lambda: out.update(svc.start(stop=stop)), daemon=True)
        th.start()
        sender = start_sender() if start_sender else None
        try:
            deadline = time.monotonic() + 600
            while time.monotonic() < deadline:
                snap = svc.status()
                if snap.get("samples", 0) >= samples or (not th.is_alive()):
                    break
                for key, _, t_recv in sub.drain(4096):
                    if "/counts/" in key:
                        times.append(t_recv)
                time.sleep(0.01)
            end = time.monotonic() + 5
            while time.monotonic() < end and sub.qsize():
                for key, _, t_recv in sub.drain(1 << 16):
                    if "/counts/" in key:
                        times.append(t_recv)
        finally:
            if before_stop is not None:  # e.g. close the relay: a reader blocked on it returns at once
                before_stop()
            stop.set()
            th.join(60)
            sub.close()
            if sender is not None:
                sender.wait(60)
    got = out.get("samples", 0)
    span = (max(times) - min(times)) * 1e-9 if len(times) > 1 else float("nan")
    return {"samples": got, "seconds": span, "msamples_per_s": got / span / 1e6 if span > 0 else float("nan")}


def run(args) -> dict:
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3 import spt3g
    from mntes_stream.g3.files import read_frames
    from mntes_stream.g3.translate import FrameTranslator

    core, _ = spt3g()
    if args.modules > 8:
        raise ConfigError("--modules: at most 8 per board")
    directory = Path(tempfile.mkdtemp(prefix="mntes-bench-g3-"))
    try:
        n_samp = int(round(args.seconds * DFMUX_SAMPLE_RATE_HZ))
        path = directory / "run.g3"
        samples = write_run(path, args.boards, args.modules, args.channels, n_samp)
        detectors = args.boards * args.modules * args.channels
        tr = FrameTranslator("lab", chunk_samples=args.chunk_samples)
        n_bytes = 0
        t_first, first = None, 0
        for frame in read_frames(path):
            out = tr.handle(frame)
            n_bytes += sum(len(p) for _, p in out)
            if t_first is None and tr.counters.samples:  # steady state: from the first counts on, as below
                t_first, first = time.perf_counter(), tr.counters.samples
        n_bytes += sum(len(p) for _, p in tr.flush())
        t_translate = time.perf_counter() - t_first
        if tr.counters.samples != samples:
            raise ConfigError(f"translated {tr.counters.samples} detector-samples, wrote {samples}")
        result = {
            "detectors": detectors, "sample_rate_hz": DFMUX_SAMPLE_RATE_HZ, "stream_seconds": args.seconds,
            "detector_samples": samples, "g3_mb": round(path.stat().st_size / 1e6, 1),
            "message_mb": round(n_bytes / 1e6, 1), "spt3g": core.__file__,
            "translate_msamples_per_s": round((samples - first) / t_translate / 1e6, 3),
        }
        # One DfMux housekeeping frame: spt3g's conversion functions for every bolometer (per frame, not per sample).
        from mntes_stream.g3.mapping import Wiring, hk_snapshot

        meta = [fr for fr, _ in zip(read_frames(path), range(3))]
        wiring = Wiring.from_frame(meta[0])
        t0 = time.perf_counter()
        hk_snapshot(meta[1]["DfMuxHousekeeping"], wiring)
        result["housekeeping_frame_s"] = round(time.perf_counter() - t0, 3)
        f = _bridge(str(path), samples, args.chunk_samples)
        result["file_msamples_per_s"] = round(f["msamples_per_s"], 3)
        if not args.no_live:
            relay = _Relay()
            try:
                live = _bridge(f"tcp://127.0.0.1:{relay.down_port}", samples, args.chunk_samples,
                               start_sender=lambda: subprocess.Popen(
                                   [sys.executable, "-c", _SENDER, str(path), str(relay.up_port)],
                                   stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL), before_stop=relay.close)
            finally:
                relay.close()
            result["live_samples_received"] = live["samples"]
            result["live_msamples_per_s"] = round(live["msamples_per_s"], 3)
        rates = [result[k] for k in ("file_msamples_per_s", "live_msamples_per_s") if k in result]
        worst = min(rates) * 1e6
        result["spt3g_array_msamples_per_s"] = round(SPT3G_RATE / 1e6, 3)
        result["keeps_up_with_16000_detectors"] = bool(worst >= SPT3G_RATE)
        result["bridges_for_16000_detectors"] = math.ceil(SPT3G_RATE / worst) if worst > 0 else None
        result["note"] = ("2 shared cores under load from other jobs: ratios in one run are meaningful, "
                          "absolute figures are a lower bound")
        return result
    finally:
        shutil.rmtree(directory, ignore_errors=True)
