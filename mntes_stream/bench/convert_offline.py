"""``mntes-stream bench convert-offline``: offline ``convert`` of a recording, as a multiple of real time.

A simulated recording (``--detectors`` in modules of ``--channels``, ``--seconds``
at ``--sample-rate``, counts and housekeeping as ``simulate --out`` writes them)
is converted by ``mntes-stream convert REC OUT --params P`` in a process of its
own, as a user runs it: once with an empty cache (``HOME`` pointed at the work
directory: the table bank and the converter built and cached), then
``--repeat`` times with the cache warm; then in this process with
:func:`~mntes_stream.pipeline.offline.convert_recording` (imports and compiled
kernels already loaded). Each run is timed end to end (converter, reading,
the pipeline, writing the output MCAP); the figure is seconds of data per wall
second (target: 20x for 2,048 detectors x 30 s). Besides, each part alone in
the same minutes: the converter from the warm cache, reading the recording,
decoding the counts, and the numba kernel on the recording's own chunks;
``--profile N`` adds cProfile's top N functions (own time) of one more warm
run in process; ``--batch-s`` the in-process figure with ``batch_s=S`` besides
the default (0, the default of this option: message by message, each output
stamped at the message that released it; the default conversion puts the
messages of each second of receive time through the pipeline together).
``--startup`` measures the command's start-up alone (imports, the compiled
kernels' load, the converter from the warm cache): the same command, with the
same parameters, on a recording of one module for ``--chunk-s``; the
command's figure without it is given too.
"""

from __future__ import annotations

import dataclasses
import os
import resource
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HELP = "offline convert of a recording (default 2,048 det x 30 s): x real time, table bank from a warm cache"


def add_arguments(p) -> None:
    p.add_argument("--detectors", type=int, default=2048, help="detectors (default 2048), in modules of --channels")
    p.add_argument("--channels", type=int, default=128, help="channels per module (default 128)")
    p.add_argument("--seconds", type=float, default=30.0, metavar="S", help="seconds of data (default 30)")
    p.add_argument("--sample-rate", type=float, default=152.587890625, metavar="HZ",
                   help="default 152.587890625 (DfMux)")
    p.add_argument("--chunk-s", type=float, default=0.1, metavar="S", help="chunk length (default 0.1 s)")
    p.add_argument("--repeat", type=int, default=3, metavar="N", help="warm runs (default 3; the median is the figure)")
    p.add_argument("--profile", type=int, default=0, metavar="N",
                   help="one more warm run under cProfile: its top N functions by own time (default 0: none)")
    p.add_argument("--batch-s", type=float, default=0.0, metavar="S",
                   help="also in process with convert_recording(batch_s=S) (default 0: message by message; "
                        "the default conversion batches 1 s; < 0: not measured)")
    p.add_argument("--startup", action="store_true",
                   help="also the command's start-up alone: the same command on one module for one chunk")
    p.add_argument("--keep", metavar="DIR", help="keep the recording, parameters, cache and outputs in DIR")


def _profile(fn, top: int) -> list[dict]:
    """cProfile's ``top`` functions by own time while ``fn()`` runs (and its total)."""
    import cProfile
    import pstats

    prof = cProfile.Profile()
    prof.enable()
    fn()
    prof.disable()
    st = pstats.Stats(prof)
    total = st.total_tt
    rows = sorted(st.stats.items(), key=lambda kv: kv[1][2], reverse=True)[:top]
    out = []
    for (path, line, func), (_cc, ncalls, tottime, cumtime, _callers) in rows:
        where = f"{Path(path).name}:{line}" if line else path
        out.append({"function": f"{func} ({where})", "calls": ncalls, "own_s": round(tottime, 3),
                    "own_fraction": round(tottime / total, 3) if total else None, "cumulative_s": round(cumtime, 3)})
    return out


def _kernel_time(conv, chunks, t_bath_k: float) -> float:
    """Seconds of ``conv.convert`` over every chunk, one call per chunk as the offline pipeline makes them.

    The environment is constant (the bath temperature, no field): the kernel's
    arithmetic does not depend on it, and the pipeline's alignment is not timed here.
    """
    import numpy as np

    from mntes_stream.core.convert import EnvironmentBlock
    from mntes_stream.core.ids import detector_id

    ids, envs = {}, {}
    total = 0.0
    for c in chunks:
        key = (c.board, c.module)
        if key not in ids:
            ids[key] = [detector_id(c.board, c.module, int(ch)) for ch in c.channels]
        n = c.counts_i.shape[1]
        if n not in envs:
            envs[n] = EnvironmentBlock(t_bath_k=np.full(n, t_bath_k), b_field_t=np.zeros(n))
        t0 = time.perf_counter()
        conv.convert(ids[key], c.counts_i, c.counts_q, envs[n])
        total += time.perf_counter() - t0
    return total


