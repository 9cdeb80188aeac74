"""Which streams are converted: counts seen without power, power without counts, gaps in a stream's power.

A recorder (or anything that sees both ``counts/<b>/<m>`` and ``power/<b>/<m>``)
books every message here. A stream whose counts keep coming while no power
came for ``after_s`` is *unconverted*; why is said from the converters' latest
status ledgers (:meth:`Coverage.converter_status`): a converter that shed or
set aside the stream's chunks (overload) is named, else no converter publishes
it. When its live power comes back, the sequence numbers it skipped are a
gap (``gaps``: still missing now); power converted late (``late`` in the
power chunk) fills the gap again and is counted in ``late``. A stream whose
power comes while its counts never did is *power only*: the recorder does not
receive the source (zenoh peers do not forward for each other).
"""

from __future__ import annotations

import logging

from mntes_stream.core.ledger import StreamLedger

__all__ = ["Coverage"]

log = logging.getLogger("mntes_stream.recorder")

_MAX_RANGES = 64  # missing power ranges remembered per stream (the oldest forgotten first; they stay counted)
_MAX_STREAMS = 100_000  # streams booked at most (names come from topics any peer may publish)
_BEHIND_S = 0.5  # power reaching the recorder this much later than it used to: said to be behind


class Coverage:
    """Counts against power per stream, on the receive clock (seconds, monotonic).

    Parameters
    ----------
    after_s : float
        Counts without power (or power without counts) for this long: the stream is reported.
    """

    def __init__(self, after_s: float = 2.0):
        self.after_s = float(after_s)
        self._counts_t: dict[str, float] = {}  # "b/m" -> last counts receive time
        self._counts_first_t: dict[str, float] = {}  # "b/m" -> first counts receive time: the grace starts there
        self.converter_seen = False  # a converter's provenance or status came: before, none has announced itself
        self._power_t: dict[str, float] = {}
        self._power_first_t: dict[str, float] = {}
        self._power_seq: dict[str, int] = {}
        self._holes: dict[str, list[list[int]]] = {}  # "b/m" -> [lo, hi) ranges of power seqs never seen
        self._said: dict[str, str] = {}  # stream -> the reason last logged for it
        self._said_power_only: set[str] = set()
        self._converters: dict[str, tuple[dict, int]] = {}  # service -> (ledger dict, chunks set aside)
        self.gaps: dict[str, int] = {}  # "b/m" -> power chunks missing now while counts came
        self.late: dict[str, int] = {}  # "b/m" -> power chunks that came late (converted after overload)
        self.live: dict[str, int] = {}  # "b/m" -> power chunks converted live
        # "b/m" -> (least, latest) seconds from a power chunk's publication to its receipt here: their
        # difference is how far this recorder's intake has fallen behind (a replay's old stamps cancel out).
        self._lag_s: dict[str, tuple[float, float]] = {}

    @staticmethod
    def _stream(topic: str) -> tuple[str, str] | None:
        parts = topic.split("/")
        if len(parts) == 5 and parts[2] in ("counts", "power"):
            return parts[2], f"{parts[3]}/{parts[4]}"
        return None

    def add(self, topic: str, seq: int | None, t_s: float, late: bool = False, lag_s: float | None = None) -> None:
        """Book one message (its topic, envelope ``seq`` if any, receive time; ``late``: a power chunk marked late;
        ``lag_s``: receive wall time minus the publication time in the message, None if it has none)."""
        what = self._stream(topic)
        if what is None:
            if topic.endswith("/provenance"):
                self.converter_seen = True
            return
        kind, stream = what
        if stream not in self._counts_t and stream not in self._power_t and len(self._power_t) + len(self._counts_t) >= _MAX_STREAMS:
            return
        if kind == "counts":
            self._counts_t[stream] = t_s
            self._counts_first_t.setdefault(stream, t_s)
            return
        if late:
            self.late[stream] = self.late.get(stream, 0) + 1
        else:
            self.live[stream] = self.live.get(stream, 0) + 1
            if lag_s is not None:  # late power is late by design: not a sign of this recorder's intake
                least = self._lag_s.get(stream, (lag_s,))[0]
                self._lag_s[stream] = (min(least, lag_s), lag_s)
        last = self._power_seq.get(stream)
        if seq is not None and seq != last:
            if last is not None and last < seq <= last + 1000:
                if seq > last + 1:
                    self._hole(stream, last + 1, seq)
            elif last is not None and last - 1000 <= seq < last:
                self._fill(stream, seq)  # late (or reordered): no longer missing
            if last is None or seq > last or seq < last - 1000:  # late ones keep the newest; far off: a restart
                if last is not None and not last - 1000 <= seq <= last + 1000:
                    self._holes.pop(stream, None)  # a restarted stream: old holes cannot be filled any more
                self._power_seq[stream] = seq
        self._power_t[stream] = t_s
        self._power_first_t.setdefault(stream, t_s)
        self._said.pop(stream, None)

    def _hole(self, stream: str, lo: int, hi: int) -> None:
        holes = self._holes.setdefault(stream, [])
        holes.append([lo, hi])
        if len(holes) > _MAX_RANGES:
            holes.pop(0)
        missing = hi - lo
        self.gaps[stream] = self.gaps.get(stream, 0) + missing
        log.warning("stream %s: power again after a gap of %d chunk(s) (seq %d to %d never came live): %s", stream,
                    missing, lo, hi - 1, self.reason(stream, "no converter published them"))

    def _fill(self, stream: str, seq: int) -> None:
        holes = self._holes.get(stream, ())
        for i, (lo, hi) in enumerate(holes):
            if lo <= seq < hi:
                if hi - lo == 1:
                    del holes[i]
                elif seq == lo:
                    holes[i][0] += 1
                elif seq == hi - 1:
                    holes[i][1] -= 1
                else:
                    holes[i:i + 1] = [[lo, seq], [seq + 1, hi]]
                self.gaps[stream] -= 1
                if not self.gaps[stream]:
                    del self.gaps[stream]
                return

    def converter_status(self, service: str, ledger: dict | None, set_aside: int = 0) -> None:
        """The newest status of a converter: its ledger (stream -> columns) and the chunks it holds set aside."""
        self.converter_seen = True
        if service in self._converters or len(self._converters) < 1000:
            self._converters[str(service)] = (dict(ledger or {}), int(set_aside or 0))

    def reason(self, stream: str, default: str = "no converter publishes it") -> str:
        """Why a stream has no power, as the converters' latest ledgers say (shed, set aside), else ``default``."""
        other = []
        for name, (ledger, set_aside) in sorted(self._converters.items()):
            cols = ledger.get(stream)
            if not cols:
                continue
            s = StreamLedger.from_dict(cols)
            if s.shed_total:
                reasons = ", ".join(sorted(s.shed))
                return f"converter {name} shed {s.shed_total} chunks of it ({reasons})"
            if set_aside and s.pending:
                other.insert(0, f"converter {name} holds {s.pending} chunks of it set aside (overload)")
            elif s.rejected_total:
                reasons = ", ".join(sorted(s.rejected))
                other.append(f"converter {name} rejected {s.rejected_total} chunks of it ({reasons})")
            elif s.pending and not s.done + s.late:
                other.append(f"converter {name} holds {s.pending} chunks of it (waiting for housekeeping, or starting)")
            elif s.done + s.late:
                why = (f"converter {name} converted {s.done + s.late} chunks of it by its last status, but no power "
                       f"for {self.after_s:.3g} s ")
                behind = self.behind_s(stream)
                if behind >= _BEHIND_S:
                    why += (f"(its power reaches this recorder late: the last {behind:.3g} s later than the "
                            "earliest did; this recorder or its link is behind: zenoh's BLOCK congestion control "
                            "slows the converter and the source, and past its block budget, 5 s by default, "
                            "closes the link and loses what is queued on it)")
                else:
                    why += "(stalled, or its power does not reach this recorder)"
                other.append(why)
        return other[0] if other else default

    def behind_s(self, stream: str) -> float:
        """How much later than its earliest the latest live power chunk of ``stream`` reached this recorder
        (seconds, from each chunk's own publication time; 0 with none)."""
        least, latest = self._lag_s.get(stream, (0.0, 0.0))
        return max(latest - least, 0.0)

    def unconverted(self, now_s: float) -> list[str]:
        """Streams whose counts came in the last ``after_s`` with no power for ``after_s`` (logged once per reason)."""
        out = []
        for stream, t_counts in self._counts_t.items():
            if now_s - t_counts > self.after_s:
                continue  # the stream itself stopped: nothing to convert
            t_power = self._power_t.get(stream)
            # No power yet: only after after_s of counts (a stream's first counts come before its first power).
            since = self._counts_first_t.get(stream, t_counts) if t_power is None else t_power
            if now_s - since > self.after_s:
                out.append(stream)
                why = self.reason(stream) if self.converter_seen else (
                    "no converter has announced itself yet (one is starting, or none runs)")
                if self._said.get(stream) != why:
                    self._said[stream] = why
                    log.warning("stream %s: counts without power for %.3g s: %s", stream, self.after_s, why)
        return sorted(out)

    def power_only(self, now_s: float) -> list[str]:
        """Streams whose power came for ``after_s`` while their counts never did (logged once each)."""
        out = []
        for stream, t_first in self._power_first_t.items():
            if stream in self._counts_t or now_s - t_first < self.after_s:
                continue
            out.append(stream)
            if stream not in self._said_power_only:
                self._said_power_only.add(stream)
                log.warning("stream %s: power for %.3g s but never its counts: this recorder does not receive the "
                            "source (zenoh peers do not forward for each other: connect to the source too, or turn "
                            "gossip scouting on)", stream, self.after_s)
        return sorted(out)

    def summary(self, now_s: float) -> dict:
        """``unconverted`` streams now (and why), ``power_only`` streams, power ``gaps`` and ``late`` so far."""
        unconverted = self.unconverted(now_s)
        return {"streams": len(self._counts_t), "unconverted": unconverted,
                "unconverted_why": {s: self._said.get(s, "") for s in unconverted},
                "power_only": self.power_only(now_s), "power_gaps": dict(self.gaps), "power_late": dict(self.late)}
