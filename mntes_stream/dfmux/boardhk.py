"""The boards' own housekeeping for ``dfmux-bridge``: bias, gains, tuning state, rails and names, read over tuber.

As spt3g's ``HousekeepingConsumer`` does (triggered there by a
``PeriodicHousekeepingCollector``): a ``Dfmux._dump_housekeeping`` call to
``iceboard<serial>.local`` port 80 with spt3g's ``TuberClient``, the reply
parsed by spt3g's ``HousekeepingFromJSON`` (an ``HkBoardInfo`` in a
``DfMuxHousekeepingMap``) and ``WiringFromJSON`` (the mapped channel names:
the lab's hardware map stored on the board). From those, the G3 path's own
code (:mod:`mntes_stream.g3.mapping`: ``Wiring``, ``hk_snapshot``, which
calls spt3g's ``bolo_bias_voltage_rms`` and ``counts_to_rms_amps``) gives
each channel's bias (RMS Thevenin volts) and amps per count.

One :class:`BoardPoller` thread per board reads at a fixed cadence and
hands :class:`BoardReading` or :class:`BoardFailure` to the bridge through a
queue: the packet path never waits for a board. :class:`BoardHkTracker`
turns them into housekeeping messages: ``bias/<board>/<module>`` when it
changes (the old value 1 ns before the new one, as the G3 path publishes a
step) and every ``bias_every_s``, and ``readout_flags/<board>/<module>``
(UNTUNED, RAILED, HK_STALE per channel) when they change; each change
stamped at the board's time stamp, or just after the newest sample already
published if that is later; events, and the status fields of the bridge.
"""

from __future__ import annotations

import json
import logging
import queue
import socket
import threading
import time
from dataclasses import dataclass, field

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core.ids import detector_id

__all__ = ["BoardPoller", "BoardReading", "BoardFailure", "ModuleReading", "BoardHkTracker", "read_board",
           "read_once", "reading_from_dump", "board_params", "parse_hosts", "channel_flags", "TUNED_STATES"]

log = logging.getLogger("mntes_stream.dfmux")

# The tuning states that are an operating point (spt3g's HkChannelInfo.state; "" = the board says nothing).
TUNED_STATES = frozenset({"tuned", ""})
# The board's tuning results against the detector parameters' (model.describe at the nominal operating point):
# beyond these, a disagreement reported per detector. R_normal relative; R_frac achieved absolute; loop gain
# relative (it moves with the optical load, so only a gross mismatch is said).
TUNING_TOLERANCES = {"r_normal_ohm": ("relative", 0.10), "r_frac": ("absolute", 0.10), "loop_gain": ("relative", 0.5)}


def parse_hosts(entries) -> dict[int, tuple[str, int]]:
    """``SERIAL=HOST[:PORT]`` entries -> {serial: (host, port)}; ConfigError on a bad one."""
    from mntes_stream.errors import ConfigError

    out = {}
    for item in entries:
        serial, _, where = str(item).partition("=")
        host, _, port = where.strip().rpartition(":") if ":" in where else (where.strip(), "", "")
        try:
            s = int(serial)
            p = int(port) if port else 80
            if not host or not 0 < p < 65536:
                raise ValueError
        except ValueError:
            raise ConfigError(f"dfmux-bridge: board host {item!r}: expected SERIAL=HOST[:PORT], e.g. "
                              "10=192.168.1.10 or 10=127.0.0.1:8080") from None
        out[s] = (host, p)
    return out


