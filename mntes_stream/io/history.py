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

__all__ = ["HISTORY_KINDS", "POWER_CHUNK_S", "HistoryTopUp", "cache_chunks", "capped_chunks",
           "declare_history_publisher", "declare_recovering_subscriber"]

# The data, and the converter's power (a recorder restarted after a crash records the power published meanwhile);
# status and provenance are periodic.
HISTORY_KINDS = ("counts", "hk", "power")
POWER_CHUNK_S = 0.1  # the converter does not know its streams' chunk length before they come: caches assume this
_SAID = 8  # keys asked again with a line each (a source without caches would give one per key of the array)
# A first message published less than this before the subscriber was declared may still be a live one (in flight
# as the subscription arrived) or the tail of a history zenoh cut short: its key's cache is asked too. A CI run of
# bench chaos saw a restarted recorder's first message of one stream of four, published 1.3 s before, arrive with
# the 1.3 s after it and none of the 8.7 s of cache before (the others' history began 10 s back).
_MAYBE_LIVE_NS = 3_000_000_000
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


class HistoryTopUp:
    """Asks a publisher's cache again for a key whose history zenoh dropped.

    zenoh-ext's ``AdvancedSubscriber`` (1.x, ``handle_sample``) asks a publisher
    it learns of late (liveliness) for its cache, but where a live sample of
    that publisher arrives before the cache's replies it delivers the sample,
    and then drops the replies as older than it: a recorder restarted while
    the sources publish then lacks, for some keys, what the caches held
    (seen in ``bench chaos``: one stream of four, 100 chunks, in a recorder;
    three of four in a converter). Here the first message of each key after
    the subscriber was declared is looked at: one published after that moment,
    or less than 3 s before it (in flight as the subscription arrived, or the
    tail of a history cut short: ``_MAYBE_LIVE_NS``), with a sequence number
    above 0 (housekeeping, which has no publish time: its first sample's time)
    means the history may not have come first, so
    that key's cache is asked directly (``<key>/@adv/pub/**``, the
    ``AdvancedPublisher``'s queryable) and its messages numbered before the
    first one received join the queue.
    Messages from the cache are never counted twice: the earlier ones only.
    ``QueueSubscriber(recover="history")`` (callback mode) does this for every
    message it hands out.

    Parameters
    ----------
    session, subscriber
        The zenoh session and the ``QueueSubscriber`` (callback mode) the replies join.
    declared_ns : int
        Wall-clock time (ns) the subscriber was declared.
    max_keys : int
        Keys remembered (a bound on memory; beyond it no key is looked at).
    """

    def __init__(self, session, subscriber, declared_ns: int, max_keys: int = 100_000):
        self._session, self._sub, self._declared_ns = session, subscriber, int(declared_ns)
        self._seen: set[str] = set()
        self._max_keys = int(max_keys)
        self.asked: list[tuple[str, int]] = []  # (key, first sequence number received)

    def first(self, key: str, payload: bytes) -> str | None:
        """Look at a received message; the line to log when its key's cache was asked again, else None."""
        if key in self._seen or len(self._seen) >= self._max_keys:
            return None
        self._seen.add(key)
        if not wants_history(key):
            return None
        from mntes_stream.io.mcap.envelope import peek_envelope

        env = peek_envelope(payload)
        published_ns = env.publish_time_ns
        if published_ns is None and env.seq and not env.problem:
            published_ns = _first_sample_ns(payload)  # housekeeping: no publish time, its first sample's
        if env.problem or not env.seq or published_ns is None or published_ns < self._declared_ns - _MAYBE_LIVE_NS:
            return None  # the history came first (or the key starts here): nothing missed
        first, age_s = env.seq, max(self._declared_ns - published_ns, 0) / 1e9

        def earlier(reply: bytes) -> bool:
            seq = peek_envelope(reply).seq
            return seq is not None and seq < first

        self._sub.query(self._session, f"{key}/@adv/pub/**", timeout_s=5.0, keep=earlier)
        self.asked.append((key, first))
        if len(self.asked) > _SAID:
            return None if len(self.asked) > _SAID + 1 else (
                f"{key} and further keys whose first message was live: their publishers' caches asked again too "
                "(no line each)")
        return (f"{key}: its first message (seq {first}) was live or nearly (published {age_s:.1f} s before this "
                f"subscription), zenoh's history of it did not come first: asked its publisher's cache for the "
                f"messages before it")


def _first_sample_ns(payload: bytes) -> int | None:
    """A message's first sample time (ns) when it has sample times (housekeeping), else None; never raises."""
    from mntes_stream.io.messages import decode

    try:
        t = getattr(decode(payload), "t_ns", None)
        return int(t[0]) if t is not None and len(t) else None
    except Exception:  # noqa: BLE001 - a message the converter will reject: nothing to ask for
        return None
