"""A synthetic IceBoard: UDP multicast packets as boards send them, for tests, ``bench dfmux`` and the lab recipe.

Run it as its own process (``python -m mntes_stream.dfmux.sender``): spt3g's
``DfMuxCollector.Stop()`` holds the GIL until one more datagram arrives, so
a sender in the bridge's process could never wake it. Multicast leaves on
``--interface`` only (``IP_MULTICAST_IF``) with TTL 0: it never crosses a
router, and on 127.0.0.1 it stays on this machine.

Counts (``--counts``):

- ``detector`` (default): the array simulator's detectors behind each board
  (:mod:`.detectors`), with their bias, optical signal and noise: what a
  converter turns into power. ``--params-out`` writes their parameter file
  (ids as the bridge publishes them), ``--bias-args`` prints the bridge's
  ``--bias`` arguments for their bias and sends nothing.
- ``checkable``: :func:`~mntes_stream.dfmux.packets.synthetic_counts` of
  (board, module, channel, sample number), so a receiver can check every
  value (no detector could produce them).

The last line on stdout is a JSON summary (``t0_ns``, samples and packets
sent per board, ``late_s`` the most a sample went out behind its time).
"""

from __future__ import annotations

import argparse
import json
import queue
import socket
import sys
import threading
import time

from mntes_stream.dfmux.packets import GROUP, PORT, SAMPLE_NS, PacketBuilder, header_dtype
from mntes_stream.errors import MntesError

__all__ = ["main", "parse_board", "multicast_socket", "detector_boards"]

# Detector counts are simulated ahead by a thread, 64 samples (0.42 s) at a time: the send clock never waits
# for the simulator, which takes about a quarter of a core for 128 detectors.
BLOCK_SAMPLES = 64


def parse_board(text: str) -> dict:
    """``VERSION:SERIAL:MODULES[:CHANNELS[:SOURCE_IP]]`` -> dict (SOURCE_IP names a V2 board to the collector)."""
    parts = text.split(":")
    try:
        if not 3 <= len(parts) <= 5:
            raise ValueError
        spec = {"version": int(parts[0]), "serial": int(parts[1]), "modules": int(parts[2]),
                "channels": int(parts[3]) if len(parts) > 3 and parts[3] else 64,
                "source": parts[4] if len(parts) > 4 else ""}
    except ValueError:
        raise argparse.ArgumentTypeError(f"--board {text!r}: expected VERSION:SERIAL:MODULES[:CHANNELS[:SOURCE_IP]]") from None
    return spec


def parse_skip(text: str) -> tuple[int, int, int]:
    """``SERIAL:FROM:TO`` -> (serial, first sample not sent, first sample sent again)."""
    try:
        serial, k0, k1 = (int(x) for x in text.split(":"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"--skip {text!r}: expected SERIAL:FROM:TO (sample numbers)") from None
    return serial, k0, k1


BAD_KINDS = ("magic", "version", "short", "long", "board", "module")


def parse_bad(text: str) -> tuple[str, int, int]:
    """``KIND:SERIAL:K`` -> (kind, serial, sample number); see ``--bad``."""
    parts = text.split(":")
    try:
        if len(parts) != 3 or parts[0] not in BAD_KINDS:
            raise ValueError
        return parts[0], int(parts[1]), int(parts[2])
    except ValueError:
        raise argparse.ArgumentTypeError(f"--bad {text!r}: expected KIND:SERIAL:K, KIND one of "
                                         f"{', '.join(BAD_KINDS)}") from None


def parse_shift(text: str) -> tuple[int, int, float]:
    """``SERIAL:K:SECONDS`` -> (serial, first sample shifted, seconds); see ``--shift``."""
    try:
        serial, k, sec = text.split(":")
        return int(serial), int(k), float(sec)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--shift {text!r}: expected SERIAL:K:SECONDS") from None


def bad_packets(kind: str, packets: list[bytes]) -> tuple[list[bytes], list[bytes]]:
    """A board's packets of one sample, made hostile: ``(packets to send instead, extra packets)``.

    ``magic``, ``version``, ``short`` (10 bytes cut), ``long`` (20 bytes added), ``board`` (serial 999, not a
    configured board): one extra packet, a copy of the first, spoilt; ``module``: the last module's packet
    claims module 200 instead (the module's sample goes missing).
    """
    first = packets[0]
    if kind == "module":
        last = bytearray(packets[-1])
        last[header_dtype(1).fields["module"][1]] = 200
        return packets[:-1] + [bytes(last)], []
    spoilt = {"magic": lambda r: bytes(4) + r[4:], "version": lambda r: r[:4] + (9).to_bytes(2, "little") + r[6:],
              "short": lambda r: r[:-10], "long": lambda r: r + bytes(20),
              "board": lambda r: r[:6] + (999).to_bytes(2, "little") + r[8:]}[kind](first)
    return packets, [spoilt]


def multicast_socket(interface: str, source: str = "") -> socket.socket:
    """A UDP socket sending to the DfMux group on ``interface`` only, TTL 0, looped back to local listeners."""
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM, socket.IPPROTO_UDP)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(interface))
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
    sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_LOOP, 1)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, 4 << 20)
    if source:
        sock.bind((source, 0))
    return sock