def run(args) -> dict:
    from mntes_stream.core.sim import SimConfig
    from mntes_stream.errors import ConfigError, MntesError
    from mntes_stream.io import keys
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import CountsChunk
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.pipeline.build import ConverterSpec, build_converter
    from mntes_stream.pipeline.offline import convert_recording
    from mntes_stream.service.simulator import SimulatorSource, write_mcap

    if args.detectors < 1 or args.channels < 1 or args.detectors % args.channels:
        raise ConfigError(f"--detectors {args.detectors} is not a whole number of modules of {args.channels} channels")
    if args.repeat < 1 or not args.seconds > 0:
        raise ConfigError("bench convert-offline takes --repeat >= 1 and --seconds > 0")
    work = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="mntes-bench-offline-"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        setup = "bench"
        cfg = SimConfig(boards=1, modules=args.detectors // args.channels, channels=args.channels,
                        sample_rate_hz=args.sample_rate)
        source = SimulatorSource(cfg, setup, args.chunk_s)
        rec, params_file = work / "recording.mcap", work / "params.toml"
        tiny = work / "startup.mcap"  # one module, one chunk: the command's start-up
        for stale in (rec, tiny, *work.glob("out*.mcap")):
            stale.unlink(missing_ok=True)
        shutil.rmtree(work / "home", ignore_errors=True)
        dump_params(source.params, params_file)
        written = write_mcap(source, rec, args.seconds)
        n_samples = written["samples"]
        if args.startup:
            write_mcap(SimulatorSource(dataclasses.replace(cfg, modules=1), setup, args.chunk_s), tiny, args.chunk_s)

        cache = work / "home" / ".cache" / "mntes-stream" / "tables"  # the CLI's default cache under HOME

        def convert(k: int, batch_s: float | None = None):
            t0, c0 = time.perf_counter(), time.process_time()
            stats = convert_recording(rec, work / f"out{k}.mcap", params=params_file, table_cache=cache,
                                      progress=False, **({} if batch_s is None else {"batch_s": batch_s}))
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            (work / f"out{k}.mcap").unlink()
            return wall, stats, cpu

        def command(k: int, recording=rec) -> tuple[float, float]:
            # The command as a user runs it, its own process: imports and compiled kernels loaded too.
            out = work / f"cli{k}.mcap"
            r0 = resource.getrusage(resource.RUSAGE_CHILDREN)
            t0 = time.perf_counter()
            res = subprocess.run([sys.executable, "-m", "mntes_stream", "convert", str(recording), str(out), "--params",
                                  str(params_file), "-q"], capture_output=True, text=True,
                                 env={**os.environ, "HOME": str(work / "home")})
            wall = time.perf_counter() - t0
            r1 = resource.getrusage(resource.RUSAGE_CHILDREN)
            if res.returncode != 0:
                raise MntesError(f"bench convert-offline: convert failed ({res.returncode}): "
                                 f"{res.stderr.strip().splitlines()[-1:]}")
            out.unlink()
            return wall, (r1.ru_utime + r1.ru_stime) - (r0.ru_utime + r0.ru_stime)

        load = [os.getloadavg()[0]]
        cli_cold_s, cli_cold_cpu = command(0)  # fills the cache
        cli_warm, cli_warm_cpu = zip(*(command(k + 1) for k in range(args.repeat)))
        # The same parameters: the converter from the same warm cache.
        startup, startup_cpu = zip(*(command(k + 1, tiny) for k in range(args.repeat))) if args.startup else ((), ())
        stats = convert(0)[1]  # in process: the kernels compiled or loaded once, as a long-lived process has them
        warm, _, warm_cpu = zip(*(convert(k + 1) for k in range(args.repeat)))
        batched = [convert(k + 1, args.batch_s) for k in range(args.repeat)] if args.batch_s >= 0 else []
        if batched and batched[0][1].samples_converted != stats.samples_converted:
            raise MntesError(f"bench convert-offline: batch_s={args.batch_s} converted "
                             f"{batched[0][1].samples_converted} samples, the default {stats.samples_converted}")
        # The parts alone, in the same minutes.
        t0 = time.perf_counter()
        conv = build_converter(ConverterSpec(params_file=str(params_file), table_cache=str(cache))).converter
        build_warm_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        counts_payloads = []
        n_read = 0
        for msg in Session(rec).iter_messages():
            n_read += 1
            if keys.kind_of(msg.topic) == "counts":
                counts_payloads.append(msg.payload)
        read_s = time.perf_counter() - t0
        t0 = time.perf_counter()
        chunks = [CountsChunk.from_bytes(p) for p in counts_payloads]
        decode_s = time.perf_counter() - t0
        kernel_s = _kernel_time(conv, chunks, source.params[0].t_bath_k)
        profile = _profile(lambda: convert(args.repeat + 1), args.profile) if args.profile else None
        load.append(os.getloadavg()[0])
    finally:
        if not args.keep:
            shutil.rmtree(work, ignore_errors=True)
    warm_s = statistics.median(warm)
    return {
        "detectors": args.detectors,
        "seconds": args.seconds,
        "sample_rate_hz": args.sample_rate,
        "chunk_s": args.chunk_s,
        "kind": stats.converter_kind,
        "samples": n_samples,
        "recording_mb": round(written["bytes"] / 1e6, 1),
        "recorded_messages": n_read,
        "power_chunks": stats.power_chunks,
        "samples_converted": stats.samples_converted,
        "ledger": stats.ledger_line,
        # `mntes-stream convert REC OUT --params P` in its own process: first with an empty cache (bank and
        # converter built and cached), then warm; in process (convert_recording, imports and kernels loaded).
        "command_cold_s": round(cli_cold_s, 3),
        "command_warm_s": [round(w, 3) for w in cli_warm],
        "realtime_factor_command_cold": round(args.seconds / cli_cold_s, 2),
        "realtime_factor_command": round(args.seconds / statistics.median(cli_warm), 2),
        "in_process_warm_s": [round(w, 3) for w in warm],
        "realtime_factor": round(args.seconds / warm_s, 2),
        # Per CPU second of the conversion's own process (user + system): what a machine shared with other
        # work gives on one core it has to itself; the wall figures above move with the load.
        "command_cold_cpu_s": round(cli_cold_cpu, 2),
        "command_warm_cpu_s": [round(c, 2) for c in cli_warm_cpu],
        "realtime_factor_command_per_cpu_s": round(args.seconds / statistics.median(cli_warm_cpu), 2),
        # The command's start-up alone: the same command on one module for one chunk (cache warm).
        "command_startup_s": [round(w, 3) for w in startup] or None,
        "command_startup_cpu_s": [round(c, 2) for c in startup_cpu] or None,
        "realtime_factor_command_without_startup_per_cpu_s": round(
            args.seconds / max(statistics.median(cli_warm_cpu) - statistics.median(startup_cpu), 1e-3), 2)
        if startup else None,
        "in_process_warm_cpu_s": [round(c, 2) for c in warm_cpu],
        "realtime_factor_per_cpu_s": round(args.seconds / statistics.median(warm_cpu), 2),
        # The same in process with convert_recording(batch_s=--batch-s): 0, message by message.
        "batch_s": args.batch_s if batched else None,
        "in_process_at_batch_s_cpu_s": [round(b[2], 2) for b in batched] or None,
        "realtime_factor_at_batch_s_per_cpu_s": round(args.seconds / statistics.median(b[2] for b in batched), 2)
        if batched else None,
        "realtime_factor_at_batch_s": round(args.seconds / statistics.median(b[0] for b in batched), 2) if batched else None,
        "target_realtime_factor": 20.0,
        "msamples_per_s": round(n_samples / warm_s / 1e6, 3),
        # The parts alone (same minutes): what of the warm run each would take if nothing else did.
        "parts_s": {"converter_from_warm_cache": round(build_warm_s, 3), "read_recording": round(read_s, 3),
                    "decode_counts": round(decode_s, 3), "kernel": round(kernel_s, 3)},
        "parts_fraction_of_warm": {k: round(v / warm_s, 3) for k, v in (
            ("converter_from_warm_cache", build_warm_s), ("read_recording", read_s), ("decode_counts", decode_s),
            ("kernel", kernel_s))},
        "profile_top_own_time": profile,
        "load_average_1min": [round(x, 2) for x in load],
    }
