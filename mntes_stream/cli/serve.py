"""``mntes-stream serve --config FILE`` (one service) and ``mntes-stream up`` (all of them, one machine).

``serve`` picks the service from the config's table: ``[converter]``,
``[source]`` (minimal source), ``[simulator]`` (array simulator),
``[recorder]`` or ``[replay]`` (see ``services/``).

``up`` runs source -> converter -> recorder on embedded defaults, each in its
own process (``multiprocessing`` *spawn*: no process ever forks with a zenoh
session open, and the converter and recorder get a core each), connected as
zenoh peers over explicit ``tcp/127.0.0.1`` ports. It prints a line per
second (power flowing, latency, MCAP file growing) and stops after
``--duration`` seconds or on Ctrl-C / SIGTERM, in order: source first, then
the converter (which converts what it holds), then the recorder (which
finishes its file).
"""

from __future__ import annotations

import json
import logging
import sys
import time
import tomllib
from pathlib import Path

SERVICES = ("converter", "source", "simulator", "recorder", "replay")


def _logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING,
                        format="%(asctime)s %(processName)s %(name)s: %(message)s")


def _load(path: str) -> tuple[str, dict]:
    from mntes_stream.errors import ConfigError

    try:
        doc = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise ConfigError(f"{path}: {exc}") from None
    kinds = [k for k in SERVICES if k in doc]
    if len(kinds) != 1:
        raise ConfigError(f"{path}: needs exactly one of the tables {['[' + k + ']' for k in SERVICES]}, found {kinds}")
    return kinds[0], doc


def run_serve(args) -> int:
    from mntes_stream.errors import ConfigError

    _logging(not args.quiet)
    kind, doc = _load(args.config)
    base = Path(args.config).resolve().parent
    if args.duration is not None:
        if kind == "replay":
            raise ConfigError("--duration does not apply to replay (use its time range)")
        doc.setdefault(kind, {})["duration_s"] = args.duration
    if kind == "converter":
        from mntes_stream.service.converter import ConverterConfig, run_converter

        result = run_converter(ConverterConfig.from_dict(doc, args.config, base_dir=base))
    elif kind == "source":
        from mntes_stream.service.source import SourceService, run_source

        result = run_source(SourceService.from_dict(doc, args.config, base_dir=base))
    elif kind == "simulator":
        from mntes_stream.service.simulator import SimulatorService, run_simulator

        result = run_simulator(SimulatorService.from_dict(doc, args.config, base_dir=base))
    elif kind == "recorder":
        from dataclasses import asdict

        from mntes_stream.service.recorder import RecorderConfig, run_recorder

        result = asdict(run_recorder(RecorderConfig.from_dict(doc, args.config, base_dir=str(base))))
    else:
        from dataclasses import asdict

        from mntes_stream.service.replay import ReplayConfig, run_replay

        result = asdict(run_replay(ReplayConfig.from_toml(args.config)))
    if args.json:
        print(json.dumps(result, indent=2, default=str))
    return 0


# ------------------------------------------------------------------------------ up


def _up_simulator(svc, stop, ready) -> dict:
    """The array simulator in the ``function(cfg, stop, ready)`` form of a service process."""
    from mntes_stream.service.simulator import run_simulator

    ready.set()  # run_simulator waits for the converter's subscription before its clock starts
    return run_simulator(svc, stop)


def _pick_source(setup: str, args, zenoh):
    """The array simulator when installed (unless ``--minimal``), else the minimal physics source.

    Returns
    -------
    (description, truth parameters, process target, its config)
    """
    n = max(1, round(args.chunk_s * args.sample_rate))
    if not args.minimal:
        try:
            from mntes_stream.core.sim import SimConfig
            from mntes_stream.service.simulator import SimulatorService, SimulatorSource
        except ImportError:
            pass
        else:
            cfg = SimConfig(boards=1, modules=args.modules, channels=args.channels, sample_rate_hz=args.sample_rate)
            params = SimulatorSource(cfg, setup, args.chunk_s).params
            svc = SimulatorService(cfg, zenoh, setup=setup, chunk_s=args.chunk_s)
            return "array simulator", params, "mntes_stream.cli.serve:_up_simulator", svc
    from mntes_stream.service.source import MinimalSource, SourceConfig, SourceService

    # Housekeeping once per chunk, read at the chunk boundaries: every chunk is
    # bracketed when it arrives, so nothing waits (see README: latency).
    cfg = SourceConfig(setup=setup, boards=1, modules=args.modules, channels=args.channels,
                       sample_rate_hz=args.sample_rate, chunk_s=args.chunk_s, hk_interval_s=n / args.sample_rate)
    return ("minimal source", MinimalSource(cfg).params, "mntes_stream.service.source:run_source",
            SourceService(source=cfg, zenoh=zenoh))