def wait_listener(timeout_s: float) -> bool:
    """True once a UDP socket is bound to the DfMux port in this network namespace (read from /proc/net/udp)."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        if udp_sockets():
            return True
        time.sleep(0.05)
    return False


def udp_sockets(port: int = PORT) -> list[dict]:
    """UDP sockets bound to ``port`` in this network namespace: receive queue and drops (/proc/net/udp)."""
    out = []
    try:
        with open("/proc/net/udp") as f:
            lines = f.read().splitlines()[1:]
    except OSError:
        return out
    for line in lines:
        fields = line.split()
        if len(fields) > 12 and fields[1].endswith(f":{port:04X}"):
            out.append({"rx_queue": int(fields[4].split(":")[1], 16), "drops": int(fields[-1])})
    return out


def detector_boards(boards, seed: int = 0) -> list:
    """A :class:`~mntes_stream.dfmux.detectors.DetectorBoard` per ``--board`` spec (:func:`parse_board`)."""
    from mntes_stream.dfmux.detectors import DetectorBoard

    return [DetectorBoard(b["serial"], b["modules"], PacketBuilder(b["version"], b["serial"], b["modules"],
                                                                   b["channels"]).channels, seed)
            for b in boards]


class _Feed:
    """The detectors' counts sample by sample, simulated ``BLOCK_SAMPLES`` ahead by a thread."""

    def __init__(self, boards, n: int):
        self._boards = {b.serial: b for b in boards}
        self._q: queue.Queue = queue.Queue(maxsize=2)
        self._block: dict = {}
        self._k0 = self._width = 0
        threading.Thread(target=self._run, args=(n,), name="detectors", daemon=True).start()
        self._advance()  # the first block before the first packet

    def _run(self, n: int) -> None:
        k = 0
        try:
            while k < n:
                m = min(BLOCK_SAMPLES, n - k)
                self._q.put({s: b.next_counts(m)[1:] for s, b in self._boards.items()})
                k += m
        except Exception as exc:  # said by the sending thread, in one line
            self._q.put(exc)

    def _advance(self) -> None:
        got = self._q.get()
        if isinstance(got, Exception):
            raise got
        self._k0 += self._width
        self._block = got
        self._width = next(iter(got.values()))[0].shape[2]

    def counts(self, serial: int, k: int):
        """``(I, Q)`` of board ``serial`` at sample ``k`` (non-decreasing), shape (modules, channels)."""
        while k >= self._k0 + self._width:
            self._advance()
        i, q = self._block[serial]
        return i[:, :, k - self._k0], q[:, :, k - self._k0]


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mntes_stream.dfmux.sender", description=__doc__.split("\n")[0])
    p.add_argument("--board", action="append", type=parse_board, required=True,
                   help="VERSION:SERIAL:MODULES[:CHANNELS[:SOURCE_IP]] (repeatable)")
    p.add_argument("--counts", choices=("detector", "checkable"), default="detector",
                   help="detector: the array simulator's detectors, with their bias (default); checkable: a function "
                        "of (board, module, channel, sample number), for receivers checking every value")
    p.add_argument("--seed", type=int, default=0, help="detector counts: with each serial, the simulator's seed")
    p.add_argument("--params-out", metavar="TOML", help="detector counts: write the detectors' parameter file "
                   "(ids b<serial>m<module>c<channel>, as dfmux-bridge publishes them)")
    p.add_argument("--bias-args", action="store_true", help="detector counts: print dfmux-bridge's --bias arguments "
                   "for the detectors' bias (one line) and send nothing")
    p.add_argument("--interface", default="127.0.0.1", help="address of the interface to send on")
    p.add_argument("--duration", type=float, default=1.0, help="seconds of data to send (0: none, e.g. only "
                   "--params-out)")
    p.add_argument("--flat-out", action="store_true", help="send as fast as possible, not at the DfMux rate")
    p.add_argument("--start-ns", type=int, default=0, help="time of sample 0 (0: now, on a sample boundary)")
    p.add_argument("--skip", action="append", type=parse_skip, default=[],
                   help="SERIAL:FROM:TO: that board sends nothing for samples FROM..TO-1 (repeatable)")
    p.add_argument("--restart", action="append", type=int, default=[], metavar="SERIAL",
                   help="that board's sequence numbers start again at 0 after its first skip (a reboot)")
    p.add_argument("--bad", action="append", type=parse_bad, default=[], metavar="KIND:SERIAL:K",
                   help=f"at sample K that board also sends a hostile packet ({', '.join(BAD_KINDS[:-1])}; module: "
                        "its last module's packet claims module 200) (repeatable)")
    p.add_argument("--shift", action="append", type=parse_shift, default=[], metavar="SERIAL:K:SECONDS",
                   help="from sample K on, that board's time stamps are SECONDS later (an IRIG jump; negative: "
                        "back) (repeatable, cumulative)")
    p.add_argument("--wait", type=float, default=0.0, help="seconds to wait before sending")
    p.add_argument("--wait-listener", type=float, default=0.0, metavar="S",
                   help="first wait up to S seconds for a UDP socket on port 9876 here (a collector listening)")
    args = p.parse_args(argv)
    detectors = args.counts == "detector"
    if not detectors and (args.params_out or args.bias_args):
        p.error("--params-out and --bias-args are for --counts detector")
    n = max(1, round(args.duration * 1e9 / SAMPLE_NS))
    try:
        return _send(args, detector_boards(args.board, args.seed) if detectors else None, n)
    except (MntesError, OSError) as exc:
        print(f"sender: {exc}", file=sys.stderr)
        return 2


