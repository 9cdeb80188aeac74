"""The ``dfmux-bridge`` service: IceBoard packets -> counts and housekeeping on zenoh, without SPT-3G's DAQ.

spt3g's own ``DfMuxCollector`` (UDP multicast on one interface, or SCTP to
named boards) parses the packets and its ``DfMuxBuilder`` collates them into
Timepoint frames; a thread pulls the frames (``builder.Process`` blocks, the
GIL released) and the service turns them into the simulator's messages
(:mod:`.assemble`): counts per (board serial, module), ``t_bath`` and
``b_field`` from constants. Each V3/V4 board's own housekeeping is read
over its tuber interface (:mod:`.boardhk`, a thread per board, off the
packet path): the bias of every channel as the G3 path derives it, its
tuning state and rails as readout flags, its mapped names; the configured
bias table is the fallback while a module has no board housekeeping.

spt3g runs here as the ``spt3g`` package (1.0.2), never so3g's bundled copy:
the bridge refuses to start in a process that has imported so3g, and says
which spt3g it uses in one line.

Stopping: ``DfMuxCollector.Stop()`` holds the GIL until one more datagram
arrives, so on UDP the bridge starts a small process that sends ignored
wake-up datagrams (a V2 packet of no channels, from no known board) until
Stop() returns.
"""

from __future__ import annotations

import logging
import queue
import subprocess
import sys
import threading
import time
from dataclasses import dataclass

import numpy as np

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError, import_extra
from mntes_stream.io import keys
from mntes_stream.io.transport import ZenohSettings
from mntes_stream.service.base import Service
from mntes_stream.service.metrics import MetricsSettings

__all__ = ["DfMuxBridgeSettings", "DfMuxBridgeConfig", "DfMuxBridgeService", "load_spt3g", "ledger_line",
           "bias_table"]

log = logging.getLogger("mntes_stream.dfmux")


@dataclass(frozen=True)
class DfMuxBridgeSettings(Settings):
    """Which boards, how packets arrive, what goes out (the ``[dfmux-bridge]`` table)."""

    setup: str = setting(keys.DEFAULT_SETUP, "keys mntes/<setup>/...", pattern=NAME_PATTERN)
    interface: str = setting("", "address of the interface the boards' UDP multicast (239.192.0.2:9876) arrives on")
    boards: tuple[int, ...] = setting((), "serials of the V3/V4 boards (every one must send: spt3g's builder "
                                      "collates a sample when all boards are in it)", ge=0)
    v2_boards: tuple[str, ...] = setting((), "V2 boards, which send no serial: IP=SERIAL each")
    sctp: tuple[str, ...] = setting((), "board host names to read by SCTP instead of UDP multicast")
    chunk_samples: int = setting(16, "samples per counts chunk per module (16 = 0.105 s)", ge=1)
    duration_s: float = setting(0.0, "stop after this long (0: until stopped)", unit="s", ge=0)
    t_bath_k: float | None = setting(None, "bath temperature to publish with every chunk (None: another source "
                                     "publishes t_bath, e.g. an OCS bridge)", unit="K", gt=0)
    b_field_t: float | None = setting(0.0, "magnetic field to publish with every chunk (None: another source does)",
                                      unit="T")
    bias: tuple[str, ...] = setting((), "bias table: BOARD/MODULE=VOLTS_RMS, BOARD/*=..., or *=... (first match "
                                    "wins); modules with no entry: no bias published (the converter's nominal bias)")
    bias_every_s: float = setting(60.0, "republish the bias this often (data time)", unit="s", gt=0)
    board_hk: bool = setting(True, "read each V3/V4 board's housekeeping (tuber Dfmux._dump_housekeeping, as "
                             "spt3g's HousekeepingConsumer): bias, gains, tuning state, rails, mapped names")
    board_hosts: tuple[str, ...] = setting((), "SERIAL=HOST[:PORT] per board whose tuber is not at "
                                           "iceboard<serial>.local:80 (labs without mDNS)")
    board_names: bool = setting(True, "the names the boards' hardware map stores are the detector ids of their "
                                "channels (counts, power, exports, monitor); fixed at each board's first housekeeping "
                                "read (the bridge receives packets once every board's first read is back or "
                                "names_wait_s passed); unnamed channels, and boards not read by then: "
                                "b<serial>m<module>c<channel>")
    names_wait_s: float = setting(10.0, "at the start, wait this long at most for every board's first housekeeping "
                                  "read (its names) before receiving packets", unit="s", ge=0)
    hk_every_s: float = setting(10.0, "read each board's housekeeping this often (spt3g's "
                                "PeriodicHousekeepingCollector: every 15200 samples, 100 s)", unit="s", gt=0)
    hk_timeout_s: float = setting(5.0, "a board's tuber reply must come within this (spt3g: 5 s)", unit="s", gt=0)
    hk_stale_s: float = setting(60.0, "a board's last good housekeeping holds this long; then its samples are "
                                "flagged HK_STALE until it answers again", unit="s", gt=0)
    params: str = setting("", "detector parameters (TOML, keyed by detector id or the boards' mapped names): the "
                          "boards' R_normal, R_frac achieved and loop gain are checked against them (10 %, 0.1, "
                          "50 %) and disagreements reported per detector")
    bias_tolerance: float = setting(0.02, "a configured bias differing from the board's by more than this "
                                    "(relative, median over the module) is a warning and a status field", ge=0)
    silent_s: float = setting(2.0, "a module (or board) without samples this long is reported silent", unit="s",
                              gt=0)
    wait_subscribers_s: float = setting(5.0, "wait this long for subscribers to the first keys", unit="s", ge=0)
    spt3g_log: str = setting("error", "spt3g's own lines shown at this level or above (the first 3 of each kind of "
                             "dropped packet; every drop is counted, whatever the level)",
                             choices=("debug", "info", "warn", "error", "fatal"))


