"""Chaos on a lab's network: three hosts as network namespaces, a lossy slow link, a partition, a router restart.

Hosts (network namespaces this run creates, named with a prefix of its own,
joined by veth links to a bridge in a fourth, the "switch"; addresses in
198.18.0.0/15, the range set aside for network tests, inside the namespaces
only):

- ``daq``: ``mntes-stream router`` and the minimal source (a client of it);
- ``analysis``: the converter and the recorder (clients of the DAQ router);
- ``laptop``: ``mntes-stream monitor --text`` (a client).

Each host's link carries ``tc netem`` delay and loss (when the kernel has
netem; else the run says so and goes on without). After a steady phase the
DAQ link is cut (switch port down) for ``partition_s``, then brought back;
later the router is stopped and started again. No process is restarted by
hand: each service reconnects by itself (zenoh client mode, io/reconnect.py).

Afterwards, from the services' own final statistics and the recording:

- per stream, converter and recorder each account for every chunk the source
  published (its ``counts_published``): received - duplicate + never
  received = published (a chunk in no ledger fails this);
- what they never received is what the partition lost beyond the source's
  history (``history_s``): ``lost`` > 0 only when the partition outlasted it,
  and each closing line says ``lost N of M``;
- the recording holds exactly the counts chunks the recorder says it recorded;
- reconnect times: from the link coming back (and the router restarting) to
  the next counts chunk recorded.

Needs root (``ip netns``); ``skip_reason()`` says why it cannot run.
"""

from __future__ import annotations

import os
import re
import secrets
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from mntes_stream.bench.chaos import ServiceProcess, service_configs

HELP = ("daq/analysis/laptop hosts as network namespaces: netem delay and loss, a DAQ-link partition, a router "
        "restart; every ledger accounts for every published chunk")

CHUNK_S = 0.1  # the minimal source's chunk length (its default)
PORT = 7447


def add_arguments(p) -> None:
    p.add_argument("--partition-s", type=float, default=15.0, help="seconds the DAQ link is down (default 15)")
    p.add_argument("--history-s", type=float, default=10.0, help="the sources' [zenoh] history_s (default 10)")
    p.add_argument("--delay-ms", type=float, default=50.0, help="netem delay on each host's link (default 50)")
    p.add_argument("--loss-pct", type=float, default=1.0, help="netem loss on each host's link (default 1)")
    p.add_argument("--modules", type=int, default=1, help="readout modules (default 1)")
    p.add_argument("--channels", type=int, default=8, help="channels per module (default 8)")
    p.add_argument("--keep", metavar="DIR", help="work in DIR and keep it (recordings, logs)")


def run(args) -> dict:
    reason = skip_reason()
    if reason:
        from mntes_stream.errors import ConfigError

        raise ConfigError(f"bench chaos-net: {reason}")
    # A SIGTERM (a timeout, a CI cancel) unwinds like Ctrl-C: the namespaces are deleted on the way out.
    signal.signal(signal.SIGTERM, lambda *_: (_ for _ in ()).throw(KeyboardInterrupt()))
    kw = dict(partition_s=args.partition_s, history_s=args.history_s, delay_ms=args.delay_ms, loss_pct=args.loss_pct,
              modules=args.modules, channels=args.channels)
    if args.keep:
        work = Path(args.keep)
        work.mkdir(parents=True, exist_ok=True)
        return run_chaos_net(work, **kw)
    with tempfile.TemporaryDirectory(prefix="mntes-chaos-net-") as tmp:
        return run_chaos_net(Path(tmp), **kw)


def _ip(*args: str, check: bool = True) -> subprocess.CompletedProcess:
    return subprocess.run(["ip", *args], capture_output=True, text=True, timeout=30, check=check)


