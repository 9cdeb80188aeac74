"""Restart benchmark: how long after a converter process starts does power flow again (5,120 detectors).

A source publishes the array in real time (default 40 modules x 128 channels
at 200 Hz, 0.1 s chunks) and keeps going. A converter is started as its own
process (``mntes-stream serve``, exactly what an operator or systemd runs),
first with an empty table cache (the bank is built and cached), then killed
with SIGKILL and started again ``--restarts`` times with the cache warm.
For each start, measured from the moment the process is spawned (interpreter,
imports, parameters, table bank, compiled kernels, zenoh session):

- ``ready_s``: its provenance is received (subscribed, converting from now);
- ``first_power_s``: its first power chunk is received;
- ``all_modules_s``: every module has had a power chunk from it;
- ``missed_per_module``: counts chunks of each module (median) published
  after the last power of the killed process and never converted by the new
  one during its run (0 when the sources' history covers the restart: the new
  converter starts where its checkpoint says, ``io/history.py``; recovered
  history may reach it after its first live chunks);
  ``restarted_chunks_lost``: what the restarted converter itself reports (its
  ``checkpoint``), to compare.

``imports_s`` is what a bare interpreter takes to import the converter's
modules on this machine at this moment (measured alongside, three times,
median): the part of a start that is Python's, not the converter's. On a
shared machine every figure moves with its load (``load_average_1min``).

The converter connects to the source and to the measuring session (as a
client connects to its router), so a restart is not also a reconnection
back-off of the others.
"""

from __future__ import annotations

import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mntes_stream.options import add_zenoh_args, zenoh_layer

HELP = "converter restart: process start to power flowing again, cold and with the table cache warm"


def add_arguments(p) -> None:
    p.add_argument("--modules", type=int, default=40, help="readout modules (default 40)")
    p.add_argument("--channels", type=int, default=128, help="channels per module (default 128)")
    p.add_argument("--sample-rate", type=float, default=200.0, metavar="HZ", help="default 200")
    p.add_argument("--chunk-s", type=float, default=0.1, help="chunk length (default 0.1 s)")
    p.add_argument("--restarts", type=int, default=3, help="warm restarts after the cold start (default 3)")
    p.add_argument("--run-s", type=float, default=3.0, metavar="S", help="each converter runs this long before "
                   "it is killed (default 3 s)")
    p.add_argument("--kind", default="table", help="conversion kind (default table)")
    add_zenoh_args(p)


def _converter_toml(work: Path, params: Path, kind: str, connect: list[str]) -> Path:
    f = work / "converter.toml"
    f.write_text(
        "[converter]\n"
        f'setup = "bench"\nparams = "{params}"\nkind = "{kind}"\ntable_cache = "{work / "cache"}"\n'
        f'provenance_interval_s = 0\ncheckpoint = "{work / "state.json"}"\n'
        "[status]\ninterval_s = 0.5\n"
        f'[zenoh]\nmode = "peer"\nconnect = {connect!r}\n'.replace("'", '"'))
    return f


def _imports_s() -> float:
    """Spawn-to-exit of an interpreter that imports what ``serve`` of a converter imports."""
    runs = []
    for _ in range(3):
        t0 = time.monotonic()
        subprocess.run([sys.executable, "-c", "import mntes_stream.cli, mntes_stream.service.converter, "
                        "mntes_stream.pipeline.pipeline, mntes_stream.core.convert, zenoh"], check=True)
        runs.append(time.monotonic() - t0)
    return statistics.median(runs)


