"""``mntes-stream up``: source -> converter -> recorder on this machine, embedded defaults.

Each service runs in its own process (``service.supervise.Services``:
*spawn*, so no process forks with a zenoh session open, and the converter
and recorder get a core each), connected as zenoh peers over explicit
``tcp/127.0.0.1`` ports. It prints a line per second (power flowing, latency,
MCAP file growing) and stops after ``--duration`` seconds or on Ctrl-C /
SIGTERM, in order: source first, then the converter (which converts what it
holds), then the recorder (which finishes its file). Ctrl-C at any moment
ends with exit code 130 and the summary of what was written.

A service that dies meanwhile (killed, or failed) is started again on the
same ports and config, at most ``--restarts`` times a minute each (then up
stops, saying why, exit code 1); the converter continues its streams from
its checkpoint, so what was published while it was down is counted as never
received. The restarts are in the per-second line, before the summary and
in ``--json`` (``restarts``, ``deaths``); a run with restarts still exits 0.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from mntes_stream.cli._common import add_quiet, add_zenoh_args, arguments, setup_logging, zenoh_layer


def _pick_source(setup: str, up, zenoh):
    """The array simulator (unless ``--minimal``), else the minimal physics source.

    Returns
    -------
    (description, truth parameters, registry service name, its config)
    """
    n = max(1, round(up.chunk_s * up.sample_rate_hz))
    if not up.minimal:
        from mntes_stream.core.sim import SimConfig
        from mntes_stream.service.simulator import SimulatorServiceConfig, SimulatorSource

        cfg = SimConfig(boards=1, modules=up.modules, channels=up.channels, sample_rate_hz=up.sample_rate_hz)
        params = SimulatorSource(cfg, setup, up.chunk_s).params
        return "array simulator", params, "simulator", SimulatorServiceConfig(sim=cfg, setup=setup,
                                                                               chunk_s=up.chunk_s, zenoh=zenoh)
    from mntes_stream.service.source import MinimalSource, SourceConfig, SourceServiceConfig

    # Housekeeping once per chunk, read at the chunk boundaries: every chunk is
    # bracketed when it arrives, so nothing waits (see README: latency).
    cfg = SourceConfig(setup=setup, boards=1, modules=up.modules, channels=up.channels,
                       sample_rate_hz=up.sample_rate_hz, chunk_s=up.chunk_s, hk_interval_s=n / up.sample_rate_hz)
    return "minimal source", MinimalSource(cfg).params, "source", SourceServiceConfig(source=cfg, zenoh=zenoh)


def _metrics_ports(up) -> dict:
    """``--metrics-port``: each service serves its own endpoint on a free loopback port (merged by the parent)."""
    if up.metrics_port is None:
        return {}
    from mntes_stream.io.transport import free_tcp_port
    from mntes_stream.service.metrics import MetricsSettings, require_metrics

    require_metrics()  # one line naming the extra, before anything starts
    return {label: MetricsSettings(port=free_tcp_port()) for label in ("recorder", "converter", "source")}


def _metrics_of(metrics: dict, label: str) -> dict:
    return {"metrics": metrics[label]} if metrics else {}


def _serve_merged(up, metrics: dict, say):
    """The services' metrics on one endpoint, ``127.0.0.1:--metrics-port`` (0: any free port)."""
    from mntes_stream.service.metrics import MergedMetrics, MetricsSettings

    merged = MergedMetrics({label: f"http://{m.bind}:{m.port}/metrics" for label, m in metrics.items()})
    port = merged.serve(MetricsSettings(port=up.metrics_port))
    say(f"  Prometheus metrics of every service: http://127.0.0.1:{port}/metrics "
        f"(dashboard: services/grafana/mntes.json)")
    return merged


def _flagged(st) -> str:
    """``  flagged: saturated 1.6%, ...`` (share of converted samples), or nothing."""
    if not st.samples_converted:
        return ""
    parts = [f"{name} {100 * n / st.samples_converted:.1f}%" for name, n in st.flag_counts.items() if n]
    return f"  flagged: {', '.join(parts)}" if parts else ""