def _tuber_client():
    """spt3g's ``TuberClient``, with a port, a timeout on connect too, and an error where the board closes the
    connection mid-reply (spt3g's reads one byte at a time and would loop for ever on the closed socket)."""
    from spt3g.dfmux.TuberClient import TuberClient

    class Tuber(TuberClient):
        def __init__(self, host: str, port: int, timeout: float):
            super().__init__(host, timeout=timeout)
            self.port = port

        def OpenSocket(self):  # noqa: N802 - spt3g's name
            self.socket = socket.create_connection((self.host, self.port), timeout=self.timeout)

        def ReadLineFromSocket(self):  # noqa: N802
            out = b""
            while not out.endswith(b"\n"):
                byte = self.socket.recv(1)
                if not byte:
                    raise ConnectionError("the board closed the connection mid-reply")
                out += byte
            return out.decode(errors="replace")

    return Tuber


@dataclass(frozen=True)
class ModuleReading:
    """One module's channels as its board reports them.

    Attributes
    ----------
    channels : ndarray of int32, shape (n_ch,)
        0-indexed channels (those the board's housekeeping lists).
    names : tuple of str, length n_ch
        The board's mapped name of each channel, or its detector id where the board stores none.
    bias_v, amps_rms_per_count : ndarray of float64, shape (n_ch,)
        spt3g's ``bolo_bias_voltage_rms`` and ``counts_to_rms_amps``.
    flags : ndarray of uint16, shape (n_ch,)
        UNTUNED and RAILED (:func:`channel_flags`).
    states : tuple of str
        The board's tuning state of each channel.
    r_normal_ohm, r_frac, loop_gain : ndarray of float64, shape (n_ch,)
        The board's tuning results (NaN where it has none).
    gains : dict
        ``{"carrier": int, "nuller": int}``, the module's gain settings.
    """

    channels: np.ndarray
    names: tuple
    bias_v: np.ndarray
    amps_rms_per_count: np.ndarray
    flags: np.ndarray
    states: tuple
    r_normal_ohm: np.ndarray
    r_frac: np.ndarray
    loop_gain: np.ndarray
    gains: dict


@dataclass(frozen=True)
class BoardReading:
    """One good ``_dump_housekeeping`` reply: board time stamp (ns), modules by 0-indexed number."""

    serial: int
    t_ns: int
    modules: dict
    named_channels: int
    t_wall: float = field(default_factory=time.monotonic)
    wiring: object = field(default=None, repr=False)  # g3.mapping.Wiring: the board's names both ways
    snap: object = field(default=None, repr=False)    # g3.mapping.HkSnapshot of this reply


@dataclass(frozen=True)
class BoardFailure:
    """A board that did not answer usefully (``text``: why, one line)."""

    serial: int
    text: str
    t_wall: float = field(default_factory=time.monotonic)


def channel_flags(chan, mod) -> int:
    """UNTUNED (a tuning state other than tuned) and RAILED (DAN railed, or the module's carrier, nuller or
    demodulator overloaded) of one spt3g ``HkChannelInfo`` in its ``HkModuleInfo``."""
    bits = 0
    if str(chan.state).strip().lower() not in TUNED_STATES:
        bits |= fl.UNTUNED
    if chan.dan_railed or mod.carrier_railed or mod.nuller_railed or mod.demod_railed:
        bits |= fl.RAILED
    return bits


def read_board(client, serial: int, ip: str, previous=None) -> tuple[BoardReading, object]:
    """One ``_dump_housekeeping`` call and its reading (and the snapshot, to pass as ``previous`` next time).

    Raises on anything but a good reply (the caller says which board and why).
    """
    reply = client.CallMethod("Dfmux", "_dump_housekeeping")
    if not isinstance(reply, list) or not reply or not isinstance(reply[0], dict) or "result" not in reply[0]:
        raise ValueError(f"not a tuber result: {str(reply)[:80]}")
    return reading_from_dump(reply[0]["result"], serial, ip, previous)


