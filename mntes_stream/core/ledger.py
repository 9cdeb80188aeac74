"""Where every chunk of every stream went: the ledger.

Every stage that takes chunks (the converter, offline ``convert``, the
recorder, a bridge) keeps one :class:`Ledger`. For every stream
(``"<board>/<module>"``) each chunk it received is in exactly one column:

- ``done``: converted live (recorded, published: the stage's own verb);
- ``late``: set aside under overload, converted later (published as late power);
- ``shed``: set aside under overload and given up, by reason (the counts are
  recorded: offline ``convert`` gives their power);
- ``rejected``: refused, by reason (malformed, internal error, ...);
- ``duplicate``: a chunk received twice (dropped);
- ``pending``: still held (waiting for housekeeping, or set aside): zero
  once a stage has finished.

so ``received = done + late + shed + rejected + duplicate + pending``, and
besides, ``missing``: sequence numbers never received (gaps at the source or
on the way; a chunk that comes late is no longer missing), and ``again``: of
the chunks received, those a converter restarted from its checkpoint took
again because its predecessor may not have sent their power (the
predecessor's last status interval): :func:`merge_restarts` counts each once
over the two processes.

**Lost** means one thing everywhere: chunks of a stream for which the stage
put out nothing, ``lost = missing + shed + rejected``. A summary that says
``lost 0`` means nothing was missed, shed or rejected.

>>> led = Ledger("converted")
>>> led.received("0/1", 5); led.done("0/1", 3); led.shed("0/1", "overload"); led.duplicate("0/1")
>>> led.set_missing("0/1", 2)
>>> t = led.totals()
>>> t.received, t.done, t.shed_total, t.duplicate, t.pending, t.lost
(5, 3, 1, 1, 0, 3)
>>> led.line()
'received 5 chunks: converted 3, shed 1 (overload 1), duplicate 1; never received 2; lost 3 of 7'
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from mntes_stream.core.shards import StreamKey

__all__ = ["Ledger", "StreamLedger", "OTHER", "LOST_MEANS", "HELD_AT_KILL", "merge_restarts", "stream_order", "summary_line",
           "totals_of"]

OTHER = "other"  # chunks of streams a stage does not keep (unknown streams): one bounded entry
LOST_MEANS = "lost = never received + shed + rejected (chunks the stage put out nothing for)"
_INTS = ("received", "done", "late", "duplicate", "missing", "again")
# The shed reason of chunks a killed converter held that its successor never received again (merge_restarts).
HELD_AT_KILL = "held at a kill"


@dataclass
class StreamLedger:
    """One stream's columns (see the module docstring); ``shed`` and ``rejected`` count by reason."""

    received: int = 0
    done: int = 0
    late: int = 0
    duplicate: int = 0
    missing: int = 0
    again: int = 0  # of received: taken again after a restart (see the module docstring)
    shed: Counter = field(default_factory=Counter)
    rejected: Counter = field(default_factory=Counter)

    @property
    def shed_total(self) -> int:
        return sum(self.shed.values())

    @property
    def rejected_total(self) -> int:
        return sum(self.rejected.values())

    @property
    def pending(self) -> int:
        """Received and not yet in another column (held); never negative in a consistent ledger."""
        return self.received - self.done - self.late - self.shed_total - self.rejected_total - self.duplicate

    @property
    def lost(self) -> int:
        return self.missing + self.shed_total + self.rejected_total

    def add(self, other: StreamLedger) -> None:
        for name in _INTS:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.shed.update(other.shed)
        self.rejected.update(other.rejected)

    def as_dict(self) -> dict:
        """Non-zero columns only (``received`` always), plus ``pending``: compact for status messages."""
        d = {name: getattr(self, name) for name in _INTS if name == "received" or getattr(self, name)}
        if self.shed:
            d["shed"] = dict(self.shed)
        if self.rejected:
            d["rejected"] = dict(self.rejected)
        if self.pending:
            d["pending"] = self.pending
        return d

    @classmethod
    def from_dict(cls, d: dict) -> StreamLedger:
        return cls(**{name: int(d.get(name, 0)) for name in _INTS},
                   shed=Counter({str(k): int(v) for k, v in (d.get("shed") or {}).items()}),
                   rejected=Counter({str(k): int(v) for k, v in (d.get("rejected") or {}).items()}))


