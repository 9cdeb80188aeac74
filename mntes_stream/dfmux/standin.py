"""A stand-in IceBoard's tuber interface: ``Dfmux._dump_housekeeping`` over HTTP, for tests and the lab recipe.

A real HTTP/1.1 server (``POST /tuber``, JSON calls, keep-alive) answering
the calls spt3g's ``TuberClient`` sends, with housekeeping in the shape
spt3g's ``HousekeepingConsumer.HousekeepingFromJSON`` and ``WiringFromJSON``
parse: 2 mezzanines x 4 modules x 64 channels, gains, overload flags,
SQUID and channel tuning (state, mapped name, R_normal, R_frac achieved,
loop gain), the board's time stamp now. ``POST /standin`` changes the board
while it runs (JSON body, one change a call; the reply says when it took
effect, ``t_ns``):

- ``{"retune": {"module": M, "factor": F}}``: carrier amplitudes of module M
  (0-7) times F (a retune: the bias changes in that ratio);
- ``{"state": {"module": M, "channel": C, "state": "latched"}}``;
- ``{"rail": {"module": M, "what": "carrier"|"nuller"|"demod"}}`` or
  ``{"rail": {"module": M, "channel": C}}`` (the channel's DAN);
- ``{"mode": "ok"|"hang"|"garbage"}``: answer, never answer (a tuber
  timeout), or answer bytes that are not JSON;
- ``{}``: nothing (every reply also says how many housekeeping dumps the
  board has answered, ``dumps``).

``python -m mntes_stream.dfmux.standin --board SERIAL[=HOST[:PORT]]`` serves
one board per address (default: what ``iceboard<serial>.local`` resolves
to, port 80, as spt3g connects); its first line on stdout is ``standin:
listening SERIAL=HOST:PORT ...`` once every socket listens. With
``--detectors VERSION:SERIAL:MODULES[:CHANNELS] --seed N`` (the synthetic
sender's ``--board`` and ``--seed``) it serves the carrier amplitudes that
give exactly the bias of the sender's detectors (:meth:`BoardState.serve_bias`).
"""

from __future__ import annotations

import argparse
import json
import signal
import socket
import sys
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

__all__ = ["BoardState", "StandInBoard", "main", "board_host"]

MEZZANINES, MODULES, CHANNELS = 2, 4, 64  # an IceBoard: 2 mezzanines x 4 modules x 64 channels (64x firmware)
CARRIER_AMPLITUDE = 0.0068  # normalised; ~3 uV RMS at carrier gain 3 through spt3g's 2017 transfer function


def board_host(serial: int) -> str:
    """The name spt3g's ``HousekeepingConsumer`` reaches a board by."""
    return f"iceboard{int(serial):04d}.local"


def channel_name(serial: int, module: int, channel: int) -> str:
    """The mapped name the stand-in stores for a channel (a lab's hardware map: its own names)."""
    return f"Lab{serial}.{module}.{channel:02d}"