def reading_from_dump(dat: dict, serial: int, ip: str, previous=None) -> tuple[BoardReading, object]:
    """A ``_dump_housekeeping`` result (JSON as the board sends it) -> its reading and snapshot, through
    spt3g's ``HousekeepingFromJSON``/``WiringFromJSON`` and the G3 path's ``hk_snapshot``."""
    from mntes_stream.g3 import spt3g
    from mntes_stream.g3.mapping import Wiring, hk_snapshot

    core, dfmux = spt3g()
    from spt3g.dfmux.Housekeeping import HousekeepingConsumer, HousekeepingForBolo

    boardhk = HousekeepingConsumer.HousekeepingFromJSON(dat)
    if int(boardhk.serial) != serial:
        raise ValueError(f"it answers as board {boardhk.serial}")
    ip_int = int.from_bytes(socket.inet_aton(ip), "little", signed=True)  # as spt3g packs it ("i")
    named = any((ch.get("tuning") or {}).get("name") for mz in dat["mezzanines"] for md in mz["modules"]
                for ch in md["channels"])
    # spt3g's own map of the names stored on the board (it logs an error for a board without any: not asked)
    wm = HousekeepingConsumer.WiringFromJSON(dat, ip_int, -1, -1) if named else dfmux.DfMuxWiringMap()
    n_named = len(wm.keys())
    taken = {(int(m.module), int(m.channel)) for m in wm.values()}
    n_mod = len(boardhk.mezz[1].modules) if 1 in boardhk.mezz else 0
    for z, mezz in boardhk.mezz.items():
        for j, mod in mezz.modules.items():
            module = (j - 1) + n_mod * (z - 1)
            for c in mod.channels.keys():
                if (module, c - 1) in taken:
                    continue
                m = dfmux.DfMuxChannelMapping()
                m.board_ip, m.board_serial, m.board_slot, m.crate_serial = ip_int, serial, -1, -1
                m.module, m.channel = module, c - 1
                wm[detector_id(serial, module, c - 1)] = m  # unnamed: its detector id, as the G3 path names it
    wiring = Wiring.from_map(wm, "ICE", "spt3g_filtering_2017_full")
    hkmap = dfmux.DfMuxHousekeepingMap()
    hkmap[serial] = boardhk
    snap = hk_snapshot(hkmap, wiring, time.time_ns(), previous)
    modules = {}
    for (_, m), rows in wiring.modules().items():
        hk = [HousekeepingForBolo(hkmap, wiring.wiring_map, wiring.names[r], True) for r in rows]
        mod = hk[0][2]
        modules[int(m)] = ModuleReading(
            channels=wiring.channel[rows].astype(np.int32), names=tuple(wiring.names[r] for r in rows),
            bias_v=snap.v_bias_rms_v[rows].copy(), amps_rms_per_count=snap.amps_rms_per_count[rows].copy(),
            flags=np.array([channel_flags(h[3], h[2]) for h in hk], dtype=fl.FLAG_DTYPE),
            states=tuple(str(h[3].state) for h in hk),
            r_normal_ohm=np.array([h[3].rnormal / core.G3Units.ohm for h in hk]),
            r_frac=np.array([h[3].rfrac_achieved for h in hk]), loop_gain=np.array([h[3].loopgain for h in hk]),
            gains={"carrier": int(mod.carrier_gain), "nuller": int(mod.nuller_gain)})
    return BoardReading(serial, snap.t_ns, modules, n_named, wiring=wiring, snap=snap), snap


def read_once(serial: int, host: str | None = None, port: int = 80, timeout_s: float = 5.0) -> BoardReading:
    """One board's housekeeping now (ConfigError naming the board if it cannot be read)."""
    from mntes_stream.errors import ConfigError

    where = f"{host or f'iceboard{serial:04d}.local'}:{port}"
    try:
        ip = socket.gethostbyname(host or f"iceboard{serial:04d}.local")
        return read_board(_tuber_client()(ip, port, timeout_s), serial, ip)[0]
    except Exception as exc:  # noqa: BLE001 - one line naming the board
        raise ConfigError(f"board {serial}: housekeeping from {where} not read: {_why(exc)}") from None


