"""What spt3g's collector and builder drop, counted from their own log lines.

spt3g 1.0.2's ``DfMuxCollector`` and ``DfMuxBuilder`` drop a packet with
one log line (``dfmux/src/DfMuxCollector.cxx``, ``DfMuxBuilder.cxx``) and
count nothing; its logger (``G3PrintfLogger``) writes to file descriptor 2
and cannot be subclassed from Python. :class:`Spt3gLog` puts a pipe on
descriptor 2 while the bridge runs and reads it in a thread: every line of
spt3g's that names a dropped packet is counted by reason; every other line
(the bridge's own, Python's, any library's) goes on to the real stderr
unchanged, and spt3g's own lines too at or above the level the user asked
for (the first few of each kind; then counted only, so a flood of bad
packets cannot flood the log).

Reasons (:data:`REASONS`): ``magic``, ``version``, ``length`` (truncated or
oversized), ``board not configured`` (V3/V4 serial not named, V2 address
not mapped: spt3g logs these at DEBUG, so the collector's unit is set to
DEBUG and its lines are counted, never shown), ``duplicate`` (a second
packet for a module/block at one time), ``before the builder's last
sample`` (a time stamp behind the last frame out: an IRIG step back).

Sequence numbers: the collector warns when a module's packet sequence
number is not the last one + 1 (``Out-of-order packet from B/M (GOT
instead of EXPECTED)``): packets lost (or dropped above) before it, or a
board that restarted (GOT < EXPECTED). :meth:`Spt3gLog.take_seq_events`
hands them to the bridge, which tells a gap in a stream's time stamps with
no sequence skip (the board's IRIG time jumped) from one with a skip (lost
packets).
"""

from __future__ import annotations

import os
import re
import sys
import threading
import time
from collections import Counter
from dataclasses import dataclass

from mntes_stream.dfmux.packets import SAMPLE_NS

__all__ = ["Spt3gLog", "SeqEvent", "REASONS", "classify"]

REASONS = ("magic", "version", "length", "board not configured", "duplicate", "before the builder's last sample")
SHOWN_PER_KIND = 3
SAMPLE_S = SAMPLE_NS / 1e9  # spt3g lines of one drop kind shown before they are only counted

_ANSI = re.compile(r"\x1b\[[0-9;]*m")
_LINE = re.compile(r"^(TRACE|DEBUG|INFO|NOTICE|WARN|ERROR|FATAL) \((\w+)\)[^:]*(?::\d\d)*[^:]*: (.*)$")
_KINDS = (
    (re.compile(r"^Corrupted packet from "), "magic"),
    (re.compile(r"^Unknown packet version "), "version"),
    (re.compile(r"^Badly-sized packet "), "length"),
    (re.compile(r"^(V2 \(64x\) data from unknown board|Received V\d+ data for board \d+ not enumerated)"),
     "board not configured"),
    (re.compile(r"^Duplicate packet from board "), "duplicate"),
    (re.compile(r"^Bogon packet from board "), "before the builder's last sample"),
)
_SEQ = re.compile(r"^Out-of-order packet from (\d+)/(\d+) \((-?\d+) instead of (-?\d+)\)")
_BOGON = re.compile(r"^Bogon packet from board (\d+) at past time (\S+) \(last outbound frame was at (\S+)\)")
_LEVELS = ("TRACE", "DEBUG", "INFO", "NOTICE", "WARN", "ERROR", "FATAL")


@dataclass(frozen=True)
class SeqEvent:
    """A module's packet sequence number not following its last: ``got`` where ``expected`` was due.

    ``mod_id`` is the collector's: the module (V2/V3), ``module * 8 + block`` (V4); ``t_read_ns``: when the
    bridge read the line (``time.time_ns()``).
    """

    board: int
    mod_id: int
    got: int
    expected: int
    t_read_ns: int = 0


def _g3_time_s(text: str) -> float | None:
    """spt3g's ``G3Time.Description()`` (``28-Nov-2026:16:16:39.733440000``, UTC) -> POSIX seconds."""
    import datetime as dt

    try:
        whole, _, frac = text.partition(".")
        t = dt.datetime.strptime(whole, "%d-%b-%Y:%H:%M:%S").replace(tzinfo=dt.UTC)
    except ValueError:
        return None
    return t.timestamp() + (float("0." + frac) if frac.isdigit() else 0.0)