def _restarts(services) -> str:
    """``  restarts converter 1, source 2`` once any service was restarted, else nothing."""
    if not services.restarts:
        return ""
    return "  restarts " + ", ".join(f"{label} {n}" for label, n in services.restarts.items())


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


class _Files:
    """The MCAP files this run wrote (files already in the directory are not this run's)."""

    def __init__(self, directory: Path):
        self.directory = directory
        self._before = set(directory.glob("*.mcap"))

    def paths(self) -> list[Path]:
        return sorted(f for f in self.directory.glob("*.mcap") if f not in self._before)

    def now(self) -> tuple[int, int]:
        files = self.paths()
        return len(files), sum(f.stat().st_size for f in files)


def _recorded_ledger(files: _Files, processes: int) -> dict:
    """The recorder's ledger over every file of this run, recomputed from the messages: a killed recorder's
    file has no ledger metadata, and each recorder process books only what it saw (not the gap between them)."""
    import warnings

    from mntes_stream.io.mcap import Session
    from mntes_stream.io.mcap.ledger import recompute_ledger

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # an unfinished file is expected here: its recorder was killed
        session = Session(files.paths(), warn=False)
        whole = recompute_ledger(session)
    from mntes_stream.io.mcap.ledger import unpowered_line

    led, holes = whole.recorder, whole.unpowered or {}
    return {"messages": sum(f.messages for f in session.files), "ledger": led.as_dict(),
            "ledger_line": f"{led.line()} (over {processes} recorder processes, recomputed from the files)",
            "unpowered": holes, "ledger_note": f"; WARNING {unpowered_line(holes)}" if holes else ""}


def _restart_dead(services, budget, stopping, say) -> str | None:
    """Start again every service that died; why up gives up instead, or None."""
    from mntes_stream.service.supervise import exit_reason

    for label in services.dead():
        why = exit_reason(services.procs[label].exitcode)
        if not budget.take(label):
            return (f"{label} died ({why}) after {services.restarts[label]} restart(s), more than "
                    f"{budget.per_minute} within a minute (--restarts); giving up")
        say(f"  {label} died ({why}); restarting it (restart {services.restarts[label] + 1})", err=True)
        t0 = time.monotonic()
        services.restart(label, abort=stopping)
        say(f"  {label} restarted in {time.monotonic() - t0:.1f} s", err=True)
    return None


def monitor_command(setup: str, p_conv: int, p_src: int) -> str:
    """The exact command that attaches the monitor to this run: the same program the user ran (no venv to
    guess), both ports (power and status from the converter, housekeeping from the source: zenoh peers do
    not forward for each other), and the setup unless it is the default."""
    import shlex
    import shutil

    from mntes_stream.io.keys import DEFAULT_SETUP

    argv0 = Path(sys.argv[0])
    if argv0.name == "mntes-stream":  # the console script: bare when it is the one on PATH, else its path
        on_path = shutil.which("mntes-stream")
        exe = "mntes-stream" if on_path and Path(on_path).resolve() == argv0.resolve() else shlex.quote(str(argv0.resolve()))
    else:  # python -m mntes_stream, or main() called in-process
        exe = f"{shlex.quote(sys.executable)} -m mntes_stream"
    where = "" if setup == DEFAULT_SETUP else f" --setup {shlex.quote(setup)}"
    return f"{exe} monitor{where} -e tcp/127.0.0.1:{p_conv} -e tcp/127.0.0.1:{p_src}"


