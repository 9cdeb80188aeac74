"""Chaos: router, source, converter and recorder as processes; stalls, kills and a CPU hog; then the ledger.

Every service is a ``mntes-stream serve`` process, a zenoh client of a
``mntes-stream router`` on 127.0.0.1. While the minimal source publishes in
real time, a schedule (seeded) stalls (SIGSTOP, then SIGCONT) and kills
(SIGKILL, then a restart) the source, converter, recorder and router, and runs
a CPU hog on every core. Afterwards, from the services' own final statistics
and from the recording:

- the last converter's ledger balances for every stream (received = converted
  live + late + shed + rejected + duplicate), and its ``lost`` is what it says;
- the recording's counts are complete except while the source itself was down
  (a sequence gap inside one run of the source is a recording gap);
- offline ``convert`` of the recording gives power for every recorded counts
  chunk (never shed, nothing rejected);
- no summary hides a chunk: the counts chunks recorded without any recorded
  power are at most what the converters' ledgers (and the chunks published
  while no converter ran) account for.
"""

from __future__ import annotations

import json
import os
import random
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

HELP = "router + source + converter + recorder under SIGSTOP/SIGKILL/CPU hog: the ledger and the recording afterwards"

# (event name, target): what the schedule may do; "stop" stalls for a few seconds, "kill" restarts the process.
EVENTS = ("stop:source", "hog", "stop:converter", "kill:converter", "stop:recorder", "kill:recorder",
          "stop:router", "kill:router", "kill:source")


def add_arguments(p) -> None:
    p.add_argument("--duration", type=float, default=80.0, metavar="S", help="seconds of chaos (default 80; the "
                   "events are at least 7 s apart, so every event fits in about 70 s)")
    p.add_argument("--seed", type=int, default=0, help="schedule seed (default 0)")
    p.add_argument("--modules", type=int, default=4, help="readout modules (default 4)")
    p.add_argument("--channels", type=int, default=32, help="channels per module (default 32)")
    p.add_argument("--events", default=",".join(EVENTS), help=f"comma-separated events (default {','.join(EVENTS)})")
    p.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (recordings, logs)")


def run(args) -> dict:
    events = tuple(e for e in args.events.split(",") if e)
    unknown = sorted(set(events) - set(EVENTS))
    if unknown:
        from mntes_stream.errors import ConfigError

        raise ConfigError(f"unknown chaos event(s) {unknown}; choose from {', '.join(EVENTS)}")
    if args.keep:
        work = Path(args.keep)
        work.mkdir(parents=True, exist_ok=True)
        return run_chaos(work, args.duration, args.seed, args.modules, args.channels, events)
    with tempfile.TemporaryDirectory(prefix="mntes-chaos-") as tmp:
        return run_chaos(Path(tmp), args.duration, args.seed, args.modules, args.channels, events)


class ServiceProcess:
    """One ``mntes-stream`` process, restartable; its output goes to a log file per run.

    ``prefix`` runs it through a command (``ip netns exec NAME``: it execs the process, so the pid is the
    process's own).
    """

    def __init__(self, name: str, argv: list[str], work: Path, prefix: tuple[str, ...] = ()):
        self.name, self.argv, self.work, self.prefix = name, argv, work, tuple(prefix)
        self.runs: list[subprocess.Popen] = []
        self.logs: list[Path] = []
        self.start()

    def start(self) -> None:
        log = self.work / f"{self.name}-{len(self.runs)}.log"
        out = self.work / f"{self.name}-{len(self.runs)}.json"
        with open(log, "w") as err, open(out, "w") as stdout:
            self.runs.append(subprocess.Popen([*self.prefix, sys.executable, "-m", "mntes_stream", *self.argv],
                                              cwd=self.work, stdout=stdout, stderr=err, start_new_session=True))
        self.logs.append(log)

    @property
    def p(self) -> subprocess.Popen:
        return self.runs[-1]

    def signal(self, sig) -> None:
        if self.p.poll() is None:
            os.kill(self.p.pid, sig)

    def wait_log(self, text: str, timeout_s: float = 120.0) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if text in self.logs[-1].read_text(errors="replace"):
                return
            if self.p.poll() is not None:
                break
            time.sleep(0.1)
        from mntes_stream.errors import TransportError

        raise TransportError(f"chaos: {self.name} did not say {text!r}: {self.logs[-1].read_text()[-1500:]}")

    def stop(self, timeout_s: float = 60.0) -> int:
        self.signal(signal.SIGCONT)
        self.signal(signal.SIGINT)
        try:
            return self.p.wait(timeout_s)
        except subprocess.TimeoutExpired:
            self.p.kill()
            return self.p.wait()

    def results(self) -> list[dict]:
        """The JSON final statistics of every run that printed them (a killed run prints none)."""
        out = []
        for k in range(len(self.runs)):
            text = (self.work / f"{self.name}-{k}.json").read_text()
            try:
                out.append(json.loads(text))
            except ValueError:
                out.append(None)
        return out