def _flagged(st) -> str:
    """``  flagged: saturated 1.6%, ...`` (share of converted samples), or nothing."""
    if not st.samples_converted:
        return ""
    parts = [f"{name} {100 * n / st.samples_converted:.1f}%" for name, n in st.flag_counts.items() if n]
    return f"  flagged: {', '.join(parts)}" if parts else ""


def _converter_idle(sub, timeout_s: float) -> bool:
    """Wait for two converter statuses in a row with nothing new received and nothing pending."""
    from mntes_stream.io.messages import StatusMessage

    deadline = time.monotonic() + timeout_s
    last = None
    while time.monotonic() < deadline:
        item = sub.get(timeout_s=0.2)
        if item is None:
            continue
        st = StatusMessage.from_bytes(item[1])
        if st.chunks_pending == 0 and st.chunks_received == last:
            return True
        last = st.chunks_received
    return False


def _mcap_bytes(directory: Path) -> tuple[int, int]:
    files = sorted(directory.glob("*.mcap"))
    return len(files), sum(f.stat().st_size for f in files)


def run_up(args) -> int:
    from mntes_stream.io import keys
    from mntes_stream.io.messages import StatusMessage
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session
    from mntes_stream.service import Services, stop_on_signals
    from mntes_stream.service.converter import ConverterConfig
    from mntes_stream.service.pipeline import PipelineConfig

    _logging(args.verbose)
    setup = args.setup
    out = Path(args.out).resolve()
    rec_dir = out / "recordings"
    rec_dir.mkdir(parents=True, exist_ok=True)
    p_rec, p_conv, p_src = free_tcp_port(), free_tcp_port(), free_tcp_port()
    what, truth, src_target, src_svc = _pick_source(setup, args, loopback(p_src, [p_conv, p_rec]))
    params_file = out / "params.toml"
    # The truth is the converter's calibration here: what it converts should match what was simulated.
    dump_params(truth, params_file, metadata={"source": f"mntes-stream up ({what}, truth)"})
    recorder_doc = {
        "recorder": {"setup": setup, "directory": str(rec_dir), "flush_interval_s": 1.0, "rotate_s": 0, "log_interval_s": 3600},
        "zenoh": {"mode": "peer", "listen": [f"tcp/127.0.0.1:{p_rec}"]},
    }
    conv_cfg = ConverterConfig(params=str(params_file), kind=args.kind,
                               pipeline=PipelineConfig(setup=setup, status_interval_s=1.0),
                               zenoh=loopback(p_conv, [p_rec]))

    services = Services()
    print(f"mntes-stream up: {what}, {len(truth)} detectors ({args.modules} modules x {args.channels} channels) "
          f"at {args.sample_rate} Hz -> {args.kind} conversion -> MCAP in {rec_dir}")
    print(f"  zenoh peers on 127.0.0.1: recorder :{p_rec}, converter :{p_conv}, source :{p_src}; "
          f"{'until Ctrl-C' if not args.duration else f'for {args.duration:g} s (Ctrl-C stops earlier)'}")
    status_key = keys.status_key(setup, conv_cfg.pipeline.service)
    failed = False
    with stop_on_signals() as stopping:
        try:
            services.start("recorder", "mntes_stream.service:run_recorder_doc", recorder_doc, abort=stopping)
            services.start("converter", "mntes_stream.service.converter:run_converter", conv_cfg, abort=stopping)
            services.start("source", src_target, src_svc, abort=stopping)
            with open_session(loopback(None, [p_rec, p_conv, p_src])) as session:
                sub = QueueSubscriber(session, [status_key])
                t_end = time.monotonic() + args.duration if args.duration else float("inf")
                while not stopping.is_set() and time.monotonic() < t_end:
                    if not services.alive():
                        failed = True
                        print("a service stopped unexpectedly; shutting down", file=sys.stderr)
                        break
                    item = sub.get(timeout_s=0.2)
                    if item is None or args.quiet:
                        continue
                    st = StatusMessage.from_bytes(item[1])
                    n_files, size = _mcap_bytes(rec_dir)
                    p50 = "-" if st.latency_p50_ms is None else f"{st.latency_p50_ms:.1f}"
                    p99 = "-" if st.latency_p99_ms is None else f"{st.latency_p99_ms:.1f}"
                    print(f"  t={st.uptime_s:6.1f} s  power chunks {st.chunks_converted:7d}  "
                          f"{st.rate_msamples_per_s * 1e3:7.1f} ksamples/s  latency p50/p99 {p50}/{p99} ms  "
                          f"lost {st.chunks_lost}  bad {sum(st.bad_messages.values())}  "
                          f"MCAP {n_files} file(s) {size / 1e6:.2f} MB{_flagged(st)}", flush=True)
                # Ordered stop: no new data; the converter takes in and converts what is on its
                # way (its status says when), converts what it still holds and says so in a
                # final status; once that status is here, its last power chunks have reached the
                # recorder, which then finishes its file.
                failed |= not services.stop("source")
                if not failed and not _converter_idle(sub, 10.0):
                    print("the converter did not settle within 10 s; stopping it anyway", file=sys.stderr)
                while sub.get() is not None:  # statuses from before the stop
                    pass
                failed |= not services.stop("converter")
                sub.get(timeout_s=2.0)
                sub.close()
        finally:
            # Also after an error: source, converter, recorder (stopping a stopped one is a no-op).
            failed |= not services.stop("source")
            failed |= not services.stop("converter")
            failed |= not services.stop("recorder")
    summary, ok = services.collect()
    failed |= not ok
    n_files, size = _mcap_bytes(rec_dir)
    conv = summary.get("converter", {})
    rec = summary.get("recorder", {})
    print(f"done: {conv.get('chunks_converted', 0)} power chunks ({conv.get('samples_converted', 0) / 1e6:.2f} Msamples), "
          f"lost {conv.get('chunks_lost', '?')}, recorded {rec.get('messages', 0)} messages into {n_files} MCAP file(s), "
          f"{size / 1e6:.2f} MB: {', '.join(rec.get('files', [])) or '-'}")
    if args.json:
        print(json.dumps(summary, indent=2, default=str))
    return 1 if failed else 0


