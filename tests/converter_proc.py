"""A converter service as a process of its own (``mntes-stream serve``) on loopback, and a process's memory."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from mntes_stream.io.paramfile import dump_params
from mntes_stream.io.transport import free_tcp_port
from mntes_stream.service.source import MinimalSource


def mem_mb(pid: int | str = "self", what: str = "VmRSS") -> float:
    """Resident memory of a process now (``VmRSS``) or at its peak so far (``VmHWM``), in MiB."""
    with open(f"/proc/{pid}/status") as f:
        for line in f:
            if line.startswith(what + ":"):
                return int(line.split()[1]) / 1024
    raise AssertionError(f"no {what}")


def start_converter(tmp_path: Path, source: MinimalSource, converter: str = "", rest: str = ""):
    """``serve`` a table converter of ``source``'s detectors (setup ``lab``) in ``tmp_path``, listening on a free
    loopback port; ``converter`` and ``rest`` add lines to its ``[converter]`` table and after it.

    Returns ``(process, port, log path)``.
    """
    dump_params(source.params, tmp_path / "params.toml")
    port = free_tcp_port()
    (tmp_path / "converter.toml").write_text(
        '[converter]\nsetup = "lab"\nparams = "params.toml"\nkind = "table"\ntable_cache = "cache"\n'
        f'{converter}{rest}[status]\ninterval_s = 0.5\n[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{port}"]\n')
    log = tmp_path / "serve.log"
    with open(log, "wb") as f:
        proc = subprocess.Popen([sys.executable, "-m", "mntes_stream", "serve", "--config", "converter.toml", "-q"],
                                stdout=f, stderr=subprocess.STDOUT, cwd=tmp_path)
    return proc, port, log