def classify(line: str):
    """One line of spt3g's log -> ``(level, kind, detail)``; kind: a :data:`REASONS` entry, ``"seq"`` (detail: a
    :class:`SeqEvent`), ``"spt3g"`` (another line of spt3g's), or None (not spt3g's: level and detail None)."""
    m = _LINE.match(_ANSI.sub("", line.rstrip("\n")))
    if m is None:
        return None, None, None
    level, _unit, message = m.groups()
    s = _SEQ.match(message)
    if s:
        return level, "seq", SeqEvent(*(int(x) for x in s.groups()), t_read_ns=time.time_ns())
    for pattern, kind in _KINDS:
        if pattern.match(message):
            detail = None
            b = _BOGON.match(message) if kind == REASONS[-1] else None
            if b:
                past, last = _g3_time_s(b[2]), _g3_time_s(b[3])
                # the step: from the sample before it (the builder's last out) to the first one after
                step_s = None if past is None or last is None else last - past + SAMPLE_S
                detail = (int(b[1]), step_s, b[3])
            return level, kind, detail
    return level, "spt3g", None


class Spt3gLog:
    """Descriptor 2 through a pipe while the bridge runs; spt3g's drops counted (see the module's docstring).

    Parameters
    ----------
    core : module
        ``spt3g.core`` (its logger's levels are set here).
    show_level : str
        spt3g lines at or above this level (``debug`` ... ``fatal``) are shown (the first few of a drop kind).
    """

    def __init__(self, core, show_level: str = "error"):
        self.show_at = _LEVELS.index(show_level.upper())
        self.dropped: Counter = Counter()
        self.seq_events: list[SeqEvent] = []
        self.steps_back: list[tuple[int, float]] = []  # (board, seconds back) of each step's first past-time drop
        self._step_keys: set = set()
        self._shown: Counter = Counter()
        self._v2_ours = False
        self._lock = threading.Lock()
        self._fd_saved = self._thread = None
        logger = core.G3Logger.global_logger
        # The collector's DEBUG lines are its "board not configured" drops only; WARN brings the sequence numbers
        # and the builder's past-time drops. Lines below the user's level are counted, not shown.
        level = core.G3LogLevel
        logger.set_level(getattr(level, f"LOG_{_LEVELS[self.show_at]}"))
        logger.set_level_for_unit("DfMuxCollector", level.LOG_DEBUG)
        logger.set_level_for_unit("DfMuxBuilder", getattr(level, f"LOG_{_LEVELS[min(self.show_at, 4)]}"))  # WARN

    def start(self) -> None:
        """Put the pipe on descriptor 2 (what was there keeps every line that is not a counted drop)."""
        if self._thread is not None:
            return
        sys.stderr.flush()
        read_fd, write_fd = os.pipe()
        self._fd_saved = os.dup(2)
        os.dup2(write_fd, 2)
        os.close(write_fd)
        self._thread = threading.Thread(target=self._read, args=(read_fd,), name="spt3g-log", daemon=True)
        self._thread.start()

    def stop(self, timeout_s: float = 2.0) -> None:
        """Give descriptor 2 back and read what is left in the pipe."""
        if self._thread is None:
            return
        sys.stderr.flush()
        os.dup2(self._fd_saved, 2)  # the pipe's last write end closes: the reader sees its end
        self._thread.join(timeout_s)
        os.close(self._fd_saved)
        self._thread = None

    def _read(self, read_fd: int) -> None:
        out = self._fd_saved
        with os.fdopen(read_fd, "rb", buffering=1 << 16) as pipe:
            for raw in pipe:
                show = self._book(raw.decode("utf-8", "replace"))
                if show:
                    try:
                        os.write(out, raw)
                    except OSError:
                        pass

    def _book(self, line: str) -> bool:
        """Count one line; True: show it."""
        level, kind, detail = classify(line)
        if kind is None:
            return True
        shown = _LEVELS.index(level) >= self.show_at
        with self._lock:
            if kind == "seq":
                self.seq_events.append(detail)
                return shown
            if kind == "spt3g":
                return shown
            if self._v2_ours and kind == "board not configured" and "V2 (64x)" in line:
                return False
            self.dropped[kind] += 1
            if kind == REASONS[-1] and detail is not None:
                board, back_s, last = detail
                # one step: the builder sends nothing while it drops, so its "last outbound frame" stays put
                if back_s is not None and (board, last) not in self._step_keys and len(self._step_keys) < 1000:
                    self._step_keys.add((board, last))
                    self.steps_back.append((board, back_s))
            self._shown[kind] += shown
            return shown and self._shown[kind] <= SHOWN_PER_KIND

    def ignore_v2_unknown(self) -> None:
        """From now on V2 packets from unknown addresses are the bridge's own wake-up datagrams (its stop): not
        counted."""
        with self._lock:
            self._v2_ours = True

    def take_seq_events(self) -> list[SeqEvent]:
        """The sequence events read since the last call."""
        with self._lock:
            out, self.seq_events = self.seq_events, []
        return out

    def counts(self) -> dict[str, int]:
        """Packets dropped by spt3g so far, by reason (reasons with none left out)."""
        with self._lock:
            return {k: self.dropped[k] for k in REASONS if self.dropped[k]}