def run_up(args) -> int:
    import dataclasses

    from mntes_stream.cli._common import settings_from_args
    from mntes_stream.cli.up_config import UpSettings
    from mntes_stream.core.lag import who_is_behind
    from mntes_stream.core.ledger import Ledger, merge_restarts
    from mntes_stream.errors import MntesError
    from mntes_stream.io import keys
    from mntes_stream.io.messages import StatusMessage
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session
    from mntes_stream.service.base import stop_on_signals
    from mntes_stream.service.converter import ConverterConfig
    from mntes_stream.service.recorder import RecorderConfig
    from mntes_stream.service.supervise import RestartBudget, Services

    up = UpSettings(**settings_from_args(args, [f.name for f in dataclasses.fields(UpSettings)]))
    setup_logging(args.verbose)
    stdout = sys.stderr if args.json else sys.stdout  # --json: stdout is the JSON document alone

    def say(message: str, err: bool = False) -> None:
        print(message, file=sys.stderr if err else stdout, flush=True)

    flags = zenoh_layer(args)
    if flags.listen is not None:
        from mntes_stream.errors import ConfigError

        raise ConfigError("up chooses its own listen ports on 127.0.0.1; use serve for fixed endpoints")
    # A restarted service's peers re-dial it within a second (zenoh's default backoff grows to 4 s);
    # a zenoh file, if given, says how instead.
    redial = () if flags.file else ("connect/retry:{period_init_ms: 250, period_max_ms: 1000, period_increase_factor: 2}",)
    layered = lambda z: flags.over(dataclasses.replace(z, cfg=z.cfg + redial))  # noqa: E731
    setup = up.setup
    out = Path(up.out).resolve()
    rec_dir = out / "recordings"
    rec_dir.mkdir(parents=True, exist_ok=True)
    files = _Files(rec_dir)
    p_rec, p_conv, p_src = free_tcp_port(), free_tcp_port(), free_tcp_port()
    what, truth, src_service, src_cfg = _pick_source(setup, up, layered(loopback(p_src, [p_conv, p_rec])))
    metrics = _metrics_ports(up)  # {label: MetricsSettings} of each service, or {} without --metrics-port
    if metrics:
        src_cfg = dataclasses.replace(src_cfg, metrics=metrics["source"])
    params_file = out / "params.toml"
    # The truth is the converter's calibration here: what it converts should match what was simulated.
    dump_params(truth, params_file, metadata={"source": f"mntes-stream up ({what}, truth)"})
    rec_cfg = RecorderConfig(setup=setup, directory=str(rec_dir), flush_interval_s=1.0, rotate_s=0,
                             log_interval_s=3600, zenoh=layered(loopback(p_rec)), **_metrics_of(metrics, "recorder"))
    conv_cfg = ConverterConfig(setup=setup, params=str(params_file), zenoh=layered(loopback(p_conv, [p_rec])),
                               **settings_from_args(args, ("kind",)), **_metrics_of(metrics, "converter"))
    # A restarted converter continues from this run's checkpoint (an older run's would be a different stream).
    checkpoint = out / "converter-checkpoint.json"
    checkpoint.unlink(missing_ok=True)
    conv_cfg = dataclasses.replace(conv_cfg, status=dataclasses.replace(conv_cfg.status, interval_s=1.0),
                                   checkpoint=str(checkpoint))
    budget = RestartBudget(up.restarts)
    dead_ledgers, last_ledger = [], {}  # converters that died: their ledgers, as their last status said

    services = Services()
    t_start = time.monotonic()
    # A first start compiles kernels and builds tables (tens of seconds): say so, not nothing.
    if not args.quiet:  # -q: no start lines (docs/cli.md)
        services.on_progress = lambda label, text: say(f"  {label}: {text}")
    say(f"mntes-stream up: {what}, {len(truth)} detectors ({up.modules} modules x {up.channels} channels) "
        f"at {up.sample_rate_hz} Hz -> {conv_cfg.kind} conversion -> MCAP in {rec_dir}")
    say(f"  zenoh peers on 127.0.0.1: recorder :{p_rec}, converter :{p_conv}, source :{p_src}; "
        f"{'until Ctrl-C' if not up.duration_s else f'for {up.duration_s:g} s (Ctrl-C stops earlier)'}")
    say(f"  monitor, from a second terminal: {monitor_command(setup, p_conv, p_src)}")
    status_key = keys.status_key(setup, conv_cfg.name)
    failed = interrupted = False
    merged = None
    with stop_on_signals() as stopping:
        try:
            services.start("recorder", "recorder", rec_cfg, abort=stopping)
            services.start("converter", "converter", conv_cfg, abort=stopping)
            services.start("source", src_service, src_cfg, abort=stopping)
            if not args.quiet:
                say(f"  recorder, converter and source ready after {time.monotonic() - t_start:.1f} s; the source "
                    "publishes once its subscribers are connected")
            first_power = not args.quiet
            if metrics:
                merged = _serve_merged(up, metrics, say)
            with open_session(layered(loopback(None, [p_rec, p_conv, p_src]))) as session:
                sub = QueueSubscriber(session, [status_key])
                t_end = time.monotonic() + up.duration_s if up.duration_s else float("inf")
                while not stopping.is_set() and time.monotonic() < t_end:
                    if "converter" in services.dead():
                        # Its last status holds its ledger: what it did before it died (the statuses
                        # still queued are its own; the new one continues from its checkpoint).
                        while (item := sub.get()) is not None:
                            last_ledger = StatusMessage.from_bytes(item[1]).ledger
                        # Merged with its successors' at the end (core.ledger.merge_restarts: each chunk once).
                        dead_ledgers.append(Ledger.from_dict(last_ledger))
                        last_ledger = {}
                    give_up = _restart_dead(services, budget, stopping, say)
                    if give_up:
                        failed = True
                        say(give_up, err=True)
                        break
                    item = sub.get(timeout_s=0.2)
                    if item is None:
                        continue
                    st = StatusMessage.from_bytes(item[1])
                    last_ledger = st.ledger
                    if first_power and st.chunks_converted:
                        first_power = False
                        say(f"  first power {time.monotonic() - t_start:.1f} s after the start")
                    if args.quiet:
                        continue
                    n_files, size = files.now()
                    p50 = "-" if st.latency_p50_ms is None else f"{st.latency_p50_ms:.1f}"
                    p99 = "-" if st.latency_p99_ms is None else f"{st.latency_p99_ms:.1f}"
                    arr = "-" if st.arrival_p99_ms is None else f"{st.arrival_p99_ms:.1f}"
                    behind = who_is_behind(st.latency_p99_ms, st.arrival_p99_ms)
                    say(f"  t={st.uptime_s:6.1f} s  power chunks {st.chunks_converted:7d}  "
                        f"{st.rate_msamples_per_s * 1e3:7.1f} ksamples/s  latency p50/p99 {p50}/{p99} ms "
                        f"(arrival p99 {arr})  lost {st.chunks_lost}  bad {sum(st.bad_messages.values())}  "
                        f"MCAP {n_files} file(s) {size / 1e6:.2f} MB{_flagged(st)}{_restarts(services)}"
                        f"{f'  BEHIND: {behind}' if behind else ''}")
                interrupted = stopping.is_set()
                # Ordered stop: no new data; the converter takes in and converts what is on its
                # way (its status says when), converts what it still holds and says so in a
                # final status; once that status is here, its last power chunks have reached the
                # recorder, which then finishes its file.
                failed |= not services.stop("source")
                if not failed and not _converter_idle(sub, 10.0):
                    say("the converter did not settle within 10 s; stopping it anyway", err=True)
                while sub.get() is not None:  # statuses from before the stop
                    pass
                failed |= not services.stop("converter")
                sub.get(timeout_s=2.0)
                sub.close()
        except MntesError as exc:
            interrupted = stopping.is_set()
            if not interrupted:
                say(f"mntes-stream: error: {exc}", err=True)
                failed = True
        finally:
            # Also after an error or Ctrl-C: source, converter, recorder (stopping a stopped one is a no-op).
            failed |= not services.stop("source")
            failed |= not services.stop("converter")
            failed |= not services.stop("recorder")
            if merged is not None:
                merged.close()
    if services.restarts:
        say("restarted " + "; ".join(f"{label} {services.restarts[label]} time(s) ({', '.join(why)})"
                                     for label, why in services.deaths.items()))
    summary, ok = services.collect()
    if services.restarts["recorder"] and isinstance(summary.get("recorder"), dict):
        summary["recorder"] = {**summary["recorder"], **_recorded_ledger(files, services.restarts["recorder"] + 1)}
    if dead_ledgers and isinstance(summary.get("converter"), dict):  # the ledger of every converter process
        whole = merge_restarts([*dead_ledgers, Ledger.from_dict(summary["converter"].get("ledger") or {})])
        again = whole.totals().again
        both = f"; {again} chunk(s) converted again after a restart, counted once" if again else ""
        summary["converter"] = {**summary["converter"], "ledger": whole.as_dict(), "ledger_line":
                                f"{whole.line()} (over {services.restarts['converter'] + 1} converter processes"
                                f"{both})"}
    failed |= not ok and not interrupted
    n_files, size = files.now()
    conv = summary.get("converter", {}) if isinstance(summary.get("converter"), dict) else {}
    rec = summary.get("recorder", {}) if isinstance(summary.get("recorder"), dict) else {}
    # A recorder that failed (a full disk) left no statistics: say so, not "recorded 0 messages".
    recorded = (f"recorded {rec.get('messages', 0)} messages" if rec else
                f"the recorder failed ({str(summary.get('recorder') or 'no statistics')[:300]}; `mntes-stream "
                "inspect` tells what its files hold)")
    say(f"done{' (interrupted)' if interrupted else ''}: {conv.get('samples_converted', 0) / 1e6:.2f} Msamples "
        f"converted; {recorded} into {n_files} MCAP file(s), {size / 1e6:.2f} MB: "
        f"{', '.join(rec.get('files', [])) or ', '.join(str(f) for f in files.paths()) or '-'}")
    if rec.get("ledger_line"):
        say(f"  recorder counts: {rec['ledger_line']}{rec.get('ledger_note') or ''}")
    # The last line is the converter's ledger: what happened to every chunk (lost = never received + shed + rejected).
    say(f"  converter: {conv.get('ledger_line') or 'no final statistics (it did not stop cleanly): see its log'}"
        f"{conv.get('ledger_note') or ''}")
    if args.json:
        print(json.dumps({"interrupted": interrupted, "ok": not failed, "params": str(params_file),
                          "services": summary, "restarts": dict(services.restarts), "deaths": services.deaths},
                         indent=2, default=str))
    if interrupted:
        return 130
    return 1 if failed else 0