def _one_start(config: Path, sub, n_modules: int, run_s: float, last_power: dict, timeout_s: float = 900.0) -> dict:
    """Spawn a converter, time it to provenance, first power and every module; run ``run_s``; SIGKILL it."""
    from mntes_stream.errors import TransportError
    from mntes_stream.io.messages import CountsChunk, PowerChunk, StatusMessage, decode

    while sub.get(timeout_s=0.05) is not None:  # what the previous process left behind
        pass
    t0 = time.monotonic()
    proc = subprocess.Popen([sys.executable, "-m", "mntes_stream", "serve", "--config", str(config), "-q"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    ready = first = all_mods = None
    first_seq: dict = {}
    power_seqs: dict = {}
    counts_seq: dict = {}
    last_status = None
    try:
        deadline = t0 + timeout_s
        while time.monotonic() < deadline:
            item = sub.get(timeout_s=0.05)
            now = time.monotonic() - t0
            if all_mods is not None and now >= all_mods + run_s:
                break
            if proc.poll() is not None:
                raise TransportError(f"bench restart: the converter ended: {proc.stderr.read()[-2000:]}")
            if item is None:
                continue
            key, payload, _ = item
            if "/provenance" in key and ready is None:
                ready = now
            elif "/counts/" in key:
                c = CountsChunk.from_bytes(payload)
                counts_seq.setdefault((c.board, c.module), []).append(c.seq)
            elif "/power/" in key:
                pw = PowerChunk.from_bytes(payload)
                first = now if first is None else first
                first_seq.setdefault((pw.board, pw.module), pw.seq)
                power_seqs.setdefault((pw.board, pw.module), set()).add(pw.seq)
                last = last_power.get((pw.board, pw.module))
                last_power[(pw.board, pw.module)] = pw.seq if last is None else max(last, pw.seq)
                if all_mods is None and len(first_seq) == n_modules:
                    all_mods = now
            elif "/status/" in key:
                last_status = decode(payload)
        else:
            raise TransportError(f"bench restart: no power from every module within {timeout_s} s")
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGKILL)  # a crash: nothing flushed, nothing said
        proc.wait(30)
    return {"ready_s": ready, "first_power_s": first, "all_modules_s": all_mods, "first_seq": first_seq,
            "power_seqs": power_seqs,
            "status": last_status if isinstance(last_status, StatusMessage) else None}


def run(args) -> dict:
    from mntes_stream.io import keys
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session
    from mntes_stream.service.source import MinimalSource, SourceConfig, SourceServiceConfig
    from mntes_stream.service.supervise import Services

    n = max(1, round(args.chunk_s * args.sample_rate))
    sc = SourceConfig(setup="bench", boards=1, modules=args.modules, channels=args.channels,
                      sample_rate_hz=args.sample_rate, chunk_s=args.chunk_s, hk_interval_s=n / args.sample_rate,
                      cycle_s=1.0)
    zenoh = zenoh_layer(args)
    out: dict = {"channels": args.modules * args.channels, "modules": args.modules, "sample_rate_hz": args.sample_rate,
                 "chunk_s": n / args.sample_rate, "kind": args.kind, "load_average_1min": [round(os.getloadavg()[0], 2)]}
    with tempfile.TemporaryDirectory(prefix="mntes-bench-restart-") as tmp:
        work = Path(tmp)
        params = work / "params.toml"
        dump_params(MinimalSource(sc).params, params)
        p_src, p_meas = free_tcp_port(), free_tcp_port()
        config = _converter_toml(work, params, args.kind, [f"tcp/127.0.0.1:{p_src}", f"tcp/127.0.0.1:{p_meas}"])
        services = Services()
        with open_session(zenoh.over(loopback(p_meas, [p_src]))) as z:
            sub = QueueSubscriber(z, [keys.power_key("bench", "*", "*"), keys.provenance_key("bench"),
                                      keys.status_key("bench", "**"), keys.counts_key("bench", "*", "*")],
                                  maxsize=1 << 16)
            try:
                services.start("source", "source", SourceServiceConfig(
                    source=sc, params=str(params), duration_s=0, zenoh=zenoh.over(loopback(p_src))))
                last_power: dict = {}
                starts = []
                for i in range(1 + args.restarts):
                    before = dict(last_power)
                    r = _one_start(config, sub, args.modules, args.run_s, last_power)
                    if i > 0:  # chunks of each module after the killed process's last power never converted by the
                        # new one during its run (history it recovers may come after its first live chunk)
                        r["missed"] = [sum(1 for q in range(before[m] + 1, max(seqs)) if q not in seqs)
                                       for m, seqs in r["power_seqs"].items() if m in before]
                    r.pop("power_seqs")
                    starts.append(r)
            finally:
                services.stop("source", timeout_s=30)
                sub.close()
    cold, warm = starts[0], starts[1:]
    out["imports_s"] = round(_imports_s(), 3)

    def med(key):
        vals = [s[key] for s in warm if s[key] is not None]
        return round(statistics.median(vals), 3) if vals else None

    out.update({
        "cold_ready_s": round(cold["ready_s"], 3),
        "cold_first_power_s": round(cold["first_power_s"], 3),
        "cold_all_modules_s": round(cold["all_modules_s"], 3),
        "warm_restarts": len(warm),
        "warm_ready_s": [round(s["ready_s"], 3) for s in warm],
        "warm_first_power_s": [round(s["first_power_s"], 3) for s in warm],
        "warm_all_modules_s": [round(s["all_modules_s"], 3) for s in warm],
        "warm_first_power_s_median": med("first_power_s"),
        "warm_all_modules_s_median": med("all_modules_s"),
        "missed_per_module_median": [statistics.median(s["missed"]) if s.get("missed") else None for s in warm],
        "missed_total": [sum(s["missed"]) if s.get("missed") else None for s in warm],
        "restarted_chunks_lost": [s["status"].chunks_lost if s["status"] is not None else None for s in warm],
    })
    out["load_average_1min"].append(round(os.getloadavg()[0], 2))
    return out