def register(sub) -> None:
    p = sub.add_parser("serve", help="run one service from its config file (services/*.toml)",
                       description="Run the service a config describes: [converter], [source], [simulator], [recorder] or [replay]. "
                                   "Stops cleanly on SIGINT/SIGTERM.")
    p.add_argument("--config", required=True, metavar="FILE", help="e.g. services/converter.toml")
    p.add_argument("--duration", type=float, metavar="S", help="stop after S seconds (overrides duration_s)")
    p.add_argument("--json", action="store_true", help="print the final statistics as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="warnings only")
    p.set_defaults(func=run_serve)

    p = sub.add_parser("up", help="source + converter + recorder on this machine, embedded defaults",
                       description="Run a simulated array through the converter into an MCAP recording, printing a "
                                   "status line per second. Stops after --duration or on Ctrl-C.")
    p.add_argument("--duration", type=float, default=60.0, metavar="S", help="seconds to run (0: until Ctrl-C; default 60)")
    p.add_argument("--out", default="mntes-up", metavar="DIR", help="parameters and recordings go here (default ./mntes-up)")
    from mntes_stream.io.keys import DEFAULT_SETUP

    p.add_argument("--setup", default=DEFAULT_SETUP, help=f"setup name in the keys (default {DEFAULT_SETUP})")
    p.add_argument("--modules", type=int, default=4, help="readout modules (default 4)")
    p.add_argument("--channels", type=int, default=64, help="channels per module (default 64)")
    p.add_argument("--sample-rate", type=float, default=152.59, metavar="HZ", help="default 152.59 (DfMux ground rate)")
    p.add_argument("--chunk-s", type=float, default=0.1, help="counts chunk length (s)")
    p.add_argument("--kind", default="table", help="conversion kind (table, grid, exact, linear, electrical)")
    p.add_argument("--minimal", action="store_true", help="the minimal physics source instead of the array simulator")
    p.add_argument("--json", action="store_true", help="print the services' final statistics as JSON")
    p.add_argument("-q", "--quiet", action="store_true", help="no per-second lines")
    p.add_argument("-v", "--verbose", action="store_true", help="log from every service")
    p.set_defaults(func=run_up)