def cpu_hog(seconds: float) -> list[subprocess.Popen]:
    """A busy loop on every core for ``seconds`` (separate processes: the GIL must not hide the load)."""
    code = f"import time\nt=time.monotonic()+{seconds}\nwhile time.monotonic()<t: pass"
    return [subprocess.Popen([sys.executable, "-c", code]) for _ in range(os.cpu_count() or 2)]


# Seconds between one event's start and the next: a stall lasts 3-4 s, a restart 1-3 s, and zenoh's history and
# recovery need the peers alive for a moment after (a source killed just after a gap, before anyone asked its cache
# for it, takes the gap with it: that is the source's own downtime).
SPACING_S = 7.0


def _schedule(events, duration_s: float, seed: int) -> list[tuple[float, str]]:
    """Each event at a seeded moment in [0.1, 0.8] of the run, in order of time, at least SPACING_S apart."""
    rng = random.Random(seed)
    slots = sorted(rng.uniform(0.1, 0.8) * duration_s for _ in events)
    out, t_prev = [], 0.0
    for t, e in zip(slots, rng.sample(list(events), len(events))):
        t = max(t, t_prev + SPACING_S)
        out.append((t, e))
        t_prev = t
    return out


def service_configs(work: Path, port: int, modules: int, channels: int, host: str = "127.0.0.1", setup: str = "chaos",
                    history_s: float | None = None, checkpoint: bool = True) -> dict[str, Path]:
    """The truth parameters and the router's, converter's, recorder's and source's configs, written in ``work``.

    Every service is a client of the router on ``host:port``; ``history_s`` (None: the default) is the
    sources' ``[zenoh] history_s``; ``checkpoint``: the converter keeps one.
    """
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.service.source import MinimalSource, SourceConfig

    src = SourceConfig(setup=setup, modules=modules, channels=channels, hk_interval_s=0.1)
    dump_params(MinimalSource(src).params, work / "params.toml", metadata={"source": f"bench {setup} (truth)"})
    zen = f'[zenoh]\nmode = "client"\nconnect = ["tcp/{host}:{port}"]\n'
    if history_s is not None:
        zen += f"history_s = {history_s}\n"
    files = {
        "router": f'[router]\nsetup = "{setup}"\n[zenoh]\nlisten = ["tcp/{host}:{port}"]\n',
        "converter": (f'[converter]\nsetup = "{setup}"\nparams = "params.toml"\nkind = "table"\n'
                      f'table_cache = "{work / "cache"}"\n' + ('checkpoint = "checkpoint.json"\n' if checkpoint else "")
                      + zen),
        "recorder": f'[recorder]\nsetup = "{setup}"\ndirectory = "recordings"\nflush_interval_s = 0.5\n' + zen,
        "source": (f'[source]\nsetup = "{setup}"\nparams = "params.toml"\nmodules = {modules}\nchannels = {channels}\n'
                   'hk_interval_s = 0.1\nlinger_s = 2.0\n' + zen),
    }
    out = {}
    for name, text in files.items():
        out[name] = work / f"{name}.toml"
        out[name].write_text(text)
    return out