def board_params(params: dict, readings) -> tuple[dict, list[str]]:
    """Detector parameters keyed by detector id for the boards' channels, from ``params`` keyed by the boards'
    mapped names (or by detector id), each gain the board's amps per count (the G3 path's
    ``params_for_wiring``); and the names without parameters."""
    from mntes_stream.g3.mapping import params_for_wiring

    out, missing = {}, []
    for r in readings:
        got, miss = params_for_wiring(params, r.wiring, r.snap)
        out.update(got)
        missing += miss
    return out, missing


def _why(exc: BaseException) -> str:
    """One line: why a board's housekeeping could not be read."""
    if isinstance(exc, socket.timeout):
        return "tuber timed out"
    if isinstance(exc, socket.gaierror):
        return f"name does not resolve ({exc.strerror or exc})"
    if isinstance(exc, ConnectionRefusedError):
        return "connection refused"
    if isinstance(exc, OSError):
        return f"{exc.strerror or exc}"
    if isinstance(exc, (json.JSONDecodeError, AssertionError, KeyError, TypeError, IndexError, ValueError)):
        return f"answered garbage ({type(exc).__name__}: {str(exc)[:80]})"
    return f"{type(exc).__name__}: {str(exc)[:80]}"


class BoardPoller:
    """A thread reading one board's housekeeping every ``every_s``; results in :attr:`results` (a queue).

    Parameters
    ----------
    serial : int
    host : str, optional
        Name or address (default ``iceboard<serial>.local``, as spt3g), resolved at every attempt.
    port : int
    every_s, timeout_s : float
        Cadence (from the start of one attempt to the next) and tuber timeout.
    """

    def __init__(self, serial: int, host: str | None = None, port: int = 80, every_s: float = 10.0,
                 timeout_s: float = 5.0):
        self.serial = int(serial)
        self.host = host or f"iceboard{self.serial:04d}.local"
        self.port = int(port)
        self.every_s, self.timeout_s = float(every_s), float(timeout_s)
        self.results: queue.Queue = queue.Queue()
        self.first_done = threading.Event()  # the first attempt is in results (a reading or a failure)
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name=f"dfmux-hk-{self.serial}", daemon=True)

    @property
    def where(self) -> str:
        return f"{self.host}:{self.port}"

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()

    def _run(self) -> None:
        Tuber = _tuber_client()
        previous = None
        while not self._stop.is_set():
            t0 = time.monotonic()
            try:
                ip = socket.gethostbyname(self.host)
                reading, previous = read_board(Tuber(ip, self.port, self.timeout_s), self.serial, ip, previous)
                self.results.put(reading)
            except Exception as exc:  # noqa: BLE001 - any failure of one board is one line, never the bridge's
                self.results.put(BoardFailure(self.serial, f"housekeeping from {self.where} not read: {_why(exc)}"))
            self.first_done.set()
            self._stop.wait(max(0.0, t0 + self.every_s - time.monotonic()))


