"""What the monitor shows of each converter's ledger: pure, status messages in, JSON-ready dicts out.

A converter's status carries its ledger (``ledger``: ``"<board>/<module>"`` ->
the columns of :class:`~mntes_stream.core.ledger.StreamLedger`) and the
counters ``chunks_shed``, ``chunks_late``, ``chunks_set_aside``. The monitor
shows, per converter and per stream, the columns converted, late, shed,
rejected, duplicate, never received, lost (``never received + shed +
rejected``: :data:`~mntes_stream.core.ledger.LOST_MEANS`) and pending, and a
converter is *shedding* while it holds chunks set aside or its shed count grew
within the last ``shedding_recent_s``. A converter that took some streams
neither from their first chunk nor from a checkpoint (status ``began_at``:
it started, or restarted, after their first chunks left the sources' history)
is said with the numbers it began at (``began_line``).
"""

from __future__ import annotations

from mntes_stream.core.ledger import LOST_MEANS, StreamLedger, stream_order, summary_line

__all__ = ["COLUMNS", "LOST_MEANS", "ShedWatch", "began_line", "conflict_text", "ledger_view", "row_of"]

#: Columns of a row, in the order the page and the table show them.
COLUMNS = ("converted", "late", "shed", "rejected", "duplicate", "never_received", "lost", "pending")


def row_of(s: StreamLedger) -> dict:
    """One stream's (or the totals') columns, JSON-ready."""
    return {"received": s.received, "converted": s.done, "late": s.late, "shed": s.shed_total,
            "rejected": s.rejected_total, "duplicate": s.duplicate, "never_received": s.missing, "lost": s.lost,
            "pending": s.pending, "shed_by": dict(s.shed), "rejected_by": dict(s.rejected)}


def _parse(columns) -> StreamLedger | None:
    try:
        return StreamLedger.from_dict(columns)
    except (TypeError, ValueError, AttributeError):  # decoded and checked as a map already: a stray shape
        return None


def began_line(began_at: dict, most: int = 8) -> str:
    """What a converter's ``began_at`` says, in one line ("" when empty)."""
    if not began_at:
        return ""
    items = sorted(began_at.items(), key=lambda kv: stream_order(str(kv[0])))
    text = ", ".join(f"{s} at seq {n}" for s, n in items[:most])
    more = f" and {len(items) - most} more" if len(items) > most else ""
    return (f"began {text}{more} (no checkpoint): what came before never reached this converter; a recording of "
            "the counts has them, and offline convert gives their power")


def conflict_text(conflicts: dict, most: int = 8) -> str:
    """What a converter's ``conflicts`` says, in one line ("" when empty)."""
    if not conflicts:
        return ""
    items = sorted(conflicts.items(), key=lambda kv: stream_order(str(kv[0])))
    text = ", ".join(f"{s} by {n}" for s, n in items[:most]) + (", ..." if len(items) > most else "")
    return (f"CONFLICT: streams sent by more than one publisher side by side ({text}): each one's chunks are "
            "numbered apart; two sources or bridges on one setup?")


def ledger_view(ledger: dict, max_streams: int, began_at: dict | None = None,
                conflicts: dict | None = None) -> dict | None:
    """The ledger of one status, reduced for the page.

    Parameters
    ----------
    ledger : dict
        A status's ``ledger`` (stream -> columns).
    max_streams : int
        Streams listed at most: those with something lost, shed or rejected first, then in order.
    began_at : dict, optional
        A status's ``began_at`` (stream -> the first sequence number the converter took).
    conflicts : dict, optional
        A status's ``conflicts`` (stream -> publishers sending it side by side).

    Returns
    -------
    dict or None
        None for an empty ledger (a converter of an earlier version); else ``totals`` and ``streams``
        (rows of :func:`row_of` plus ``stream``), ``streams_total``, ``unreadable`` (streams whose
        columns could not be read), ``line`` (the one-line summary), ``lost_means`` and ``began_line``
        (:func:`began_line`; "" when the converter began every stream at its start) and ``conflict_line``
        (:func:`conflict_text`).
    """
    if not ledger:
        return None
    total = StreamLedger()
    rows, unreadable = [], 0
    for stream, columns in ledger.items():
        s = _parse(columns)
        if s is None:
            unreadable += 1
            continue
        total.add(s)
        rows.append({"stream": str(stream), **row_of(s)})
    rows.sort(key=lambda r: (-(r["lost"] + r["shed"] > 0), stream_order(r["stream"])))
    return {"totals": row_of(total), "streams": rows[:max_streams], "streams_total": len(rows),
            "unreadable": unreadable, "line": summary_line(total, "converted"), "lost_means": LOST_MEANS,
            "began_line": began_line(began_at or {}), "conflict_line": conflict_text(conflicts or {})}


class ShedWatch:
    """When each service's shed count last grew (receive clock), to say SHEDDING for a while after."""

    def __init__(self):
        self._seen: dict[str, tuple[int, int | None]] = {}  # service -> (shed count, t_recv_ns of its last growth)

    def observe(self, service: str, shed: int, t_recv_ns: int) -> None:
        prev = self._seen.get(service)
        if prev is None:
            # A first status that already counts shed chunks: they were shed at some time before it.
            self._seen[service] = (shed, int(t_recv_ns) if shed > 0 else None)
        elif shed > prev[0]:
            self._seen[service] = (shed, int(t_recv_ns))
        else:
            self._seen[service] = (shed, prev[1])  # a restarted converter counts from 0 again

    def forget(self, service: str) -> None:
        self._seen.pop(service, None)

    def shed_recently(self, service: str, now_ns: int, within_s: float) -> bool:
        seen = self._seen.get(service)
        return seen is not None and seen[1] is not None and now_ns - seen[1] <= within_s * 1e9