def run_chaos(work: Path, duration_s: float = 80.0, seed: int = 0, modules: int = 4, channels: int = 32,
              events=EVENTS, say=None) -> dict:
    """Run the chaos schedule in ``work``; returns the figures and the checks (see the module docstring)."""
    from mntes_stream.io.transport import free_tcp_port

    say = say or (lambda m: print(m, file=sys.stderr, flush=True))
    port = free_tcp_port()
    cfg = service_configs(work, port, modules, channels)
    procs: dict[str, ServiceProcess] = {}
    hogs: list[subprocess.Popen] = []
    log: list[dict] = []
    down: dict[str, list[list[float]]] = {"source": [], "recorder": [], "converter": [], "router": []}
    try:
        procs["router"] = ServiceProcess("router", ["router", "--config", str(cfg["router"])], work)
        procs["router"].wait_log("zenoh id")
        procs["converter"] = ServiceProcess("converter", ["serve", "--config", str(cfg["converter"]), "--json"], work)
        procs["converter"].wait_log("detectors, kind", 600)  # a cold table build
        procs["recorder"] = ServiceProcess("recorder", ["serve", "--config", str(cfg["recorder"]), "--json"], work)
        procs["recorder"].wait_log("recording mntes/chaos/")
        procs["source"] = ServiceProcess("source", ["serve", "--config", str(cfg["source"]), "--json"], work)
        t0 = time.monotonic()
        plan = _schedule(events, duration_s, seed)
        say(f"chaos: {len(plan)} events over {duration_s:g} s: " + ", ".join(f"{e}@{t:.0f}s" for t, e in plan))
        for t_event, event in plan:
            time.sleep(max(0.0, t0 + t_event - time.monotonic()))
            now = time.monotonic() - t0
            action, _, target = event.partition(":")
            if action == "hog":
                hogs += cpu_hog(8.0)
                log.append({"t_s": round(now, 2), "event": "hog", "seconds": 8.0})
            elif action == "stop":
                pause = 4.0 if target == "source" else 3.0
                procs[target].signal(signal.SIGSTOP)
                time.sleep(pause)
                procs[target].signal(signal.SIGCONT)
                down[target].append([now, now + pause])
                log.append({"t_s": round(now, 2), "event": event, "seconds": pause})
            elif action == "kill":
                procs[target].signal(signal.SIGKILL)
                procs[target].p.wait(30)
                time.sleep(1.0)
                procs[target].start()
                down[target].append([now, time.monotonic() - t0])
                log.append({"t_s": round(now, 2), "event": event})
            say(f"chaos: t={now:5.1f} s {event}")
        time.sleep(max(0.0, t0 + duration_s - time.monotonic()))
    finally:
        for h in hogs:
            h.kill()
        # Orderly end: no new data, the converter converts what it holds and says so, the recorder finishes.
        rcs = {}
        for name in ("source", "converter", "recorder", "router"):
            if name in procs:
                if name == "converter":
                    time.sleep(3.0)
                rcs[name] = procs[name].stop()
                if name == "converter":
                    time.sleep(2.0)
    return _analyse(work, procs, rcs, log, down, duration_s)