class BoardHkTracker:
    """Board readings -> housekeeping messages, events and status for the bridge.

    Parameters
    ----------
    publisher : HkPublisher
        Makes the messages (its sequence numbers); learns which modules have the board's bias.
    stale_s : float
        A board's last good housekeeping holds this long (wall time) after it; then its modules' samples
        are flagged HK_STALE from that data time on, until it answers again.
    bias_tolerance : float
        Relative difference between a configured bias and the board's beyond which the bridge warns.
    params : dict, optional
        Detector parameters keyed by detector id or the boards' mapped names: the board's R_normal, R_frac
        achieved and loop gain are checked against them (``TUNING_TOLERANCES``).
    """

    def __init__(self, publisher, stale_s: float = 60.0, bias_tolerance: float = 0.02, params=None):
        self.pub = publisher
        self.stale_s = float(stale_s)
        self.bias_tolerance = float(bias_tolerance)
        self.boards: dict[int, dict] = {}
        self.modules: dict[tuple[int, int], ModuleReading] = {}
        self._flags_sent: dict[tuple[int, int], np.ndarray] = {}
        self._t_bias_sent: dict[tuple[int, int], int] = {}
        self.events: list[str] = []
        self.changes: list[str] = []
        self.bias_disagree: dict[str, dict] = {}
        self.names: dict[str, str] = {}  # detector id -> the board's mapped name
        self.frozen: dict[tuple[int, int], dict[int, str]] | None = None  # the ids of the run (freeze_names)
        self._names_said: set[int] = set()
        self.tuning_disagree: dict[str, dict] = {}
        self._expected = {key: _expected_tuning(p) for key, p in (params or {}).items()}

    def _board(self, serial: int) -> dict:
        return self.boards.setdefault(serial, {"reads": 0, "failures": 0, "last_error": None, "stale": False,
                                               "failing": False, "t_ns": None, "t_wall": None,
                                               "named_channels": 0, "gains": {}})

    def add(self, item, t_floor_ns: int = 0) -> list[tuple[str, bytes]]:
        """One reading or failure -> messages to publish now.

        ``t_floor_ns``: the newest sample time already published. A change is stamped at the board's time
        stamp or just after that sample, whichever is later: counts already published are converted with
        what was in force, and the recorded readings say exactly what each sample was converted with."""
        st = self._board(item.serial)
        if isinstance(item, BoardFailure):
            st["failures"] += 1
            st["last_error"] = item.text
            if not st["failing"]:  # one line per outage, the count in the status
                st["failing"] = True
                held = "" if st["t_wall"] is None else \
                    f"; the last good housekeeping holds for {self.stale_s:g} s, then its samples are flagged HK_STALE"
                self.events.append(f"board {item.serial}: {item.text}{held}")
            return []
        out = []
        t_ns = max(int(item.t_ns), int(t_floor_ns) + 1)
        if st["failing"]:
            self.events.append(f"board {item.serial}: housekeeping read again after {st['failures']} failure(s)")
        st.update(reads=st["reads"] + 1, failing=False, stale=False, t_ns=item.t_ns, t_wall=item.t_wall,
                  named_channels=item.named_channels)
        for m, mr in sorted(item.modules.items()):
            key = (item.serial, m)
            before = self.modules.get(key)
            self.modules[key] = mr
            for c, name in zip(mr.channels.tolist(), mr.names):
                det = detector_id(item.serial, m, c)
                if name != det:
                    self.names[det] = name
            if self.frozen is not None and item.serial not in self._names_said and \
                    _named(item.serial, m, mr) != self.frozen.get(key, {}):
                self._names_said.add(item.serial)
                self.events.append(f"board {item.serial}: its channel names differ from those of the start (module "
                                   f"{m}): the detector ids stay those of the start until the bridge restarts")
            if before is not None and before.gains != mr.gains:
                self._change(f"board {item.serial} module {m}: gains {before.gains} -> {mr.gains} at "
                             f"{t_ns} ns")
            st["gains"][str(m)] = mr.gains  # str keys: the status goes out as msgpack (ps), JSON
            out += self._bias(item.serial, m, t_ns, before, mr)
            if self._expected:
                self._check_tuning(item.serial, m, mr)
            out += self._flags(item.serial, m, t_ns, mr.flags)
        return out

    def freeze_names(self, serials) -> dict[tuple[int, int], dict[int, str]]:
        """The detector ids of the run: ``(board, module) -> {channel: name}`` of the named channels read so far;
        a board of ``serials`` not read yet keeps b/m/c ids (one line)."""
        self.frozen = {key: named for key, mr in self.modules.items() if (named := _named(*key, mr))}
        for s in serials:
            if self.boards.get(s, {}).get("reads", 0) == 0:
                self.events.append(f"board {s}: not read before the first sample: its detector ids are "
                                   f"b{s}m<module>c<channel> for the run")
                self._names_said.add(s)
        return self.frozen

    def _check_tuning(self, board: int, m: int, mr) -> None:
        """The board's R_normal, R_frac achieved and loop gain against the parameters', per detector."""
        new = []
        for row, (c, name) in enumerate(zip(mr.channels.tolist(), mr.names)):
            det = detector_id(board, m, c)
            want = self._expected.get(name, self._expected.get(det))
            if want is None:
                continue
            got = {"r_normal_ohm": mr.r_normal_ohm[row], "r_frac": mr.r_frac[row], "loop_gain": mr.loop_gain[row]}
            off = {}
            for q, (kind, tol) in TUNING_TOLERANCES.items():
                b, e = float(got[q]), float(want[q])
                if not (np.isfinite(b) and np.isfinite(e)):
                    continue
                d = abs(b - e) / abs(e) if kind == "relative" else abs(b - e)
                if d > tol:
                    off[q] = {"board": round(b, 6), "params": round(e, 6)}
            if off:
                if det not in self.tuning_disagree:
                    new.append(det)
                self.tuning_disagree[det] = off
            else:
                self.tuning_disagree.pop(det, None)
        if new:
            first = self.tuning_disagree[new[0]]
            self.events.append(f"board {board} module {m}: {len(new)} detector(s) tuned unlike their parameters "
                               f"(e.g. {new[0]}: " + ", ".join(f"{q} {v['board']:g} on the board, {v['params']:g} "
                                                               "in the parameters" for q, v in first.items())
                               + "; see status tuning_disagree)")

    def _change(self, text: str) -> None:
        self.changes.append(text)
        log.info("dfmux-bridge: %s", text)

    def _bias(self, board: int, m: int, t_ns: int, before, mr) -> list:
        key = (board, m)
        same = before is not None and np.array_equal(before.channels, mr.channels) and \
            np.array_equal(before.bias_v, mr.bias_v, equal_nan=True)
        if same:  # republished every bias_every_s of board time: the converter's bias never goes stale
            if t_ns - self._t_bias_sent.get(key, t_ns) < self.pub.bias_every_ns:
                return []
            self._t_bias_sent[key] = t_ns
            return self.pub.board_bias(board, m, mr.channels, [t_ns], mr.bias_v[None, :])
        self._t_bias_sent[key] = t_ns
        if before is not None and np.array_equal(before.channels, mr.channels):
            with np.errstate(invalid="ignore", divide="ignore"):
                ratio = float(np.nanmedian(mr.bias_v / before.bias_v))
            self._change(f"board {board} module {m}: bias changed (median ratio {ratio:.4g}) at {t_ns} ns")
            t, v = [t_ns - 1, t_ns], np.stack([before.bias_v, mr.bias_v])
        else:
            t, v = [t_ns], mr.bias_v[None, :]
        self._check_configured(board, m, mr)
        return self.pub.board_bias(board, m, mr.channels, t, v)

    def _check_configured(self, board: int, m: int, mr) -> None:
        configured = self.pub.configured_bias(board, m)
        key = f"{board}/{m}"
        if configured is None:
            self.bias_disagree.pop(key, None)
            return
        board_v = float(np.nanmedian(mr.bias_v))
        rel = abs(configured - board_v) / board_v if board_v > 0 else np.inf
        if rel > self.bias_tolerance:
            if key not in self.bias_disagree:
                self.events.append(f"board {board} module {m}: configured bias {configured:.4g} V differs from the "
                                   f"board's {board_v:.4g} V (median) by {rel:.1%} (tolerance "
                                   f"{self.bias_tolerance:.0%}): the board's is published")
            self.bias_disagree[key] = {"configured_v": configured, "board_v": board_v, "relative": round(rel, 4)}
        else:
            self.bias_disagree.pop(key, None)

    def _flags(self, board: int, m: int, t_ns: int, flags: np.ndarray) -> list:
        key = (board, m)
        sent = self._flags_sent.get(key)
        if sent is not None and np.array_equal(sent, flags):
            return []
        if sent is None and not flags.any():
            self._flags_sent[key] = flags
            return self.pub.board_flags(board, m, self.modules[key].channels, t_ns, flags)
        n = int(np.count_nonzero(flags)) if sent is None else int(np.count_nonzero(flags != sent))
        self._change(f"board {board} module {m}: readout flags of {n} channel(s) changed at {t_ns} ns "
                     f"({', '.join(fl.describe(int(np.bitwise_or.reduce(flags))) or ['none'])} now)")
        self._flags_sent[key] = flags
        return self.pub.board_flags(board, m, self.modules[key].channels, t_ns, flags)

    def check_stale(self, t_floor_ns: int = 0, now_wall: float | None = None) -> list[tuple[str, bytes]]:
        """Boards whose last good housekeeping is older than ``stale_s``: HK_STALE on their modules' channels
        from the data time it went stale (its time stamp + ``stale_s``, or just after the newest sample
        published, ``t_floor_ns``, if later)."""
        now_wall = time.monotonic() if now_wall is None else now_wall
        out = []
        for serial, st in self.boards.items():
            if st["stale"] or st["t_wall"] is None or now_wall - st["t_wall"] <= self.stale_s:
                continue
            st["stale"] = True
            t_ns = max(int(st["t_ns"] + self.stale_s * 1e9), int(t_floor_ns) + 1)
            self.events.append(f"board {serial}: no good housekeeping for {self.stale_s:g} s: its samples are "
                               f"flagged HK_STALE from {t_ns} ns until it answers again")
            for (b, m), mr in sorted(self.modules.items()):
                if b == serial:
                    out += self._flags(b, m, t_ns, mr.flags | np.uint16(fl.HK_STALE))
        return out

    def status(self) -> dict:
        """The status fields: per board reads, failures, staleness; bias disagreements; the changes."""
        boards = {str(s): {k: v for k, v in st.items() if k not in ("t_wall", "failing")}
                  for s, st in sorted(self.boards.items())}
        now = time.monotonic()
        for s, st in self.boards.items():
            boards[str(s)]["age_s"] = None if st["t_wall"] is None else round(now - st["t_wall"], 3)
        flagged = {f"{b}/{m}": fl.describe(int(np.bitwise_or.reduce(f))) for (b, m), f in self._flags_sent.items()
                   if f.any()}
        return {"board_hk": boards, "board_hk_failures": sum(st["failures"] for st in self.boards.values()),
                "board_hk_reads": sum(st["reads"] for st in self.boards.values()),
                "bias_from_board": sorted(f"{b}/{m}" for b, m in self.pub.from_board),
                "bias_disagree": dict(sorted(self.bias_disagree.items())), "readout_flagged": flagged,
                "hk_changes": self.changes[-20:], "hk_changes_total": len(self.changes),
                "board_names": len(self.names),
                "detector_names": sum(len(v) for v in (self.frozen or {}).values()),
                "tuning_disagree": dict(sorted(self.tuning_disagree.items())[:100]),
                "tuning_disagree_total": len(self.tuning_disagree)}


def _named(board: int, module: int, mr: ModuleReading) -> dict[int, str]:
    """``{channel: name}`` of a module's channels the board names (the others carry their b/m/c id)."""
    return {c: n for c, n in zip(mr.channels.tolist(), mr.names) if n != detector_id(board, module, c)}


def _expected_tuning(p) -> dict:
    """What the parameters say the board's tuning should show: R_normal, and R_frac and loop gain at the
    nominal operating point (``core.model.describe``)."""
    from mntes_stream.core import model

    try:
        d = model.describe(p)
    except Exception:  # noqa: BLE001 - parameters without an operating point: R_normal only
        d = {}
    return {"r_normal_ohm": p.r_normal_ohm, "r_frac": d.get("r_frac", np.nan), "loop_gain": d.get("loop_gain", np.nan)}
