"""A key whose zenoh history did not come first is asked of its publisher's cache again (io/history.HistoryTopUp).

zenoh-ext 1.x drops a late-detected publisher's cached samples when one of its live samples arrived first
(``bench chaos`` saw a restarted recorder miss 100 chunks of one stream of four). Here, over real zenoh on
loopback, a subscriber without history stands in for that outcome: the top-up must bring exactly the
messages before the first live one, once each, and ask nothing where nothing was missed.
"""

from __future__ import annotations

import contextlib
import time

import msgpack

from mntes_stream.io import keys
from mntes_stream.io.history import HistoryTopUp
from mntes_stream.io.transport import Publishers, QueueSubscriber, free_tcp_port, loopback, open_session


def _msg(seq: int, t_pub_ns: int | None = None) -> bytes:
    return msgpack.packb({"schema": "mntes.counts", "version": 1, "seq": seq,
                          "t_pub_ns": time.time_ns() if t_pub_ns is None else t_pub_ns})


def _seqs(sub, seconds: float) -> list[int]:
    got, deadline = [], time.monotonic() + seconds
    while time.monotonic() < deadline:
        item = sub.get(timeout_s=0.05)
        if item is not None:
            got.append(msgpack.unpackb(item[1])["seq"])
    return got


@contextlib.contextmanager
def _twenty_cached(key: str):
    """Publishers whose cache holds ``key``'s seq 0..19, and a second session connected to them."""
    port = free_tcp_port()
    with open_session(loopback(port)) as zp:
        pubs = Publishers(zp, history_chunks=100)
        for i in range(20):
            pubs.put(key, _msg(i))
        try:
            with open_session(loopback(None, [port])) as zs:
                yield pubs, zs
        finally:
            pubs.close()


def test_a_live_first_message_brings_the_cached_ones_before_it_once_each():
    key, other = keys.counts_key("t", 0, 0), keys.counts_key("t", 0, 1)
    with _twenty_cached(key) as (pubs, zs):
        sub = QueueSubscriber(zs, ["mntes/t/**"])  # no history: as when zenoh dropped it
        top_up = HistoryTopUp(zs, sub, time.time_ns())
        time.sleep(1.0)  # the subscription reaches the publisher
        pubs.put(key, _msg(20))
        pubs.put(other, _msg(0))  # a key that starts here: nothing before it to ask for
        first = [sub.get(timeout_s=5.0) for _ in range(2)]
        assert sorted(k for k, *_ in first) == [key, other]
        said = [top_up.first(k, p) for k, p, *_ in first]
        assert [s is not None for s in said] == [k == key for k, *_ in first], said
        assert top_up.asked == [(key, 20)]
        assert _seqs(sub, 2.0) == list(range(20))  # the cache's 0..20, less the one already here
        assert top_up.first(key, _msg(21)) is None  # a key is looked at once
        sub.close()


def test_a_first_message_from_the_history_asks_nothing():
    port = free_tcp_port()
    key = keys.counts_key("t", 0, 0)
    with open_session(loopback(port)) as zp:
        pubs = Publishers(zp, history_chunks=100)
        for i in range(5):
            pubs.put(key, _msg(i))
        with open_session(loopback(None, [port])) as zs:
            declared = time.time_ns()
            sub = QueueSubscriber(zs, ["mntes/t/**"], recover="history")
            item = sub.get(timeout_s=5.0)
            assert item is not None and msgpack.unpackb(item[1])["seq"] == 0
            top_up = HistoryTopUp(zs, sub, declared)
            assert top_up.first(item[0], item[1]) is None and top_up.asked == []
            assert _seqs(sub, 1.0) == [1, 2, 3, 4]
            sub.close()
        pubs.close()


def test_a_source_without_caches_gives_a_few_lines_not_one_per_key():
    """Every key's first message is live where the sources keep no cache: each is asked, eight said, then one line."""
    port = free_tcp_port()
    with open_session(loopback(port)) as zs:
        sub = QueueSubscriber(zs, ["mntes/t/**"])
        top_up = HistoryTopUp(zs, sub, time.time_ns() - 1)
        said = [top_up.first(keys.counts_key("t", 0, m), _msg(7)) for m in range(12)]
        assert len(top_up.asked) == 12
        assert [s is not None for s in said] == [True] * 9 + [False] * 3
        assert "further keys" in said[8] and all("seq 7" in s for s in said[:8])
        assert _seqs(sub, 0.5) == []  # nobody answers
        sub.close()


def test_a_first_message_published_just_before_the_subscription_still_brings_the_ones_before_it():
    """CI's bench chaos: a restarted recorder's first message of a stream was published 1.3 s before its
    subscription (the tail of a history cut short), and the 8.7 s of cache before it never came. A first message
    that recent has its key's cache asked; one from further back (a history that began there) does not."""
    key, old_key = keys.counts_key("t", 0, 0), keys.counts_key("t", 0, 1)
    with _twenty_cached(key) as (_, zs):
        declared = time.time_ns()
        sub = QueueSubscriber(zs, ["mntes/t/**"])  # no history: as when zenoh cut it short
        top_up = HistoryTopUp(zs, sub, declared)
        time.sleep(1.0)  # the subscription reaches the publisher
        # The first of each key as the cut history gave it: seq 15 published 1.3 s before the subscription,
        # and seq 3 of a key whose history began 8 s back.
        assert top_up.first(key, _msg(15, declared - 1_300_000_000)) is not None
        assert top_up.first(old_key, _msg(3, declared - 8_000_000_000)) is None
        assert top_up.asked == [(key, 15)]
        assert _seqs(sub, 2.0) == list(range(15))  # the cache's 0..14, once each
        sub.close()