def _analyse(work: Path, procs: dict, rcs: dict, log: list, down: dict, duration_s: float) -> dict:
    from mntes_stream.core.ledger import Ledger, merge_restarts
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import CountsChunk, PowerChunk, StatusMessage
    from mntes_stream.pipeline.offline import convert_recording

    session = Session(work / "recordings")
    counts: dict[str, dict[tuple, int]] = {}  # stream -> {(seq, t0): 1}
    power: dict[str, set] = {}
    late: dict[str, set] = {}
    runs: list[StatusMessage] = []  # each converter run's last status (uptime starts over at a restart)
    for msg in session.iter_messages():
        kind = msg.topic.split("/")[2] if msg.topic.count("/") >= 2 else ""
        if kind == "counts":
            c = CountsChunk.from_bytes(msg.payload)
            counts.setdefault(f"{c.board}/{c.module}", {})[(c.seq, c.times_ns()[0].item())] = 1
        elif kind == "power":
            pw = PowerChunk.from_bytes(msg.payload)
            key = (pw.seq, pw.times_ns()[0].item())
            (late if pw.late else power).setdefault(f"{pw.board}/{pw.module}", set()).add(key)
        elif kind == "status":
            st = StatusMessage.from_bytes(msg.payload)
            if st.service == "converter":
                if runs and st.uptime_s >= runs[-1].uptime_s:
                    runs[-1] = st
                else:
                    runs.append(st)
    # Recording gaps: a sequence step other than +1 inside one run of the source (a restart starts over).
    gaps = {}
    for stream, chunks in counts.items():
        seqs = [s for s, _ in sorted(chunks, key=lambda k: k[1])]
        gaps[stream] = sum(b - a - 1 for a, b in zip(seqs, seqs[1:]) if b > a + 1)
    powerless = {s: sorted(k for k in chunks if k not in power.get(s, ()) and k not in late.get(s, ()))
                 for s, chunks in counts.items()}
    without_power = {s: len(v) for s, v in powerless.items()}
    t_first = min((t for chunks in counts.values() for _, t in chunks), default=0)
    conv_runs = procs["converter"].results() if "converter" in procs else []
    last = next((r for r in reversed(conv_runs) if r), None)
    ledger = Ledger.from_dict(last.get("ledger", {}) if last else {})
    # A killed converter printed no final statistics: its last recorded status stands for it, and what it held
    # then (pending, set aside) never became power.
    killed = sum(1 for r in conv_runs if r is None)
    reported_lost = sum(r.get("chunks_lost", 0) for r in conv_runs if r) + sum(
        st.chunks_lost + st.chunks_pending + st.chunks_set_aside for st in runs[:-1])
    # That bound counts a killed run's held chunks lost, though its successor converts them (or counts them never
    # received): the ledger over every run, each chunk once, is what `up` reports (core.ledger.merge_restarts).
    whole = merge_restarts([*(Ledger.from_dict(st.ledger) for st in runs[:-1]), ledger]) if last else None
    offline = convert_recording(work / "recordings", work / "offline.mcap", progress=False)
    off = Ledger.from_dict(offline.ledger).totals()
    tot = ledger.totals()
    checks = {
        "converter_ledger_balances": bool(last) and ledger.balanced(),
        "converter_line_says_lost": bool(last) and f"lost {tot.lost} of" in (last.get("ledger_line") or ""),
        "recording_counts_complete": sum(gaps.values()) == 0,
        "offline_converts_every_recorded_chunk": off.received == off.done + off.duplicate and off.shed_total == 0,
        "no_summary_hides_a_chunk": sum(without_power.values()) <= reported_lost,
    }
    return {
        "duration_s": duration_s,
        "events": log,
        "return_codes": rcs,
        "converter_runs": len(conv_runs),
        "converter_runs_killed": killed,
        "converter_ledger_line": last.get("ledger_line") if last else None,
        "converter_ledger_totals": tot.as_dict(),
        "converter_lost_reported_all_runs": reported_lost,
        "converter_ledger_line_all_runs": whole.line() if whole else None,
        "converter_lost_all_runs": whole.totals().lost if whole else None,
        "converter_unconfirmed_before_restart": last.get("unconfirmed_before_restart") if last else None,
        "recorder_lines": [r.get("ledger_line") for r in procs["recorder"].results() if r] if "recorder" in procs else [],
        "recorded_counts_chunks": sum(len(c) for c in counts.values()),
        "recording_gaps": gaps,
        "recorded_counts_without_power": without_power,
        # Which ones, and when (s after the first recorded sample; the events' clock starts about then), and what
        # the services warned of: a failed check says where to look.
        "without_power_seq_t_s": {s: [(q, round((t - t_first) / 1e9, 2)) for q, t in v[:12]]
                                  for s, v in powerless.items() if v},
        "warnings": _warnings(work),
        "late_power_chunks": sum(len(v) for v in late.values()),
        "offline_ledger_line": offline.ledger_line,
        "checks": checks,
        "ok": all(checks.values()),
    }


def _warnings(work: Path, most: int = 30) -> list[str]:
    """The services' lines about losses, gaps and history (each run's log; the first ``most``), without time stamps."""
    import re

    notable = re.compile(r"missed|lost [1-9]|gap|asked|dropped|never received|did not|error", re.IGNORECASE)
    lines = []
    for log in sorted(work.glob("*-[0-9]*.log")):
        for line in log.read_text(errors="replace").splitlines():
            if notable.search(line) and "running, up" not in line:
                lines.append(f"{log.stem}: {line.split(': ', 1)[-1][:300]}")
    return lines[:most]
