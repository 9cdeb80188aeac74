"""``mntes-stream bench dfmux``: the ``dfmux-bridge``'s throughput on synthetic IceBoard packets, per core.

Each case runs in a private network namespace (``unshare -n``, loopback up):
a zenoh subscriber (this process), the bridge (``mntes-stream dfmux-bridge``,
its own process, spt3g 1.0.2 without so3g) and the synthetic boards
(``python -m mntes_stream.dfmux.sender``, another process: UDP multicast on
127.0.0.1, TTL 0) at the DfMux rate, ``MODULES / 8`` V3 boards of 8 modules
x 64 channels. Measured: packets per second, the bridge's CPU (its process:
spt3g's listener and builder threads, our assembly, zenoh) from its first to
its last counts message, hence M detector-samples per second per core; and
every sample checked against what was sent (lost, wrong).

:func:`run_netns` is also the harness of ``tests/test_dfmux_bridge.py`` and
of the lab recipe's check.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time

from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ

HELP = "dfmux-bridge throughput: IceBoard packets -> counts on zenoh (packets/s, M samples/s per core)"
SPT3G_DETECTORS = 16_000
SPT3G_MSAMPLES_S = SPT3G_DETECTORS * DFMUX_SAMPLE_RATE_HZ / 1e6
_PORT = 7447


def netns_reason() -> str | None:
    """Why a private network namespace cannot be made here (None: it can)."""
    if not sys.platform.startswith("linux"):
        return "private network namespaces need Linux"
    for tool in ("unshare", "ip"):
        if shutil.which(tool) is None:
            return f"{tool} not found"
    try:
        r = subprocess.run(["unshare", "-n", "ip", "link", "set", "lo", "up"], capture_output=True, timeout=10)
    except (OSError, subprocess.TimeoutExpired) as exc:
        return f"unshare -n failed: {exc}"
    if r.returncode:
        return f"unshare -n not permitted: {r.stderr.decode(errors='replace').strip()[:100]}"
    return None


def run_netns(spec: dict, timeout_s: float = 120.0) -> dict:
    """Run one case (see :func:`inside`) in a new private network namespace; its result."""
    proc = subprocess.run(["unshare", "-n", sys.executable, "-m", "mntes_stream.bench.dfmux", json.dumps(spec)],
                          capture_output=True, text=True, timeout=timeout_s)
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode or not lines:
        raise RuntimeError(f"dfmux case failed (rc {proc.returncode}): {proc.stderr.strip()[-2000:]}")
    return json.loads(lines[-1])


def _cpu_s(pid: int) -> float | None:
    try:
        with open(f"/proc/{pid}/stat") as f:
            fields = f.read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _board_flags(spec) -> list[str]:
    flags = []
    for text in spec["boards"]:
        version, serial, *rest = text.split(":")
        if version == "2":
            flags += ["--v2-board", f"{rest[2]}={serial}"]
        else:
            flags += ["--board", serial]
    return flags


def _expected(spec, summary) -> dict:
    """``(board, module)`` -> sample numbers sent."""
    from mntes_stream.dfmux.sender import parse_board, parse_skip

    skips = [parse_skip(s) for s in spec.get("skip", [])]
    out = {}
    for text in spec["boards"]:
        b = parse_board(text)
        ks = [k for k in range(summary["samples"])
              if not any(s == b["serial"] and k0 <= k < k1 for s, k0, k1 in skips)]
        for m in range(b["modules"]):
            out[(b["serial"], m)] = ks
    return out


def inside(spec: dict) -> dict:
    """In the namespace: subscriber, bridge, sender; every counts sample checked against what was sent.

    ``spec``: ``boards`` (sender specs VERSION:SERIAL:MODULES[:CHANNELS[:SOURCE_IP]]), ``duration_s``,
    ``skip``/``restart`` (sender flags), ``bridge_args`` (more bridge flags), ``verify`` (check values),
    ``sender_args`` (more sender flags, e.g. ``--counts detector``: then give ``verify`` False), ``bias`` (the
    bridge's ``--bias`` flags; default ``*=3e-6``), ``messages_out`` (a path: every message received, an
    ``.npz`` of ``keys``, ``sizes`` and the ``payloads`` end to end, for the caller to decode).
    """
    import numpy as np

    from mntes_stream.dfmux.packets import SAMPLE_NS, synthetic_counts
    from mntes_stream.dfmux.sender import udp_sockets
    from mntes_stream.io.messages import decode
    from mntes_stream.io.transport import ZenohSettings, open_session

    subprocess.run(["ip", "link", "set", "lo", "up"], check=True)
    got: list = []
    with open_session(ZenohSettings(mode="peer", listen=(f"tcp/127.0.0.1:{_PORT}",))) as session:
        sub = session.declare_subscriber("mntes/**", lambda s: got.append(
            (str(s.key_expr), s.payload.to_bytes(), time.monotonic())))
        bridge = subprocess.Popen(
            [sys.executable, "-m", "mntes_stream", "dfmux-bridge", "--interface", "127.0.0.1", *_board_flags(spec),
             "-e", f"tcp/127.0.0.1:{_PORT}", "--t-bath-k", "0.1", *spec.get("bias", ["--bias", "*=3e-6"]),
             *spec.get("bridge_args", [])],
            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        cpu: list = []
        done = threading.Event()

        def sample_cpu():
            while not done.is_set():
                c = _cpu_s(bridge.pid)
                if c is not None:
                    cpu.append((time.monotonic(), c))
                done.wait(0.05)

        threading.Thread(target=sample_cpu, daemon=True).start()
        cmd = [sys.executable, "-m", "mntes_stream.dfmux.sender", "--counts", "checkable", "--wait-listener", "60",
               "--duration", str(spec.get("duration_s", 1.0))]
        for text in spec["boards"]:
            cmd += ["--board", text]
        for text in spec.get("skip", []):
            cmd += ["--skip", text]
        for serial in spec.get("restart", []):
            cmd += ["--restart", str(serial)]
        cmd += spec.get("sender_args", [])
        snd = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
        if snd.returncode:
            bridge.kill()
            raise SystemExit(f"sender failed: {snd.stderr.strip()[-500:]} / bridge: {bridge.communicate()[1][-1500:]}")
        summary = json.loads(snd.stdout.strip().splitlines()[-1])
        udp = udp_sockets()
        expected = _expected(spec, summary)
        full = sum(len(ks) // 16 for ks in expected.values())
        t_end = time.monotonic() + 30
        n_last, t_quiet = -1, time.monotonic()
        while time.monotonic() < t_end:  # every full chunk, or nothing new for 1.5 s (a board's gap holds the
            n = sum(1 for k, _, _ in got if "/counts/" in k)  # builder up to 1000 samples: the stop releases)
            if n >= full:
                break
            if n != n_last:
                n_last, t_quiet = n, time.monotonic()
            elif time.monotonic() - t_quiet > 1.5:
                break
            time.sleep(0.05)
        bridge.send_signal(signal.SIGINT)
        try:
            out, err = bridge.communicate(timeout=30)
        except subprocess.TimeoutExpired:
            bridge.kill()
            out, err = bridge.communicate()
        done.set()
        time.sleep(0.3)
        sub.undeclare()
    if spec.get("messages_out"):
        np.savez(spec["messages_out"], keys=np.array([k for k, _, _ in got]),
                 sizes=np.array([len(p) for _, p, _ in got]),
                 payloads=np.frombuffer(b"".join(p for _, p, _ in got), dtype=np.uint8))
    counts = [(k, p, t) for k, p, t in got if "/counts/" in k]
    seen: dict = {}
    wrong = 0
    n_values = 0
    for _, payload, _ in counts:
        m = decode(payload)
        t = m.times_ns() - summary["t0_ns"]
        ks = t // SAMPLE_NS
        wrong += int(np.count_nonzero(t % SAMPLE_NS))
        if spec.get("verify", True):
            i, q = synthetic_counts(m.board, m.module, m.channels, ks)
            wrong += int(np.count_nonzero(i != m.counts_i) + np.count_nonzero(q != m.counts_q))
        n_values += m.counts_i.size
        seen.setdefault((m.board, m.module), []).extend(ks.tolist())
    missing = sum(len(set(ks) - set(seen.get(st, ()))) for st, ks in expected.items())
    extra = sum(len(v) - len(set(v) & set(expected.get(st, ()))) for st, v in seen.items())
    result = {"sender": summary, "bridge_rc": bridge.returncode, "bridge_stdout": out.strip().splitlines(),
              "bridge_stderr": err.strip().splitlines()[-20:], "counts_messages": len(counts),
              "hk_messages": sum(1 for k, _, _ in got if "/hk/" in k),
              "hk_sensors": sorted({k.split("/hk/", 1)[1].split("/")[0] for k, _, _ in got if "/hk/" in k}),
              "values": n_values, "wrong": wrong,
              "samples_missing": missing, "samples_unexpected": extra, "streams": len(seen),
              "udp_drops": sum(s["drops"] for s in udp)}
    if counts and cpu:
        t0, t1 = counts[0][2], counts[-1][2]
        c0 = min(cpu, key=lambda x: abs(x[0] - t0))
        c1 = min(cpu, key=lambda x: abs(x[0] - t1))
        wall = max(c1[0] - c0[0], 1e-9)
        result.update({"bridge_wall_s": round(wall, 3), "bridge_cpu_s": round(c1[1] - c0[1], 3),
                       "bridge_cpu_fraction": round((c1[1] - c0[1]) / wall, 3)})
    return result


def add_arguments(p) -> None:
    p.add_argument("--modules", type=int, nargs="+", default=[16, 64, 256],
                   help="modules (V3 boards of 8 x 64 channels) of each case (default 16 64 256)")
    p.add_argument("--duration", type=float, default=5.0, help="seconds of data per case (default 5)")
    p.add_argument("--channels", type=int, default=64, help="channels per module (default 64)")


def run(args) -> dict:
    reason = netns_reason()
    if reason:
        from mntes_stream.errors import ConfigError

        raise ConfigError(f"bench dfmux: {reason}")
    cases = []
    for modules in args.modules:
        boards = [f"3:{100 + j}:{min(8, modules - 8 * j)}:{args.channels}" for j in range(-(-modules // 8))]
        r = run_netns({"boards": boards, "duration_s": args.duration, "verify": True},
                      timeout_s=120 + 10 * args.duration)
        s = r["sender"]
        det_samples = r["values"]
        case = {"modules": modules, "detectors": modules * args.channels, "boards": len(boards),
                "packets_sent": s["packets"], "packets_per_s": round(s["packets"] / max(s["wall_s"], 1e-9)),
                "sender_wall_s": s["wall_s"], "data_s": round(s["samples"] / DFMUX_SAMPLE_RATE_HZ, 3),
                "detector_samples": det_samples, "wrong": r["wrong"], "samples_missing": r["samples_missing"],
                "udp_drops": r["udp_drops"], "bridge_last_line": (r["bridge_stdout"] or [""])[-1]}
        if "bridge_cpu_s" in r:
            case.update({"bridge_cpu_s": r["bridge_cpu_s"], "bridge_wall_s": r["bridge_wall_s"],
                         "bridge_cpu_fraction": r["bridge_cpu_fraction"],
                         "msamples_per_s_per_core": round(det_samples / max(r["bridge_cpu_s"], 1e-9) / 1e6, 2),
                         "packets_per_s_per_core": round(s["packets"] / max(r["bridge_cpu_s"], 1e-9))})
        cases.append(case)
    best = max((c.get("msamples_per_s_per_core", 0) for c in cases), default=0)
    big = max(cases, key=lambda c: c["modules"])
    fits = (big["detectors"] >= SPT3G_DETECTORS and big["samples_missing"] == 0 and big["wrong"] == 0
            and big.get("bridge_cpu_fraction", 9) < 0.8)
    return {"cases": cases, "spt3g_msamples_per_s": round(SPT3G_MSAMPLES_S, 3),
            "spt3g_fits_one_bridge": fits,
            "spt3g_verdict": (f"{big['detectors']} detectors at the DfMux rate: {big.get('bridge_cpu_fraction')} of a "
                              f"core, {big['samples_missing']} samples missing, {big['wrong']} wrong -> "
                              + ("one bridge process suffices" if fits else
                                 f"split boards over bridges: about {SPT3G_MSAMPLES_S / max(best, 1e-9) * 1.25:.1f} "
                                 "cores' worth of bridges"))}


if __name__ == "__main__":
    print(json.dumps(inside(json.loads(sys.argv[1]))))