def _send(args, dets, n: int) -> int:
    if dets is not None and args.params_out:
        from mntes_stream.io.paramfile import dump_params

        dump_params([p for b in dets for p in b.params], args.params_out, metadata={
            "source": "python -m mntes_stream.dfmux.sender (truth)", "seed": str(args.seed),
            "boards": " ".join(f"{b.serial}:{b.modules}x{b.channels}" for b in dets)})
    if dets is not None and args.bias_args:
        print(" ".join(a for b in dets for a in b.bias_args()))
        return 0
    if args.duration <= 0:
        return 0
    time.sleep(args.wait)
    if args.wait_listener and not wait_listener(args.wait_listener):
        print(f"sender: nothing listens on UDP port {PORT} after {args.wait_listener:g} s", file=sys.stderr)
        return 1
    boards = [(PacketBuilder(b["version"], b["serial"], b["modules"], b["channels"]),
               multicast_socket(args.interface, b["source"])) for b in args.board]
    feed = _Feed(dets, n) if dets is not None else None
    t0_ns = args.start_ns or (time.time_ns() // SAMPLE_NS + 1) * SAMPLE_NS
    skips = {}
    for serial, k0, k1 in args.skip:
        skips.setdefault(serial, []).append((k0, k1))
    sent = {b.serial: 0 for b, _ in boards}
    packets = 0
    late_s = 0.0
    dest = (GROUP, PORT)
    t_wall0 = time.monotonic()
    for k in range(n):
        if not args.flat_out:
            delay = t_wall0 + k * SAMPLE_NS / 1e9 - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            late_s = max(late_s, -delay)
        for b, sock in boards:
            counts = feed.counts(b.serial, k) if feed is not None else None  # a skipped sample is simulated too
            spans = skips.get(b.serial, ())
            if any(k0 <= k < k1 for k0, k1 in spans):
                continue
            seq = k
            if b.serial in args.restart and spans and k >= spans[0][1]:
                seq = k - spans[0][1]
            shift_ns = sum(int(sec * 1e9) for serial, k0, sec in args.shift if serial == b.serial and k >= k0)
            raws = b.packets(k, t0_ns + k * SAMPLE_NS + shift_ns, seq, counts)
            for kind, serial, kb in args.bad:
                if serial == b.serial and kb == k:
                    raws, extra = bad_packets(kind, raws)
                    raws = raws + extra
            for raw in raws:
                sock.sendto(raw, dest)
                packets += 1
            sent[b.serial] += 1
    wall = time.monotonic() - t_wall0
    summary = {"t0_ns": t0_ns, "samples": n, "sent": sent, "packets": packets, "wall_s": round(wall, 3),
               "late_s": round(late_s, 4), "counts": args.counts}
    if dets is not None:
        summary["bias_v"] = {f"{b.serial}/{m}": float(v) for b in dets for m, v in enumerate(b.bias_v)}
    print(json.dumps(summary))
    return 0


if __name__ == "__main__":
    sys.exit(main())
