"""zenoh's own history and recovery (``zenoh.ext``): what a restarted recorder or a router restart would miss.

A plain zenoh publication reaches the subscribers that are connected at that
moment, and no one else: a recorder restarting after a crash, or every
client while their router restarts, loses what was published meanwhile. The
sources (source, simulator, bridges, replay) therefore publish counts and
housekeeping with zenoh's ``AdvancedPublisher``: each key keeps its last
``history_chunks`` samples in a cache and announces its sequence numbers in a
heartbeat. A recorder subscribes with ``AdvancedSubscriber``: at start it asks
every publisher (and one that appears later) for its cache (``history``), and
it recovers samples it missed from the caches when a heartbeat or a later
sample shows the gap (``recovery``). What cannot be recovered (older than the
cache) stays a sequence gap, counted as never received.

The cache holds ``history_s`` of data per key (``[zenoh] history_s``): about
``history_s`` x the array's data rate of memory in the publisher, and at most
``[zenoh] history_mb`` per key (16 MB unless set): a key's cache keeps
``history_mb`` / (the size of its first message) samples when that is fewer,
so big messages (a high sample rate, long chunks) cannot make the caches
grow beyond ``history_mb`` x the keys published. The
converter caches its power too (``history_s`` / ``POWER_CHUNK_S`` chunks per
key), so a restarted recorder also records the power published while it was
down.
"""

from __future__ import annotations

import math

from mntes_stream.io import keys

__all__ = ["HISTORY_KINDS", "POWER_CHUNK_S", "cache_chunks", "capped_chunks", "declare_history_publisher", "declare_recovering_subscriber"]

# The data, and the converter's power (a recorder restarted after a crash records the power published meanwhile);
# status and provenance are periodic.
HISTORY_KINDS = ("counts", "hk", "power")
POWER_CHUNK_S = 0.1  # the converter does not know its streams' chunk length before they come: caches assume this
_HEARTBEAT_S = 0.5  # how soon a subscriber learns of a sample it missed when no later sample comes


def cache_chunks(history_s: float, chunk_s: float) -> int:
    """Samples per key a publisher keeps for ``history_s`` of chunks ``chunk_s`` long (0: no cache)."""
    if history_s <= 0 or chunk_s <= 0:
        return 0
    return max(1, math.ceil(history_s / chunk_s))


def capped_chunks(max_chunks: int, max_bytes: int, message_bytes: int) -> int:
    """``max_chunks``, or fewer so that as many messages of ``message_bytes`` fit in ``max_bytes`` (at least 1).

    A cap of 0, or a size not known (0), leaves ``max_chunks``; ``max_chunks`` 0 (no cache) stays 0.
    """
    if max_chunks <= 0 or max_bytes <= 0 or message_bytes <= 0:
        return max(0, int(max_chunks))
    return max(1, min(int(max_chunks), int(max_bytes) // int(message_bytes)))


def wants_history(key: str) -> bool:
    return keys.kind_of(key) in HISTORY_KINDS


def declare_history_publisher(session, key: str, encoding, congestion_control, max_samples: int):
    """An ``AdvancedPublisher`` on ``key`` with a cache of ``max_samples``, heartbeat and publisher detection."""
    import zenoh.ext as zx

    return zx.declare_advanced_publisher(
        session, key, encoding=encoding, congestion_control=congestion_control,
        cache=zx.CacheConfig(max_samples=int(max_samples)),
        sample_miss_detection=zx.MissDetectionConfig(heartbeat=_HEARTBEAT_S, sporadic_heartbeat=None),
        publisher_detection=True)


def declare_recovering_subscriber(session, key_expr: str, handler, history: bool):
    """An ``AdvancedSubscriber``: missed samples recovered from the publishers' caches; with ``history``,
    each publisher's cache asked for at start and whenever a publisher appears. (What cannot be recovered,
    a gap longer than the cache, shows in the stream's own sequence numbers: ``core.sequence``.)
    """
    import zenoh.ext as zx

    return zx.declare_advanced_subscriber(
        session, key_expr, handler,
        history=zx.HistoryConfig(detect_late_publishers=True) if history else None,
        recovery=zx.RecoveryConfig(heartbeat=True, periodic_queries=None))
