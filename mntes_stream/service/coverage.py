"""Which streams are converted: counts seen without power, and gaps in a stream's power.

A recorder (or anything that sees both ``counts/<b>/<m>`` and ``power/<b>/<m>``)
books every message here. A stream whose counts keep coming while no power
came for ``after_s`` is *unconverted* (no converter owns it, or its converter
died); when its power comes back, the sequence numbers it skipped are the
gap, reported once per stream and kept in ``gaps``.
"""

from __future__ import annotations

import logging

__all__ = ["Coverage"]

log = logging.getLogger("mntes_stream.recorder")


class Coverage:
    """Counts against power per stream, on the receive clock (seconds, monotonic).

    Parameters
    ----------
    after_s : float
        Counts without power for this long: the stream is unconverted.
    """

    def __init__(self, after_s: float = 2.0):
        self.after_s = float(after_s)
        self._counts_t: dict[str, float] = {}  # "b/m" -> last counts receive time
        self._power_t: dict[str, float] = {}
        self._power_seq: dict[str, int] = {}
        self._said: set[str] = set()
        self.gaps: dict[str, int] = {}  # "b/m" -> chunks of power never seen while counts came (summed)

    @staticmethod
    def _stream(topic: str) -> tuple[str, str] | None:
        parts = topic.split("/")
        if len(parts) == 5 and parts[2] in ("counts", "power"):
            return parts[2], f"{parts[3]}/{parts[4]}"
        return None

    def add(self, topic: str, seq: int | None, t_s: float) -> None:
        """Book one message (its topic, envelope ``seq`` if any, receive time)."""
        what = self._stream(topic)
        if what is None:
            return
        kind, stream = what
        if kind == "counts":
            self._counts_t[stream] = t_s
            return
        last = self._power_seq.get(stream)
        if seq is not None and seq != last:
            if last is not None and seq > last + 1:
                missing = seq - last - 1
                self.gaps[stream] = self.gaps.get(stream, 0) + missing
                log.warning("stream %s: power again after a gap of %d chunk(s) (seq %d to %d never converted)",
                            stream, missing, last + 1, seq - 1)
            if last is None or seq > last or seq < last - 1000:  # late ones keep the newest; far back: a restart
                self._power_seq[stream] = seq
        self._power_t[stream] = t_s
        if stream in self._said:
            self._said.discard(stream)

    def unconverted(self, now_s: float) -> list[str]:
        """Streams whose counts came in the last ``after_s`` with no power for ``after_s`` (logged once each)."""
        out = []
        for stream, t_counts in self._counts_t.items():
            if now_s - t_counts > self.after_s:
                continue  # the stream itself stopped: nothing to convert
            t_power = self._power_t.get(stream)
            if t_power is None or now_s - t_power > self.after_s:
                out.append(stream)
                if stream not in self._said:
                    self._said.add(stream)
                    log.warning("stream %s: counts without power for %.3g s: no converter publishes it",
                                stream, self.after_s)
        return sorted(out)

    def summary(self, now_s: float) -> dict:
        """``unconverted`` streams now, power ``gaps`` so far (chunks per stream), streams seen."""
        return {"streams": len(self._counts_t), "unconverted": self.unconverted(now_s), "power_gaps": dict(self.gaps)}
