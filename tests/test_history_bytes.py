"""A publisher's history bounded in bytes ([zenoh] history_mb), over real zenoh on loopback.

Before it, a key's cache held ``history_s`` / chunk length samples whatever their size: at a high rate
or with long chunks, the sources' caches alone held history_s x the data rate.
"""

from __future__ import annotations

import time

import pytest

from mntes_stream.io import keys
from mntes_stream.io.history import capped_chunks
from mntes_stream.io.transport import Publishers, QueueSubscriber, ZenohSettings, free_tcp_port, loopback, open_session


def test_capped_chunks_divides_the_bytes_by_the_message_size():
    assert capped_chunks(100, 10_000, 1_000) == 10
    assert capped_chunks(5, 10_000, 1_000) == 5        # history_s holds fewer: that stands
    assert capped_chunks(100, 10_000, 50_000) == 1     # one message always
    assert capped_chunks(100, 0, 1_000) == 100         # no cap in bytes
    assert capped_chunks(0, 10_000, 1_000) == 0        # no cache stays no cache


def test_history_mb_setting():
    assert ZenohSettings().history_bytes == 16_000_000
    assert ZenohSettings(history_mb=0).history_bytes == 0
    assert ZenohSettings(history_mb=2.5).over(ZenohSettings()).history_bytes == 2_500_000


def _late_subscriber_gets(history_bytes: int, n: int, size: int) -> list[int]:
    """Publish ``n`` messages of ``size`` bytes with a 100-sample history, then a late subscriber asks for it."""
    port = free_tcp_port()
    key = keys.counts_key("t", 0, 0)
    with open_session(loopback(port)) as zp:
        pubs = Publishers(zp, history_chunks=100, history_bytes=history_bytes)
        for i in range(n):
            pubs.put(key, i.to_bytes(4, "little") + bytes(size - 4))
        with open_session(loopback(None, [port])) as zs:
            sub = QueueSubscriber(zs, ["mntes/t/counts/**"], recover="history")
            got, deadline = [], time.monotonic() + 10
            while time.monotonic() < deadline:
                item = sub.get(timeout_s=0.1)
                if item is not None:
                    got.append(int.from_bytes(item[1][:4], "little"))
                elif got and time.monotonic() > deadline - 8:
                    break
            sub.close()
        pubs.close()
    return got


@pytest.mark.parametrize(("history_bytes", "kept"), [(0, 50), (10 * 20_000, 10)])
def test_a_late_subscriber_gets_what_the_byte_budget_kept(history_bytes, kept):
    got = _late_subscriber_gets(history_bytes, n=50, size=20_000)
    assert got == list(range(50 - kept, 50))