class BoardState:
    """One board's housekeeping, as its ``_dump_housekeeping`` returns it; changed by :meth:`apply`.

    Parameters
    ----------
    serial : int
    named_modules : int
        Modules whose channels carry mapped names (the hardware map stored on the board); the others none.
    carrier_amplitude : float
        Every channel's normalised carrier amplitude at the start.
    """

    def __init__(self, serial: int, named_modules: int = MEZZANINES * MODULES,
                 carrier_amplitude: float = CARRIER_AMPLITUDE):
        self.serial = int(serial)
        self.named_modules = int(named_modules)
        self.lock = threading.Lock()
        n = MEZZANINES * MODULES
        self.amplitude = [[float(carrier_amplitude)] * CHANNELS for _ in range(n)]
        self.state = [["tuned"] * CHANNELS for _ in range(n)]
        self.dan_railed = [[False] * CHANNELS for _ in range(n)]
        self.overload = [{"carrier": False, "nuller": False, "demod": False} for _ in range(n)]
        self.mode = "ok"
        self.dumps = 0

    def apply(self, change: dict) -> int:
        """One change (see the module doc); returns when it took effect (ns since the epoch)."""
        with self.lock:
            if "retune" in change:
                m, f = int(change["retune"]["module"]), float(change["retune"]["factor"])
                self.amplitude[m] = [a * f for a in self.amplitude[m]]
            elif "state" in change:
                s = change["state"]
                self.state[int(s["module"])][int(s["channel"])] = str(s["state"])
            elif "rail" in change:
                r = change["rail"]
                if "channel" in r:
                    self.dan_railed[int(r["module"])][int(r["channel"])] = bool(r.get("on", True))
                else:
                    self.overload[int(r["module"])][str(r["what"])] = bool(r.get("on", True))
            elif "mode" in change:
                if change["mode"] not in ("ok", "hang", "garbage"):
                    raise ValueError(f"mode {change['mode']!r}")
                self.mode = change["mode"]
            elif change:
                raise ValueError(f"unknown change {sorted(change)}")
            return time.time_ns()

    def serve_bias(self, bias_v) -> None:
        """Carrier amplitudes whose bias, as the bridge derives it, is ``bias_v[m]`` on every channel of module m.

        ``bias_v``: RMS Thevenin volts per module, shape (n,), n <= 8 (the first n modules; e.g. a
        :class:`~mntes_stream.dfmux.detectors.DetectorBoard`'s ``bias_v``). The amplitude is the bias over
        the bias of a unit amplitude, both through the bridge's own derivation
        (:func:`~mntes_stream.dfmux.boardhk.reading_from_dump`: spt3g's ``HousekeepingFromJSON`` and
        ``bolo_bias_voltage_rms``, linear in the amplitude at a given carrier gain and frequency).
        """
        from mntes_stream.dfmux.boardhk import reading_from_dump

        bias_v = [float(v) for v in bias_v]
        if len(bias_v) > len(self.amplitude):
            raise ValueError(f"{len(bias_v)} modules: an IceBoard has {len(self.amplitude)}")
        if not all(v > 0 for v in bias_v):
            raise ValueError(f"bias must be > 0 V, got {min(bias_v)}")
        with self.lock:
            saved, dumps = self.amplitude, self.dumps
            self.amplitude = [[1.0] * CHANNELS for _ in saved]
        try:
            unit = reading_from_dump(self.dump(), self.serial, "127.0.0.1")[0].modules
        finally:
            with self.lock:
                self.amplitude, self.dumps = saved, dumps
        with self.lock:
            for m, v in enumerate(bias_v):
                row = dict(zip(unit[m].channels.tolist(), unit[m].bias_v.tolist()))
                self.amplitude[m] = [v / row[c] for c in range(CHANNELS)]

    def dump(self, t_ns: int | None = None) -> dict:
        """``Dfmux._dump_housekeeping``'s result now (or at ``t_ns``)."""
        t_ns = time.time_ns() if t_ns is None else int(t_ns)
        tm = time.gmtime(t_ns // 10**9)
        stamp = {"y": tm.tm_year - 2000, "d": tm.tm_yday, "h": tm.tm_hour, "m": tm.tm_min, "s": tm.tm_sec,
                 "ss": (t_ns % 10**9) // 10}  # ss: ticks of 10 ns, as spt3g's G3Time takes it
        with self.lock:
            self.dumps += 1
            mezz = []
            for z in range(MEZZANINES):
                mods = []
                for j in range(MODULES):
                    m = z * MODULES + j
                    chans = []
                    for c in range(CHANNELS):
                        tuning = {"state": self.state[m][c], "rnormal": 2.0, "rfrac_achieved": 0.7,
                                  "loopgain": 10.0, "rlatched": 0.05}
                        if m < self.named_modules:
                            tuning["name"] = channel_name(self.serial, m, c)
                        chans.append({"carrier_amplitude": self.amplitude[m][c], "nuller_amplitude": 0.0,
                                      "dan_gain": 0.01, "dan_streaming_enable": True,
                                      "frequency": 1.6e6 + 4e4 * c + 1e3 * m, "carrier_phase": 0.0,
                                      "nuller_phase": 0.0, "demod_phase": 0.0, "dan_accumulator_enable": True,
                                      "dan_feedback_enable": True, "dan_railed": self.dan_railed[m][c],
                                      "tuning": tuning})
                    mods.append({"routing": ["routing_nul", 0], "gains": {"carrier": 3, "nuller": 2},
                                 "overload": dict(self.overload[m]), "nco_frequency": 0.0,
                                 "squid_tuning": {"state": "tuned", "transimpedance": 500.0, "p2p": 1.5},
                                 "channels": chans})
                mezz.append({"present": True, "power": True, "temperature": 30.0, "modules": mods})
        return {"serial": f"{self.serial:04d}", "timestamp": stamp, "timestamp_port": "BACKPLANE", "fir_stage": 6,
                "is128x": False, "firmware_name": "standin", "firmware_version": "0",
                "currents": {}, "voltages": {}, "temperatures": {}, "mezzanines": mezz}


class _Handler(BaseHTTPRequestHandler):
    protocol_version = "HTTP/1.1"  # keep-alive, as TuberClient asks

    def log_message(self, *args) -> None:  # quiet: a test reads this process's stdout
        pass

    def _reply(self, body: bytes, code: int = 200) -> None:
        self.send_response(code)
        self.send_header("Content-Type", "application/json")
        self.send_header("Content-Length", str(len(body)))
        self.end_headers()
        self.wfile.write(body)

    def do_POST(self) -> None:  # noqa: N802 - http.server's name
        board: BoardState = self.server.board
        try:
            calls = json.loads(self.rfile.read(int(self.headers.get("Content-Length", 0))) or b"null")
        except ValueError:
            self._reply(b'{"error": "request is not JSON"}', 400)
            return
        if self.path == "/standin":
            try:
                t_ns = board.apply(calls)
                self._reply(json.dumps({"ok": True, "t_ns": t_ns, "dumps": board.dumps}).encode())
            except (KeyError, TypeError, ValueError, IndexError) as exc:
                self._reply(json.dumps({"ok": False, "error": str(exc)}).encode(), 400)
            return
        if self.path != "/tuber" or not isinstance(calls, list):
            self._reply(b'{"error": "POST /tuber with a JSON list of calls"}', 404)
            return
        if board.mode == "hang":  # never answers: the client's timeout
            self.close_connection = True
            time.sleep(3600)
            return
        if board.mode == "garbage":
            self._reply(b"<html>this is not tuber</html>")
            return
        out = []
        for call in calls:
            method = call.get("method") if isinstance(call, dict) else None
            if method == "_dump_housekeeping":
                out.append({"result": board.dump()})
            elif method == "_get_backplane_serial":
                out.append({"result": 1})
            elif method == "get_backplane_slot":
                out.append({"result": 1})
            else:
                out.append({"error": {"message": f"no method {method!r}"}})
        self._reply(json.dumps(out).encode())


class StandInBoard:
    """One stand-in board served on ``(host, port)`` in daemon threads; :meth:`close` stops it."""

    def __init__(self, board: BoardState, host: str, port: int = 80):
        self.board = board
        self.server = ThreadingHTTPServer((host, port), _Handler)
        self.server.daemon_threads = True
        self.server.board = board
        self.address = self.server.server_address
        self._thread = threading.Thread(target=self.server.serve_forever, name=f"standin-{board.serial}",
                                        daemon=True)
        self._thread.start()

    def close(self) -> None:
        self.server.shutdown()
        self.server.server_close()


def parse_board(text: str) -> tuple[int, str, int]:
    """``SERIAL[=HOST[:PORT]]`` -> (serial, host, port); the host by default what spt3g would reach."""
    serial, _, where = text.partition("=")
    try:
        s = int(serial)
        host, _, port = where.rpartition(":") if ":" in where else (where, "", "")
        host = host or socket.gethostbyname(board_host(s))
        return s, host, int(port) if port else 80
    except (ValueError, OSError) as exc:
        raise argparse.ArgumentTypeError(f"--board {text!r}: {exc}") from None


def main(argv=None) -> int:
    p = argparse.ArgumentParser(prog="python -m mntes_stream.dfmux.standin", description=__doc__.split("\n")[0])
    p.add_argument("--board", action="append", type=parse_board, required=True, metavar="SERIAL[=HOST[:PORT]]",
                   help="serve this board (default address: iceboard<serial>.local, port 80); repeatable")
    p.add_argument("--named-modules", type=int, default=MEZZANINES * MODULES,
                   help="modules whose channels carry mapped names (default all 8)")
    p.add_argument("--carrier-amplitude", type=float, default=CARRIER_AMPLITUDE,
                   help="every channel's normalised carrier amplitude (default %(default)s)")
    p.add_argument("--detectors", action="append", default=[], metavar="VERSION:SERIAL:MODULES[:CHANNELS]",
                   help="serve the bias of the synthetic sender's detectors on that board (the sender's --board "
                        "spec, with --seed as the sender's): each module's carrier amplitudes give its bias")
    p.add_argument("--seed", type=int, default=0, help="with --detectors: the sender's --seed")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this long (0: until killed)")
    args = p.parse_args(argv)
    states = {s: BoardState(s, args.named_modules, args.carrier_amplitude) for s, _, _ in args.board}
    if args.detectors:
        from mntes_stream.dfmux.sender import detector_boards
        from mntes_stream.dfmux.sender import parse_board as sender_board

        try:
            specs = [sender_board(d) for d in args.detectors]
        except argparse.ArgumentTypeError as exc:
            p.error(str(exc).replace("--board", "--detectors"))
        for det in detector_boards(specs, args.seed):
            if det.serial not in states:
                p.error(f"--detectors: board {det.serial} is not served (no --board {det.serial})")
            try:
                states[det.serial].serve_bias(det.bias_v)
            except ValueError as exc:
                p.error(f"--detectors: board {det.serial}: {exc}")
    try:
        boards = [StandInBoard(states[s], h, port) for s, h, port in args.board]
    except OSError as exc:
        print(f"standin: cannot listen: {exc.strerror or exc}", file=sys.stderr)
        return 1
    signal.signal(signal.SIGTERM, lambda *_: sys.exit(0))  # kill: the sockets closed, exit 0
    print("standin: listening " + " ".join(f"{b.board.serial}={b.address[0]}:{b.address[1]}" for b in boards),
          flush=True)
    try:
        t_end = time.monotonic() + args.duration if args.duration else None
        while t_end is None or time.monotonic() < t_end:
            time.sleep(0.2)
    except KeyboardInterrupt:
        pass
    finally:
        for b in boards:
            b.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
