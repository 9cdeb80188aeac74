"""What a converter owns and what it may publish: its streams, their claims, and the outputs it holds back.

A converter owns the streams of its parameters that fall in its ``boards``,
``modules`` and ``shard`` (``core.shards``). It claims each one on zenoh
(``io.claims``); where another converter claimed a stream first, this one
holds that stream's power back: as a hot standby silently, otherwise
reporting the conflict (status, heartbeat, log once). Held-back power of the
last ``holdback_s`` is kept, and the publisher's power on those streams is
watched: when the publisher goes, the first of what it did not publish goes
out at once, so a takeover leaves no gap beyond what was in flight.
"""

from __future__ import annotations

import collections
import logging

from mntes_stream.core.shards import Shard, StreamKey, stream_label
from mntes_stream.io import keys

__all__ = ["Ownership", "owns_summary"]

log = logging.getLogger("mntes_stream.converter")

_LIST_MAX = 32  # streams listed by name in status and heartbeat; beyond, counted


def _labels(streams) -> list[str]:
    labels = [stream_label(s) for s in sorted(streams)]
    return labels if len(labels) <= _LIST_MAX else labels[:_LIST_MAX] + [f"... {len(labels) - _LIST_MAX} more"]


def _text(streams) -> str:
    return ", ".join(_labels(streams))


def owns_summary(shard: Shard, boards, modules, streams) -> dict:
    """The part of the focal plane a converter owns, as status, heartbeat and provenance say it."""
    return {"shard": str(shard), "boards": list(boards) or "*", "modules": list(modules) or "*",
            "streams": len(streams), "stream_list": _labels(streams)}


def _stream_of(key: str) -> StreamKey | None:
    parts = key.split("/")
    return StreamKey.parse("/".join(parts[3:])) if len(parts) == 5 and parts[2] == "power" else None


def _seq_of(payload: bytes) -> int | None:
    import msgpack

    try:
        return int(msgpack.unpackb(payload, raw=False)["seq"])
    except Exception:  # not ours to judge here: the recorder and monitor validate power
        return None


class Ownership:
    """The publishing side of a converter's ownership (see the module docstring).

    Parameters
    ----------
    claims : io.claims.StreamClaims
    summary : dict
        :func:`owns_summary` of the converter.
    standby : bool
        Hold back streams claimed first by another converter without calling it a conflict.
    holdback_s : float
        Held-back power kept this long for a takeover.
    """

    def __init__(self, claims, summary: dict, standby: bool, holdback_s: float = 2.0, warn=None):
        self.claims = claims
        self.summary = summary
        self.standby = bool(standby)
        self.holdback_ns = int(holdback_s * 1e9)
        self._warn = warn or (lambda _: None)
        self._version = -1
        self.publishing: frozenset = frozenset()
        self.held: frozenset = frozenset()
        self._buffer: dict[tuple[int, int], collections.deque] = {}
        self._last_seen: dict[tuple[int, int], int] = {}  # newest seq the publisher put out, per held stream
        self._conflicts_said: set = set()
        self.withheld = 0
        self.taken_over = 0
        self.refresh()

    def refresh(self) -> list[tuple[str, bytes]]:
        """Re-read the claims when they changed; returns held-back power to publish now (a takeover)."""
        version = self.claims.version
        if version == self._version:
            return []
        self._version = version
        before = self.held
        self.publishing = self.claims.publishing()
        self.held = self.claims.streams - self.publishing
        others = self.claims.others()
        standby_for, lost_to, rivals = collections.defaultdict(list), collections.defaultdict(list), \
            collections.defaultdict(list)
        for stream in sorted(self.held - before):
            first = others[stream][0] if others.get(stream) else None
            who = first.name if first is not None else "?"
            if self.standby or (first is not None and first.standby):
                standby_for[who].append(stream)
            elif (stream, who) not in self._conflicts_said:
                self._conflicts_said.add((stream, who))
                lost_to[who].append(stream)
        for stream in sorted(set(others) - self.held - before):  # we publish, someone else claims it too
            later = [c for c in others[stream] if not c.standby]
            if later and not self.standby and (stream, later[0].name) not in self._conflicts_said:
                self._conflicts_said.add((stream, later[0].name))
                rivals[later[0].name].append(stream)
        for who, streams in standby_for.items():
            log.info("standby for stream(s) %s: converter %s claimed them first", _text(streams), who)
        for who, streams in lost_to.items():
            self._say(f"conflict: stream(s) {_text(streams)} claimed by converter {who} too (first): not publishing "
                      "them (run this one with standby = true to make it a hot standby)")
        for who, streams in rivals.items():
            self._say(f"conflict: stream(s) {_text(streams)} claimed by converter {who} too (later): it holds back")
        out = []
        for stream in sorted(before - self.held):  # the publisher went: what it did not publish goes out now
            last = self._last_seen.pop(stream, -1)
            taken = [(k, p) for seq, _, k, p in self._buffer.pop(stream, ()) if seq > last]
            log.info("took over stream %s: %d held-back chunk(s) published at once", stream_label(stream), len(taken))
            self.taken_over += 1
            out += taken
        return out

    def _say(self, msg: str) -> None:
        log.warning(msg)
        self._warn(msg)

    def watch_keys(self, setup: str) -> list[str]:
        """Power keys of every owned stream: the publisher's output on held streams is watched."""
        return [keys.power_key(setup, b, m) for b, m in sorted(self.claims.streams)]

    def seen(self, key: str, payload: bytes) -> None:
        """A power message on an owned stream, from whoever published it."""
        stream = _stream_of(key)
        if stream in self.held:  # zenoh's thread: one dict assignment, the buffer is the converter thread's
            seq = _seq_of(payload)
            if seq is not None and seq > self._last_seen.get(stream, -1):
                self._last_seen[stream] = seq

    def allow(self, key: str, payload: bytes, now_ns: int) -> bool:
        """True to publish this output now; held-back power is kept for a takeover instead."""
        if not self.held:
            return True
        stream = _stream_of(key)
        if stream is None or stream not in self.held:
            return True
        self.withheld += 1
        seq = _seq_of(payload)
        last = self._last_seen.get(stream, -1)
        buf = self._buffer.setdefault(stream, collections.deque())
        if seq is not None and seq > last:
            buf.append((seq, now_ns, key, payload))
        # Keep what the publisher has not put out yet, for holdback_s at most.
        while buf and (buf[0][1] < now_ns - self.holdback_ns or buf[0][0] <= last):
            buf.popleft()
        return False

    def conflict(self, others=None) -> bool:
        """True when another converter that is no standby claims one of this one's streams (and this is none)."""
        others = self.claims.others().items() if others is None else others
        return not self.standby and any(not c.standby for _, cs in others for c in cs)

    def status(self) -> dict:
        """``owns`` of the status and heartbeat: the part owned, and what is published or held back."""
        others = sorted(self.claims.others().items())
        shared = [f"{stream_label(s)}:{','.join(c.name for c in cs)}" for s, cs in others[:_LIST_MAX]]
        return {**self.summary, "role": "standby" if self.standby else "primary",
                "publishing": len(self.publishing), "held": _labels(self.held),
                "claimed_also_by": shared + ([f"... {len(others) - _LIST_MAX} more"] if len(others) > _LIST_MAX else []),
                "conflict": self.conflict(others), "withheld_chunks": self.withheld,
                "takeovers": self.taken_over}
