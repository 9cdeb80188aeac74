"""Which process is behind: the converter's latency split at its receipt of the counts.

A power chunk's latency runs from its counts' due time (the source's
publication stamp, on the data clock) to the power's publication. The
converter also knows when the counts reached it, so the latency splits into
the *arrival* (a source behind its schedule, or a slow link) and the
converter's own share (its queue and conversion). Blaming the converter for
the whole of it sent a lab after the wrong process: a simulator short of
CPU made 40 s of "converter lag" while the converter idled.
"""

from __future__ import annotations

__all__ = ["BEHIND_AFTER_MS", "who_is_behind"]

#: a latency (99th percentile) below this is not "behind"
BEHIND_AFTER_MS = 1000.0


def who_is_behind(latency_p99_ms: float | None, arrival_p99_ms: float | None,
                  after_ms: float = BEHIND_AFTER_MS) -> str:
    """"" when the latency is under ``after_ms``, else which side holds the most of it, in words.

    >>> who_is_behind(41313.0, 41200.0)
    'the source or its link: counts reach the converter 41.2 s after they are due'
    >>> who_is_behind(5000.0, 20.0)
    'the converter: it holds counts 5.0 s before their power leaves'
    >>> who_is_behind(200.0, 150.0)
    ''
    """
    if latency_p99_ms is None or latency_p99_ms < after_ms:
        return ""
    arrival_ms = max(arrival_p99_ms or 0.0, 0.0)
    own_ms = latency_p99_ms - arrival_ms
    if arrival_ms >= own_ms:
        return f"the source or its link: counts reach the converter {arrival_ms / 1e3:.1f} s after they are due"
    return f"the converter: it holds counts {own_ms / 1e3:.1f} s before their power leaves"