def skip_reason() -> str:
    """Why network namespaces cannot be made here ("" if they can)."""
    if shutil.which("ip") is None:
        return "no `ip` command (iproute2)"
    name = f"mntes-probe-{os.getpid()}-{secrets.token_hex(2)}"
    try:
        res = _ip("netns", "add", name, check=False)
    except (OSError, subprocess.SubprocessError) as exc:
        return f"`ip netns add` failed: {exc}"
    if res.returncode != 0:
        return f"`ip netns add` not permitted: {res.stderr.strip() or res.returncode}"
    try:
        for args in (("link", "add", "p0", "type", "veth", "peer", "name", "p1"), ("link", "add", "br0", "type", "bridge")):
            res = _ip("-n", name, *args, check=False)
            if res.returncode != 0:
                return f"`ip link add {' '.join(args[2:])}` not permitted in a namespace: {res.stderr.strip()}"
    finally:
        _ip("netns", "del", name, check=False)
    return ""


class Lab:
    """The namespaces, the switch and the links of one run; ``close()`` deletes every namespace it made."""

    HOSTS = ("daq", "analysis", "laptop")

    def __init__(self, delay_ms: float, loss_pct: float):
        self.prefix = f"mntes-{os.getpid()}-{secrets.token_hex(2)}"
        self.net = f"198.{18 + secrets.randbelow(2)}.{secrets.randbelow(256)}"
        self.made: list[str] = []
        self.addr = {h: f"{self.net}.{k + 1}" for k, h in enumerate(self.HOSTS)}
        self.impairment = "none"
        self.wire: subprocess.Popen | None = None
        try:
            self._build(delay_ms, loss_pct)
        except BaseException:
            self.close()
            raise

    def ns(self, host: str) -> str:
        return f"{self.prefix}-{host}"

    def _build(self, delay_ms: float, loss_pct: float) -> None:
        sw = self.ns("switch")
        for name in (sw, *(self.ns(h) for h in self.HOSTS)):
            _ip("netns", "add", name)
            self.made.append(name)
            _ip("-n", name, "link", "set", "lo", "up")
        _ip("-n", sw, "link", "add", "br0", "type", "bridge")
        _ip("-n", sw, "link", "set", "br0", "up")
        for h in self.HOSTS:
            # The switch port is named after the host; the host's end is eth0 (names are per namespace).
            _ip("-n", sw, "link", "add", h, "type", "veth", "peer", "name", "eth0", "netns", self.ns(h))
            _ip("-n", self.ns(h), "addr", "add", f"{self.addr[h]}/24", "dev", "eth0")
            _ip("-n", self.ns(h), "link", "set", "eth0", "up")
        fails = []
        if delay_ms > 0 or loss_pct > 0:
            for h in self.HOSTS:
                res = subprocess.run([*self.argv(h), "tc", "qdisc", "add", "dev", "eth0", "root", "netem", "delay",
                                      f"{delay_ms:g}ms", "loss", f"{loss_pct:g}%"], capture_output=True, text=True,
                                     timeout=30)
                if res.returncode != 0:
                    fails.append(res.stderr.strip())
                    break
        wired = ()
        if fails:
            # No netem in this kernel: the DAQ link (all traffic goes through the DAQ router) gets a wire of frames
            # delayed and dropped in user space instead, the same delay and loss each way (bench/_wire.py).
            for h in self.HOSTS:
                _ip("-n", self.ns(h), "link", "set", "eth0", "gso_max_size", "1500")  # no super-frames to forward
                subprocess.run([*self.argv(h), "tc", "qdisc", "del", "dev", "eth0", "root"], capture_output=True,
                               timeout=30)
            wired = ("daq",)
            _ip("-n", sw, "link", "add", "daq-in", "type", "veth", "peer", "name", "daq-w")
            for port in ("daq-in", "daq-w"):
                _ip("-n", sw, "link", "set", port, "gso_max_size", "1500")
            _ip("-n", sw, "link", "set", "daq-in", "master", "br0")
            for port in ("daq-in", "daq-w", "daq"):
                _ip("-n", sw, "link", "set", port, "promisc", "on", "up")
            self.wire = subprocess.Popen([*self.argv("switch"), sys.executable, "-m", "mntes_stream.bench._wire",
                                          "daq", "daq-w", f"{delay_ms:g}", f"{loss_pct:g}", "0"],
                                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
            self.impairment = (f"delay {delay_ms:g} ms, loss {loss_pct:g} % each way on the DAQ link, in user space "
                               f"(bench/_wire.py: tc netem unavailable: {fails[0]})")
        elif delay_ms > 0 or loss_pct > 0:
            self.impairment = f"netem delay {delay_ms:g} ms, loss {loss_pct:g} % on each host's link"
        for h in self.HOSTS:
            if h not in wired:
                _ip("-n", sw, "link", "set", h, "master", "br0")
            _ip("-n", sw, "link", "set", h, "up")

    def link(self, host: str, up: bool) -> None:
        """Bring the switch port of ``host`` up or down (down: a partition of that host)."""
        _ip("-n", self.ns("switch"), "link", "set", host, "up" if up else "down")

    def argv(self, host: str) -> list[str]:
        return ["ip", "netns", "exec", self.ns(host)]

    def close(self) -> None:
        if self.wire is not None and self.wire.poll() is None:
            self.wire.kill()
            self.wire.wait(10)
        for name in reversed(self.made):
            # Killing what still runs inside first: a namespace with processes would outlive `ip netns del`.
            pids = _ip("netns", "pids", name, check=False).stdout.split()
            for pid in pids:
                try:
                    os.kill(int(pid), signal.SIGKILL)
                except (ProcessLookupError, ValueError):
                    pass
            _ip("netns", "del", name, check=False)
        self.made = []


# zenoh-ext's AdvancedSubscriber times its history and recovery queries out after this (its builder's default,
# query_timeout; zenoh-python does not set it).
_QUERY_TIMEOUT_S = 10.0


def run_chaos_net(work: Path, partition_s: float = 15.0, history_s: float = 10.0, delay_ms: float = 50.0,
                  loss_pct: float = 1.0, modules: int = 1, channels: int = 8, steady_s: float = 8.0,
                  recover_s: float = 12.0, after_restart_s: float = 10.0, say=None) -> dict:
    """Run the schedule (steady, partition, recovery, router restart) in ``work``; figures and checks."""
    say = say or (lambda m: print(m, file=sys.stderr, flush=True))
    lab = Lab(delay_ms, loss_pct)
    procs: dict[str, ServiceProcess] = {}
    rcs: dict[str, int] = {}
    rss_mb: dict[str, float | None] = {}
    marks: dict[str, int] = {}
    try:
        say(f"chaos-net: namespaces {lab.prefix}-*, {lab.net}.0/24; impairment: {lab.impairment}")
        cfg = service_configs(work, PORT, modules, channels, host=lab.addr["daq"], setup="net", history_s=history_s,
                              checkpoint=False)

        def start(name: str, host: str, *argv: str) -> ServiceProcess:
            procs[name] = ServiceProcess(name, list(argv), work, prefix=lab.argv(host))
            return procs[name]

        start("router", "daq", "router", "--config", str(cfg["router"])).wait_log("zenoh id")
        rtt_s = _connect_rtt_s(lab.argv("analysis"), lab.addr["daq"])
        start("converter", "analysis", "serve", "--config", str(cfg["converter"]), "--json").wait_log(
            "detectors, kind", 600)  # a cold table build
        start("recorder", "analysis", "serve", "--config", str(cfg["recorder"]), "--json").wait_log(
            "recording mntes/net/")
        start("monitor", "laptop", "monitor", "--text", "--setup", "net", "--update-s", "1", "-m", "client",
              "-e", f"tcp/{lab.addr['daq']}:{PORT}")
        start("source", "daq", "serve", "--config", str(cfg["source"]), "--json")
        time.sleep(steady_s)
        say(f"chaos-net: DAQ link down for {partition_s:g} s")
        marks["partition_ns"] = time.time_ns()
        lab.link("daq", False)
        time.sleep(partition_s)
        lab.link("daq", True)
        marks["link_up_ns"] = time.time_ns()
        say("chaos-net: DAQ link up")
        time.sleep(recover_s)
        say("chaos-net: router restart")
        marks["router_down_ns"] = time.time_ns()
        procs["router"].stop()
        procs["router"].start()
        procs["router"].wait_log("zenoh id")
        marks["router_up_ns"] = time.time_ns()
        time.sleep(after_restart_s)
        rss_mb = {name: _max_rss_mb(pr.p.pid) for name, pr in procs.items()}
    finally:
        # Orderly end: the source stops, the converter converts what it holds, the recorder finishes last.
        # The converter is given zenoh-ext's query timeout (10 s) and one more: a subscriber that saw a gap
        # holds the samples after it until its recovery query ends. A CI run saw a converter stall 11 s after
        # the router restart while the recorder did not, and stopped 3 s after the source it lacked the last 30
        # chunks, which its summary could not know of (the recorder's named them: counts without power).
        for name in ("source", "converter", "recorder", "monitor", "router"):
            if name in procs:
                if name == "converter":
                    time.sleep(_QUERY_TIMEOUT_S + 1.0)
                rcs[name] = procs[name].stop()
        lab.close()
    res = _analyse(work, procs, rcs, marks, lab, partition_s, history_s)
    return {"impairment": lab.impairment, "tcp_connect_analysis_to_daq_ms": round(rtt_s * 1e3, 1), **res,
            "max_rss_mb": rss_mb}


def _max_rss_mb(pid: int) -> float | None:
    """The process's peak resident memory so far (``VmHWM``), MB."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return round(int(line.split()[1]) / 1024, 1)
    except OSError:
        pass
    return None


def _connect_rtt_s(prefix: list[str], host: str) -> float:
    """Median of 5 TCP connects from a namespace to the router (one round trip each): the link's delay."""
    code = (f"import socket,time,statistics\nts=[]\nfor _ in range(5):\n t=time.monotonic()\n"
            f" socket.create_connection(('{host}',{PORT}),timeout=5).close()\n ts.append(time.monotonic()-t)\n"
            "print(statistics.median(ts))")
    res = subprocess.run([*prefix, sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    try:
        return float(res.stdout.strip())
    except ValueError:
        return float("nan")


def _first_after(times_ns: list[int], t_ns: int | None) -> float | None:
    later = [t for t in times_ns if t_ns is not None and t > t_ns]
    return round((min(later) - t_ns) / 1e9, 2) if later else None


def _analyse(work: Path, procs: dict, rcs: dict, marks: dict, lab: Lab, partition_s: float, history_s: float) -> dict:
    from mntes_stream.core.ledger import Ledger
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import CountsChunk

    def final(name: str) -> dict:
        res = procs[name].results() if name in procs else []
        return res[-1] if res and res[-1] else {}

    src, conv, rec = final("source"), final("converter"), final("recorder")
    published: dict[str, int] = src.get("counts_published", {})
    recorded: dict[str, set] = {}
    arrivals: list[int] = []
    if (work / "recordings").exists():
        for msg in Session(work / "recordings").iter_messages():
            if "/counts/" in msg.topic:
                c = CountsChunk.from_bytes(msg.payload)
                recorded.setdefault(f"{c.board}/{c.module}", set()).add(c.seq)
                arrivals.append(msg.log_time_ns)
    accounts = {}
    for who, stats in (("converter", conv), ("recorder", rec)):
        led = Ledger.from_dict(stats.get("ledger", {}))
        per = {}
        for stream, n_pub in published.items():
            d = (stats.get("ledger", {}).get(stream) or {})
            accounted = d.get("received", 0) - d.get("duplicate", 0) + d.get("missing", 0)
            per[stream] = {"published": n_pub, "accounted": accounted, "missing": d.get("missing", 0)}
        accounts[who] = {"streams": per, "lost": led.totals().lost, "line": stats.get("ledger_line", "")}
    never = {who: sum(v["missing"] for v in a["streams"].values()) for who, a in accounts.items()}
    # The bounds below are per stream: each stream loses the same stretch of time.
    per_stream = [v["missing"] for a in accounts.values() for v in a["streams"].values()]
    # What the partition could lose: the link down plus the time to reconnect, less what the caches hold.
    reconnect_s = _first_after(arrivals, marks.get("link_up_ns"))
    router_reconnect_s = _first_after(arrivals, marks.get("router_up_ns"))
    beyond_s = partition_s + (reconnect_s or 0.0) - history_s
    router_down_s = (marks.get("router_up_ns", 0) - marks.get("router_down_ns", 0)) / 1e9
    outages_s = partition_s + (reconnect_s or 0.0) + router_down_s + (router_reconnect_s or 0.0)
    monitor_log = procs["monitor"].logs[-1].read_text(errors="replace") if "monitor" in procs else ""
    monitor_out = (work / "monitor-0.json").read_text(errors="replace") if "monitor" in procs else ""
    monitor_ledgers = re.findall(r"^ledger converter: (.*)$", monitor_out, re.M)
    checks = {
        "every_process_ended_cleanly": all(rc in (0, 130) for rc in rcs.values()) and bool(rcs),
        "source_summary_counts_published": bool(published) and all(n > 0 for n in published.values()),
        "converter_accounts_for_every_published_chunk": bool(published) and all(
            v["accounted"] == v["published"] for v in accounts["converter"]["streams"].values()),
        "recorder_accounts_for_every_published_chunk": bool(published) and all(
            v["accounted"] == v["published"] for v in accounts["recorder"]["streams"].values()),
        "closing_lines_say_lost": all(re.search(rf"lost {a['lost']} of \d+$", a["line"] or "")
                                      for a in accounts.values()),
        # Loss only where the partition outlasted the caches (1 s of slack either way: reconnect timing).
        "lost_only_beyond_history": bool(per_stream) and all(
            (n == 0) if beyond_s < -1.0 else (n > 0) if beyond_s > 1.0 else True for n in per_stream),
        # ... and nothing outside the partition, the router's restart and the reconnects (netem's loss is TCP's
        # to repair, not a gap).
        "lost_only_in_the_outages": all(n <= outages_s / CHUNK_S + 10 for n in per_stream),
        "recording_matches_recorder_ledger": sum(len(s) for s in recorded.values()) == sum(
            (rec.get("ledger", {}).get(s) or {}).get("done", 0) for s in published),
        "services_reconnected": reconnect_s is not None and router_reconnect_s is not None,
        "monitor_saw_the_ledger": bool(monitor_ledgers) and "Traceback" not in monitor_log,
    }
    return {
        "partition_s": partition_s,
        "history_s": history_s,
        "counts_published": published,
        "converter_ledger_line": accounts["converter"]["line"],
        "recorder_ledger_line": accounts["recorder"]["line"],
        "monitor_last_ledger_line": monitor_ledgers[-1] if monitor_ledgers else None,
        # What the monitor said where it raised (its log from the first traceback on, bounded): the failure explains
        # itself (CI keeps no work directory).
        "monitor_traceback": ("\n".join(monitor_log[monitor_log.index("Traceback"):].splitlines()[:40])
                              if "Traceback" in monitor_log else None),
        "never_received": never,
        "expected_lost_chunks_per_stream_about": max(0, round(beyond_s / CHUNK_S)),
        "reconnect_after_link_up_s": reconnect_s,
        "router_down_s": round(router_down_s, 2),
        "reconnect_after_router_restart_s": router_reconnect_s,
        "recorded_counts_chunks": sum(len(s) for s in recorded.values()),
        "accounts": accounts,
        "return_codes": rcs,
        "checks": checks,
        "ok": all(checks.values()),
    }