class Ledger:
    """Per-stream ledgers of one stage.

    Parameters
    ----------
    verb : str
        What the stage does with a chunk (``converted``, ``recorded``, ``published``): the name of the
        ``done`` column in :meth:`line`.
    """

    def __init__(self, verb: str = "converted"):
        self.verb = str(verb)
        self.streams: dict[str, StreamLedger] = {}
        self._by_tuple: dict[tuple, StreamLedger] = {}  # (board, module) -> its ledger: no key string per chunk

    def _s(self, stream) -> StreamLedger:
        s = self._by_tuple.get(stream) if type(stream) is tuple else None
        if s is not None:
            return s
        key = stream if isinstance(stream, str) else str(StreamKey(*stream))
        s = self.streams.get(key)
        if s is None:
            s = self.streams[key] = StreamLedger()
        if type(stream) is tuple and len(self._by_tuple) < 1 << 16:
            self._by_tuple[stream] = s
        return s

    def received(self, stream, n: int = 1) -> None:
        self._s(stream).received += int(n)

    def done(self, stream, n: int = 1, late: bool = False) -> None:
        s = self._s(stream)
        if late:
            s.late += int(n)
        else:
            s.done += int(n)

    def shed(self, stream, reason: str, n: int = 1) -> None:
        self._s(stream).shed[str(reason)] += int(n)

    def rejected(self, stream, reason: str, n: int = 1) -> None:
        self._s(stream).rejected[str(reason)] += int(n)

    def duplicate(self, stream, n: int = 1) -> None:
        self._s(stream).duplicate += int(n)

    def again(self, stream, n: int = 1) -> None:
        """Chunks received again after a restart (see the module docstring); also counted as received."""
        self._s(stream).again += int(n)

    def set_missing(self, stream, n: int) -> None:
        """Sequence numbers of the stream never received, as its tracker counts them now (not cumulative)."""
        self._s(stream).missing = max(int(n), 0)

    def totals(self) -> StreamLedger:
        total = StreamLedger()
        for s in self.streams.values():
            total.add(s)
        return total

    @property
    def lost(self) -> int:
        return self.totals().lost

    def balanced(self) -> bool:
        """Every chunk received is in a column other than pending, for every stream."""
        return all(s.pending == 0 for s in self.streams.values())

    def as_dict(self) -> dict[str, dict]:
        """``{stream: columns}`` (:meth:`StreamLedger.as_dict`), streams in order."""
        return {k: self.streams[k].as_dict() for k in sorted(self.streams, key=stream_order)}

    @classmethod
    def from_dict(cls, d: dict, verb: str = "converted") -> Ledger:
        led = cls(verb)
        for k, v in (d or {}).items():
            led.streams[str(k)] = StreamLedger.from_dict(v)
        return led

    def merge(self, other: Ledger) -> None:
        """Add another ledger's streams (recorder shards, converter shards) into this one."""
        for k, s in other.streams.items():
            self._s(k).add(s)

    def line(self) -> str:
        """The whole ledger in one line: what a final summary says (zero columns left out, lost always)."""
        return summary_line(self.totals(), self.verb)


def merge_restarts(ledgers) -> Ledger:
    """One ledger over the successive processes of one converter, each chunk counted once.

    ``ledgers``: each process's ledger, in order, as its last status said (the last process's may be its
    final one). Every process but the last died, and its successor resumed from the checkpoint written with
    that last status (``pipeline.ConverterPipeline.sequence_state``): each stream's newest number converted
    below what was held, floored at the status before. Of a stream:

    - the chunks between the floor and that number, the dead process had converted; its successor takes them
      again from the sources' caches (``again``, oldest first gone where the caches no longer hold them):
      converted by both, so taken out of the dead process's received and converted;
    - what the dead process held (``pending``: waiting for housekeeping, set aside) lies above that number:
      the successor converts it like any chunk after the checkpoint, or counts it never received (missed
      while down) when the caches no longer hold it. Either way its ledger has it, so it goes from the dead
      process's. Where the successor never received a chunk of the stream at all, it is shed there, reason
      ``held at a kill`` (lost, never silently).
    """
    ledgers = list(ledgers)
    whole = Ledger(ledgers[-1].verb if ledgers else "converted")
    for k, led in enumerate(ledgers):
        succ = ledgers[k + 1] if k + 1 < len(ledgers) else None
        for key, s in led.streams.items():
            s = StreamLedger.from_dict(s.as_dict())
            if succ is not None:
                held = max(s.pending, 0)
                nxt = succ.streams.get(key)
                both = min(nxt.again if nxt is not None else 0, s.done + s.late)
                from_done = min(both, s.done)
                s.done -= from_done
                s.late -= both - from_done
                if nxt is not None and nxt.received + nxt.missing > 0:
                    s.received -= both + held
                else:
                    s.received -= both
                    s.shed[HELD_AT_KILL] += held
            whole._s(key).add(s)
    return whole


def summary_line(t: StreamLedger, verb: str = "converted") -> str:
    """One line for a stream's (or all streams') columns; see :meth:`Ledger.line`."""
    parts = [f"{verb} {t.done}"]
    if t.late:
        parts.append(f"late {t.late}")
    for name, counter in (("shed", t.shed), ("rejected", t.rejected)):
        if counter:
            reasons = ", ".join(f"{r} {n}" for r, n in sorted(counter.items()))
            parts.append(f"{name} {sum(counter.values())} ({reasons})")
    if t.duplicate:
        parts.append(f"duplicate {t.duplicate}")
    if t.pending:
        parts.append(f"pending {t.pending}")
    text = f"received {t.received} chunks: {', '.join(parts)}"
    if t.missing:
        text += f"; never received {t.missing}"
    return f"{text}; lost {t.lost} of {t.received + t.missing}"


def stream_order(key: str):
    """Sort key of stream names: ``"<board>/<module>"`` numerically, then any other name."""
    stream = StreamKey.parse(key)
    return (0, *stream) if stream is not None else (1, key)


def totals_of(ledger_dict: dict) -> StreamLedger:
    """Totals of a ledger in its dict form (a status message's ``ledger``)."""
    total = StreamLedger()
    for v in (ledger_dict or {}).values():
        total.add(StreamLedger.from_dict(v))
    return total