@dataclass(frozen=True)
class DfMuxBridgeConfig(Settings):
    """A bridge config document: ``[dfmux-bridge]``, ``[metrics]``, ``[zenoh]``."""

    bridge: DfMuxBridgeSettings = setting(default_factory=DfMuxBridgeSettings, doc="boards and publication",
                                          flatten=True)
    metrics: MetricsSettings = setting(default_factory=MetricsSettings, doc="Prometheus endpoint ([metrics])")
    zenoh: ZenohSettings = setting(default_factory=ZenohSettings, doc="how to join zenoh ([zenoh])")

    @property
    def setup(self) -> str:
        return self.bridge.setup


def load_spt3g():
    """``(spt3g.core, spt3g.dfmux, "spt3g VERSION (PATH)")``: the spt3g package, never so3g's bundled copy."""
    if "so3g" in sys.modules:
        raise ConfigError("dfmux-bridge: so3g is loaded in this process (its bundled spt3g is too old for the "
                          "collector): run the bridge in its own process")
    core = import_extra("spt3g.core", "g3")
    dfmux = import_extra("spt3g.dfmux", "g3")
    import spt3g

    version = str(getattr(spt3g, "__version__", "?"))
    if not version.startswith("1."):
        raise ConfigError(f"dfmux-bridge: spt3g {version} at {spt3g.__file__}: needs spt3g 1.x (1.0.2 tested)")
    return core, dfmux, f"spt3g {version} ({spt3g.__file__.rsplit('/', 2)[0]})"


def bias_table(entries) -> list[tuple[int | None, int | None, float]]:
    """``BOARD/MODULE=V`` entries -> ``[(board or None, module or None, volts)]``; ConfigError on a bad one."""
    out = []
    for item in entries:
        where, _, value = item.partition("=")
        board, _, module = where.strip().partition("/")
        try:
            b = None if board in ("*", "") else int(board)
            m = None if module in ("*", "") else int(module)
            v = float(value)
        except ValueError:
            raise ConfigError(f"dfmux-bridge: bias entry {item!r}: expected BOARD/MODULE=VOLTS (* for any)") from None
        if not np.isfinite(v) or v < 0:
            raise ConfigError(f"dfmux-bridge: bias entry {item!r}: volts must be finite and >= 0")
        out.append((b, m, v))
    return out


def _v2_map(entries) -> dict[str, int]:
    out = {}
    for item in entries:
        ip, _, serial = item.partition("=")
        try:
            import socket

            socket.inet_aton(ip.strip())
            out[ip.strip()] = int(serial)
        except (OSError, ValueError):
            raise ConfigError(f"dfmux-bridge: V2 board {item!r}: expected IP=SERIAL, e.g. 192.168.1.62=62") from None
    return out