def _up_args(p) -> None:
    import dataclasses

    from mntes_stream.cli._common import add_settings_args
    from mntes_stream.cli.up_config import UP_FLAGS, UpSettings
    from mntes_stream.service.converter import ConverterConfig  # its kind setting (imports numba: `up` needs it)

    names, (aliases, spelled) = tuple(f.name for f in dataclasses.fields(UpSettings)), UP_FLAGS
    metavars = {"out": "DIR", "sample_rate_hz": "HZ", "metrics_port": "PORT", "restarts": "N"}
    add_settings_args(p, UpSettings, names[:7], aliases, spelled=spelled, metavars=metavars)
    add_settings_args(p, ConverterConfig, ("kind",))
    add_settings_args(p, UpSettings, names[7:], aliases, spelled=spelled, metavars=metavars)
    p.add_argument("--json", action="store_true", help="print one JSON document (the services' final statistics) "
                                                       "on stdout; progress goes to stderr")
    add_quiet(p)
    p.add_argument("-v", "--verbose", action="store_true", help="log from every service")
    add_zenoh_args(p)
    p.set_defaults(func=run_up)


def register(sub) -> None:
    p = sub.add_parser("up", help="source + converter + recorder on this machine, embedded defaults",
                       description="Run a simulated array through the converter into an MCAP recording, printing a "
                                   "status line per second. Stops after --duration or on Ctrl-C (exit code 130).")
    arguments(p, _up_args)
