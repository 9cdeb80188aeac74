"""Helpers for the recorder/replay tests: real messages and loopback zenoh endpoints."""

from __future__ import annotations

import contextlib
import signal
import subprocess
import sys
import threading
import time
import warnings
from pathlib import Path

import numpy as np

from mntes_stream.io import mcap as mcap_io
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk, Provenance
from mntes_stream.io.transport import Publishers, free_tcp_port


def free_endpoint() -> str:
    """A ``tcp/127.0.0.1:<port>`` endpoint on a port free right now."""
    return f"tcp/127.0.0.1:{free_tcp_port()}"


def counts_payload(seq: int, *, setup: str = "t", board: int = 0, module: int = 0, n_ch: int = 4, n_samp: int = 8) -> bytes:
    rng = np.random.default_rng(seq)
    t0 = 1_700_000_000_000_000_000 + seq * 100_000_000
    return CountsChunk(
        setup=setup, board=board, module=module, channels=np.arange(n_ch, dtype=np.int32), seq=seq,
        t0_ns=t0, sample_rate_hz=80.0,
        counts_i=rng.integers(-2**20, 2**20, (n_ch, n_samp), dtype=np.int32),
        counts_q=rng.integers(-2**20, 2**20, (n_ch, n_samp), dtype=np.int32),
        t_pub_ns=t0 + 100_000_000,
    ).to_bytes()


def hk_payload(seq: int, *, setup: str = "t", sensor: str = "t_bath") -> bytes:
    t = 1_700_000_000_000_000_000 + seq * 100_000_000
    return HousekeepingChunk(
        setup=setup, sensor=sensor, seq=seq, t_ns=np.array([t], dtype=np.int64), value=np.array([0.1 + 1e-6 * seq]), unit="K",
    ).to_bytes()


def provenance_payload(tag: str = "a", *, setup: str = "t") -> bytes:
    return Provenance(
        setup=setup, params_toml=f'schema = "mntes-params"\nversion = 1\n# {tag}\n', table_identity=f"sha256:{tag}",
        converter_kind="exact", software_version="test", t_ns=1_700_000_000_000_000_000,
    ).to_bytes()


class _Dead:
    """A stop flag for :meth:`Publishers.wait_matching` that is set when ``alive()`` turns False."""

    def __init__(self, alive):
        self._alive = alive

    def is_set(self) -> bool:
        return self._alive is not None and not self._alive()


def matched_publishers(z, keys, timeout_s: float = 30.0, alive=None) -> Publishers:
    """BLOCK publishers on ``keys``, each with a matching subscriber (fail after ``timeout_s``,
    or at once when ``alive()``, the subscriber's liveness, turns False)."""
    pubs = Publishers(z)
    if not pubs.wait_matching(keys, timeout_s, _Dead(alive)):
        missing = [k for k in keys if not pubs.publisher(k).matching_status.matching]
        if alive is not None and not alive():
            raise RuntimeError(f"the subscriber died before subscribing to {missing}")
        raise TimeoutError(f"no subscriber for {missing} after {timeout_s} s")
    return pubs


def readable_messages(source) -> list:
    """Messages readable right now from a recording that may still be growing (never raises)."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", mcap_io.TruncatedFileWarning)
        try:
            return list(mcap_io.iter_messages(source))
        except Exception:  # the file may not exist yet, or be mid-write at its very start
            return []


@contextlib.contextmanager
def running_recorder(directory, *, attempts: int = 3, start_timeout_s: float = 30.0, **config):
    """``run_recorder`` in a thread, listening on a free loopback port; yields ``(endpoint, result)``.

    ``result`` gets ``stats`` when the recorder has stopped (at the end of the
    block, or earlier with ``duration_s``). A port taken by another process
    between choosing and binding it is retried with a new one; any other
    start-up failure is raised at once instead of surfacing as a timeout, and
    a recorder not ready within ``start_timeout_s`` is stopped and reported.
    """
    from mntes_stream.io.transport import ZenohSettings
    from mntes_stream.service.recorder import RecorderConfig, run_recorder

    config = {"setup": "t", "flush_interval_s": 0.1, **config}
    for attempt in range(attempts):
        ep = free_endpoint()
        cfg = RecorderConfig(directory=str(directory), zenoh=ZenohSettings(listen=(ep,)), **config)
        stop, ready, result = threading.Event(), threading.Event(), {}

        def target():
            try:
                result["stats"] = run_recorder(cfg, stop, ready)
            except Exception as exc:  # handed to the test thread below
                result["error"] = exc

        thread = threading.Thread(target=target, daemon=True)  # daemon: a hung recorder cannot hang pytest's exit
        thread.start()
        deadline = time.monotonic() + start_timeout_s
        while not ready.wait(0.05) and thread.is_alive():
            if time.monotonic() > deadline:
                stop.set()
                thread.join(10)
                raise TimeoutError(f"the recorder was not ready after {start_timeout_s} s"
                                   + ("" if not thread.is_alive() else " and does not stop"))
        if ready.is_set():
            break
        thread.join()
        if attempt == attempts - 1 or "cannot open zenoh session" not in str(result.get("error")):
            raise result["error"]
    try:
        yield ep, result
    finally:
        stop.set()
        thread.join(30)
    if "error" in result:
        raise result["error"]


_WRITER_RECORDING = """
import sys, time
from mntes_stream.core.convert import make_converter
from mntes_stream.io import keys
from mntes_stream.io.mcap import RotatingMcapWriter
from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
from mntes_stream.service.source import MinimalSource, SourceConfig
T0 = 1_700_000_000_000_000_000
src = MinimalSource(SourceConfig(setup="t", modules=2, channels=8))
params = {p.detector_id: p for p in src.params}
pipe = ConverterPipeline(make_converter("table", params), PipelineConfig(setup="t"), params=params, clock=None)
w = RotatingMcapWriter(sys.argv[1], "rec", flush_interval_s=3600, rotate_s=0, rotate_bytes=0)
w.write(keys.provenance_key("t"), pipe.provenance_bytes(), T0)
for t_pub, batch in src.batches(T0, float(sys.argv[2])):
    for key, payload in batch:
        w.write(key, payload, t_pub + 1_000_000)
    w.flush()  # one chunk per batch, as the recorder's flush cadence makes them
if sys.argv[3] == "finish":
    w.close()
print(w.messages, flush=True)
time.sleep(120)  # killed long before: unless closed, the file never gets its summary
"""


def writer_recording(directory, seconds: float, *, finish: bool) -> tuple[Path, int]:
    """``(path, messages written)`` of a recording by the recorder's writer (RotatingMcapWriter, one chunk per
    batch of a MinimalSource, ``seconds`` of it) in a child process SIGKILLed after its last flush, or after
    closing the file when ``finish``."""
    proc = subprocess.Popen([sys.executable, "-c", _WRITER_RECORDING, str(directory), str(seconds),
                             "finish" if finish else "kill"], stdout=subprocess.PIPE, text=True)
    try:
        written = int(proc.stdout.readline())
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
    return Path(directory) / "rec-000001.mcap", written