def _check_interface(addr: str) -> None:
    """A one-line error now if the group cannot be joined on ``addr`` (spt3g only prints it and hears nothing)."""
    import socket

    from mntes_stream.dfmux.packets import GROUP

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        s.setsockopt(socket.IPPROTO_IP, socket.IP_ADD_MEMBERSHIP, socket.inet_aton(GROUP) + socket.inet_aton(addr))
    except OSError as exc:
        raise ConfigError(f"dfmux-bridge: cannot join {GROUP} on interface {addr}: {exc.strerror or exc}") from None
    finally:
        s.close()


def _check_sctp(hosts) -> None:
    """A one-line error now if this kernel has no SCTP or a board's name does not resolve."""
    import socket

    try:
        socket.socket(socket.AF_INET, socket.SOCK_SEQPACKET, socket.IPPROTO_SCTP).close()
    except OSError as exc:
        raise ConfigError(f"dfmux-bridge: SCTP is not available here ({exc.strerror or exc}): load the kernel's "
                          "sctp module, or take the boards' UDP multicast with --interface") from None
    for host in hosts:
        try:
            socket.getaddrinfo(host, 9876, socket.AF_INET)
        except OSError as exc:
            raise ConfigError(f"dfmux-bridge: board {host!r}: {exc.strerror or exc}") from None


_WAKE = """import socket, sys, time
s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(sys.argv[1]))
s.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
pk = (0x666d7578).to_bytes(4, "little") + (2).to_bytes(2, "little") + bytes(42)  # V2, no channels: ignored
for _ in range(200):
    s.sendto(pk, ("239.192.0.2", 9876)); time.sleep(0.02)
"""


class Readout:
    """spt3g's collector(s) and builder, and a thread pulling the builder's Timepoint frames into a queue.

    Built (and checked) first; :meth:`start` binds the sockets and starts listening at once, so nothing
    waits in a socket buffer meanwhile.
    """

    def __init__(self, b: DfMuxBridgeSettings):
        self.b = b
        self.interface = b.interface
        self.sctp = bool(b.sctp)
        self.v2 = _v2_map(b.v2_boards)
        self.serials = list(b.boards) + list(self.v2.values())
        if not self.serials:
            raise ConfigError("dfmux-bridge: name the boards (--board SERIAL, or --v2-board IP=SERIAL)")
        if len(set(self.serials)) != len(self.serials):
            raise ConfigError(f"dfmux-bridge: a board serial is named twice: {self.serials}")
        if not b.sctp and not b.interface:
            raise ConfigError("dfmux-bridge: give --interface ADDR (UDP multicast) or --sctp HOST")
        if b.sctp and self.v2:
            raise ConfigError("dfmux-bridge: V2 boards send UDP only; use --interface for them, not --sctp")
        if b.sctp:
            _check_sctp(b.sctp)
        else:
            _check_interface(b.interface)
        self._core = self._dfmux = None
        self.builder = None
        self._waker = None
        self.collectors = []
        self.frames: queue.Queue = queue.Queue()
        self._thread = threading.Thread(target=self._pull, name="dfmux-builder", daemon=True)

    def start(self, core, dfmux) -> None:
        self._core, self._dfmux, b = core, dfmux, self.b
        self.builder = dfmux.DfMuxBuilder(core.IntVector(self.serials))
        try:
            if b.sctp:
                self.collectors.append(dfmux.DfMuxCollector(self.builder, core.StringVector(list(b.sctp))))
            else:
                if b.boards:
                    self.collectors.append(dfmux.DfMuxCollector(b.interface, self.builder,
                                                                core.IntVector(list(b.boards))))
                if self.v2:  # a second listener: each ignores the other's boards
                    self.collectors.append(dfmux.DfMuxCollector(b.interface, self.builder, self.v2))
        except RuntimeError as exc:  # spt3g's log_fatal: e.g. an SCTP board that does not answer
            raise ConfigError(f"dfmux-bridge: {str(exc).strip().splitlines()[-1]}") from None
        for c in self.collectors:
            c.Start()
        self._thread.start()

    def _pull(self) -> None:
        # Process() waits for the next frames with the GIL released; it never returns without one, so this
        # thread is a daemon and is left waiting when the bridge stops.
        frame = self._core.G3Frame()
        while True:
            for f in self.builder.Process(frame):
                self.frames.put(f)

    def release(self) -> bool:
        """Push out what the builder holds: packets stamped from ``MARKER_NS`` on (False: cannot, V2 only or
        SCTP). The builder waits for 1000 later samples before it gives up on an incomplete one."""
        if self.sctp or not self.b.boards:
            return False
        import socket

        from mntes_stream.dfmux.packets import GROUP, PORT, marker_packets

        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_IF, socket.inet_aton(self.interface))
            sock.setsockopt(socket.IPPROTO_IP, socket.IP_MULTICAST_TTL, 0)
            for k, raw in enumerate(marker_packets(self.b.boards[0], 2200)):
                sock.sendto(raw, (GROUP, PORT))
                if k % 100 == 99:
                    time.sleep(0.002)  # the socket buffer holds a few hundred: let the collector read
        except OSError as exc:
            log.warning("dfmux-bridge: cannot release the builder's held samples: %s", exc)
            return False
        finally:
            sock.close()
        return True

    def start_waker(self) -> None:
        """Start the process whose datagrams let ``Stop()`` return (early: its start overlaps the last work)."""
        if self.interface and not self.sctp and self._waker is None:  # SCTP boards that stream wake it themselves
            self._waker = subprocess.Popen([sys.executable, "-c", _WAKE, self.interface], stdin=subprocess.DEVNULL,
                                           stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)

    def stop(self) -> None:
        if self.collectors:
            self.start_waker()
        try:
            for c in self.collectors:
                c.Stop()
        finally:
            if self._waker is not None:
                self._waker.kill()
                self._waker.wait()
                self._waker = None


