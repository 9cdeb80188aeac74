"""A publisher's history bounded in bytes ([zenoh] history_mb), over real zenoh on loopback.

Before it, a key's cache held ``history_s`` / chunk length samples whatever their size: at a high rate
or with long chunks, the sources' caches alone held history_s x the data rate.
"""

from __future__ import annotations

import time

import pytest
from converter_proc import mem_mb

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


def test_big_messages_fill_no_more_than_history_mb_per_key():
    """4 keys x 60 chunks of 819 kB (a 128-channel module at 8 kHz): 197 MB of history_s, 32 MB of history_mb.

    Measured (4 keys x 100 chunks): RSS +328 MB with no cap in bytes, +74 MB with 16 MB per key.
    """
    cap_mb, size, n_keys, n = 8, 819_200, 4, 60
    with open_session(loopback(free_tcp_port())) as z:
        pubs = Publishers(z, history_chunks=100, history_bytes=cap_mb * 1_000_000)
        payload = bytes(range(256)) * (size // 256)
        before = mem_mb()
        for _ in range(n):
            for m in range(n_keys):
                pubs.put(keys.counts_key("t", 0, m), payload)
        grown = mem_mb() - before
        pubs.close()
    # The caches (32 MB) plus zenoh's own buffers; without the cap they would hold n x size x n_keys = 197 MB.
    assert grown < n_keys * cap_mb + 48, f"RSS +{grown:.0f} MB"