def unpack(frame) -> tuple[int, list, list]:
    """A Timepoint frame -> ``(t_ns, [(board, module, block, nblocks, iq int32), ...], [board, ...])``: the last
    list names a board once for each module packet refused, its module beyond the board's modules (spt3g's
    builder takes any module number a packet claims)."""
    t_ns = int(frame["EventHeader"].time) * 10
    out = []
    refused = []
    meta = frame["DfMux"]
    for board, bs in meta.items():
        nb = int(bs.nblocks) or 1
        nmod = int(bs.nmodules)
        for idx, sample in bs.items():
            if idx // nb >= nmod:
                refused.append(int(board))
                continue
            out.append((int(board), idx // nb, idx % nb, nb, np.asarray(sample)))
    return t_ns, out, refused


class DfMuxBridgeService(Service):
    """IceBoard packets (spt3g's DfMuxCollector + DfMuxBuilder) -> counts and housekeeping messages on zenoh."""

    name = "dfmux-bridge"
    Config = DfMuxBridgeConfig
    summary = "IceBoard packets (UDP multicast or SCTP, no DAQ) published as counts + housekeeping"

    def owns(self) -> dict:
        b = self.config.bridge
        return {"boards": list(b.boards) + list(b.v2_boards), "interface": b.interface or None,
                "sctp": list(b.sctp)}

    def duration_s(self) -> float:
        return self.config.bridge.duration_s

    def history_chunks(self) -> int:
        from mntes_stream.io.history import cache_chunks

        return cache_chunks(self.config.zenoh.history_seconds, self.config.bridge.chunk_samples * 6.5536e-3)

    def setup(self, ctx) -> None:
        from mntes_stream.dfmux.assemble import Assembler
        from mntes_stream.dfmux.publish import HkPublisher

        b = self.config.bridge
        from mntes_stream.dfmux.boardhk import BoardHkTracker, BoardPoller, parse_hosts

        self._hk = HkPublisher(b.setup, b.t_bath_k, b.b_field_t, bias_table(b.bias), b.bias_every_s)
        self._asm = Assembler(b.setup, b.chunk_samples, hold_gaps=True)  # spt3g's sequence numbers tell them
        self._readout = Readout(b)  # every setting checked before spt3g is loaded
        hosts = parse_hosts(b.board_hosts)
        unknown = sorted(set(hosts) - set(b.boards))
        if unknown:
            raise ConfigError(f"dfmux-bridge: --board-host for board(s) {unknown}, not named by --board")
        params = None
        if b.params:
            from mntes_stream.io.paramfile import load_params

            params = load_params(b.params)
        self._tracker = BoardHkTracker(self._hk, b.hk_stale_s, b.bias_tolerance, params)
        self._pollers = [BoardPoller(s, *hosts.get(s, (None, 80)), every_s=b.hk_every_s, timeout_s=b.hk_timeout_s)
                         for s in (b.boards if b.board_hk else ())]
        self._said_hk = 0
        core, dfmux, which = load_spt3g()
        log.info("dfmux-bridge: %s", which)
        self.spt3g = which
        from mntes_stream.dfmux.spt3glog import Spt3gLog

        self._log = Spt3gLog(core, b.spt3g_log)
        self._held_gaps = 0
        self._said_back = 0
        self._said = 0
        self.released = None
        self._t_beat = 0.0
        self._waited = False
        self._marker_seen = False
        for poller in self._pollers:
            poller.start()
        self._first_hk = self._first_reads(b) if b.board_names and self._pollers else []
        self._log.start()
        try:
            self._readout.start(core, dfmux)
        except BaseException:
            self._log.stop()
            raise

    def _first_reads(self, b) -> list:
        """Every board's first housekeeping read (or ``names_wait_s``), before any packet is received: the names
        it stores are its channels' detector ids for the run, so no stream ever mixes ids. Returns the messages
        of those reads (published with the first counts)."""
        t_end = time.monotonic() + b.names_wait_s
        for poller in self._pollers:
            poller.first_done.wait(max(0.0, t_end - time.monotonic()))
        out = self._board_hk()
        self._asm.names = self._tracker.freeze_names([p.serial for p in self._pollers])
        return out

    def _board_hk(self) -> list:
        """Messages from the boards' housekeeping read since the last call (never waits for a board); stamped
        no earlier than just after the newest sample received (its chunk goes out after them)."""
        out = []
        floor = self._asm.t_newest_ns or 0
        for poller in self._pollers:
            while True:
                try:
                    out += self._tracker.add(poller.results.get_nowait(), floor)
                except queue.Empty:
                    break
        return out + self._tracker.check_stale(floor)

    def step(self, ctx) -> bool:
        self._waited = self._step(self._readout, self._asm, self._hk, ctx.publishers, ctx.stop, self._waited)
        if time.monotonic() - self._t_beat > 0.5:
            self._t_beat = time.monotonic()
            self._asm.check_silent(self.config.bridge.silent_s)
            self._beat(self._asm, self._readout, ctx.publishers)
        return True

    def finish(self, ctx) -> dict:
        b, readout, asm, hk, pubs = self.config.bridge, self._readout, self._asm, self._hk, ctx.publishers
        try:
            # What the builder still holds comes out before the marker packets; then the last chunks.
            self._log.ignore_v2_unknown()
            readout.start_waker()
            self.released = readout.release()
            t_end = time.monotonic() + 3.0
            while self.released and not self._marker_seen and time.monotonic() < t_end:
                self._waited = self._step(readout, asm, hk, pubs, ctx.stop, self._waited)
            if self.released and not self._marker_seen:
                self.released = False
            while not readout.frames.empty():  # only the marker packets' own frames are left
                readout.frames.get_nowait()
            asm.check_silent(b.silent_s)
            chunks = asm.flush(time.time_ns())
            for key, payload in hk.messages(chunks, asm.t_newest_ns) + [
                    (keys.counts_key(b.setup, c.board, c.module), c.to_bytes()) for c in chunks]:
                pubs.put(key, payload)
        finally:
            readout.stop()
            for poller in self._pollers:
                poller.stop()
            self._log.stop()  # the collectors are stopped: every line they wrote is read
        asm.resolve_gaps(self._log.take_seq_events())
        result = self._beat(asm, readout, pubs)
        log.info("dfmux-bridge stopped: %s", result)
        return result

    def _step(self, readout, asm, hk, pubs, stopping, waited: bool) -> bool:
        """Frames that have come (up to 512; waits 0.1 s for one) -> published messages."""
        from mntes_stream.dfmux.packets import MARKER_NS

        b = self.config.bridge
        try:
            frames = [readout.frames.get(timeout=0.1)]
        except queue.Empty:
            frames = []
        while len(frames) < 512:
            try:
                frames.append(readout.frames.get_nowait())
            except queue.Empty:
                break
        chunks = []
        for f in frames:
            if "DfMux" not in f or "EventHeader" not in f:
                continue
            t_ns, mods, refused = unpack(f)
            if t_ns >= MARKER_NS:  # the bridge's own stop packets
                self._marker_seen = True
                continue
            for board in refused:
                asm.reject(board, "module out of range")
            chunks += asm.add(t_ns, mods, time.time_ns())
        first, self._first_hk = self._first_hk, []
        out = first + self._board_hk() + hk.messages(chunks, asm.t_newest_ns) + [
            (keys.counts_key(b.setup, c.board, c.module), c.to_bytes()) for c in chunks]
        if out and not waited and b.wait_subscribers_s > 0:
            waited = True
            pubs.wait_matching([k for k, _ in out], b.wait_subscribers_s, stopping)
        for key, payload in out:
            pubs.put(key, payload)
        return waited

    def _beat(self, asm, readout, pubs) -> dict:
        from mntes_stream.core.ledger import Ledger

        # gaps held since the last beat (>= 0.5 s ago): their sequence events are read by now
        asm.resolve_gaps(self._log.take_seq_events(), self._held_gaps)
        self._held_gaps = len(asm.pending_gaps)
        for board, back_s in self._log.steps_back[self._said_back:]:
            asm.step_back(board, back_s)
        self._said_back = len(self._log.steps_back)
        led = Ledger("published")
        for stream, n in asm.published.items():
            led.received(stream, n)
            led.done(stream, n)
        for stream, n in asm.stream_gaps.items():
            led.set_missing(stream, -(-int(n) // self.config.bridge.chunk_samples))
        for ev in asm.events[self._said:]:  # each board event once, on the status and the log
            self.heartbeat.warn(ev.text)
            log.warning("dfmux-bridge: %s", ev.text)
        self._said = len(asm.events)
        tracker = self._tracker
        for text in tracker.events[self._said_hk:]:
            self.heartbeat.warn(text)
            log.warning("dfmux-bridge: %s", text)
        self._said_hk = len(tracker.events)
        counters = {"spt3g": self.spt3g, "timepoints": asm.timepoints, "samples": asm.samples,
                    "invalid_samples": asm.invalid_samples, "out_of_order": asm.out_of_order,
                    "gap_samples": asm.gap_samples, "jump_samples": asm.jump_samples,
                    "time_jumps": asm.time_jumps[-20:], "time_jumps_total": len(asm.time_jumps),
                    "dropped_packets": {**self._log.counts(), **asm.rejected},
                    "streams": len(asm.streams), "queued_frames": readout.frames.qsize(),
                    "held_released": self.released,
                    "messages": pubs.messages, "bytes": pubs.bytes,
                    "events": ([e.text for e in asm.events] + tracker.events)[-20:],
                    "events_total": len(asm.events) + len(tracker.events),
                    **tracker.status(),
                    "published": dict(sorted(asm.published.items())), "stream_gaps": asm.stream_gaps,
                    "ledger": led.as_dict(), "lost": led.lost}
        self.heartbeat.beat(**counters)
        return counters


def ledger_line(result: dict) -> str:
    """The bridge's last line: chunks published, never received, lost; samples never received; board events."""
    from mntes_stream.core.ledger import Ledger

    led = Ledger.from_dict(result.get("ledger", {}), "published")
    text = f"dfmux-bridge done: {led.line()}; {result.get('gap_samples', 0)} module samples never received"
    if result.get("out_of_order"):
        text += f"; {result['out_of_order']} module samples dropped (not after their stream's last one)"
    dropped = result.get("dropped_packets") or {}
    if dropped:
        text += (f"; {sum(dropped.values())} packets dropped (" +
                 ", ".join(f"{k} {v}" for k, v in sorted(dropped.items())) + ")")
    if result.get("time_jumps_total"):
        jumps = result.get("time_jumps") or []
        sizes = ", ".join(f"board {j['board']} {j['forward_s']:+.3f} s" for j in jumps[:4])
        text += (f"; {result['time_jumps_total']} time stamp jumps ({sizes}{' ...' if len(jumps) > 4 else ''}; "
                 f"{result.get('jump_samples', 0)} module samples jumped over, not lost)")
    if result.get("invalid_samples"):
        text += f"; {result['invalid_samples']} samples invalid (V4 blocks missing)"
    if result.get("held_released") is False:
        text += "; samples spt3g's builder still held at the stop (up to 1000 per board) were not released"
    if result.get("board_hk_reads"):
        text += (f"; board housekeeping read {result['board_hk_reads']} times, the bias of "
                 f"{len(result.get('bias_from_board', ()))} modules from the boards")
        if result.get("bias_disagree"):
            text += f" ({len(result['bias_disagree'])} disagreeing with the configured bias)"
    if result.get("detector_names"):
        text += f"; {result['detector_names']} channels named by the boards (their detector ids)"
    if result.get("board_hk_failures"):
        text += f"; {result['board_hk_failures']} board housekeeping reads failed"
    if result.get("events_total"):
        text += f"; {result['events_total']} board events (gaps, late, silent, housekeeping: see the log)"
    return text
