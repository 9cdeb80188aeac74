"""A converter process under a flood of made-up streams over real zenoh (loopback): memory stays bounded.

Measured before issue 18: 10,000 made-up board/module streams (20,000 tiny valid messages) grew the
converter from 195 MB to 2,006 MB for good; 10,000 made-up bias modules added 911 MB.
"""

from __future__ import annotations

import time

import numpy as np
from converter_proc import mem_mb, start_converter

from mntes_stream.io import keys
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk, PowerChunk, Provenance, StatusMessage, decode
from mntes_stream.io.transport import Publishers, QueueSubscriber, free_tcp_port, loopback, open_session
from mntes_stream.service.source import MinimalSource, SourceConfig, publish

SRC = SourceConfig(modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1)
BUDGET_MB = 100  # growth allowed under the flood (the table bank and zenoh buffers are already there)


def _wait(sub, pred, timeout_s):
    got = []
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        item = sub.get(timeout_s=0.05)
        if item is not None:
            got.append(decode(item[1]))
            if pred(got):
                return got
    raise AssertionError(f"timed out after {len(got)} messages")


def test_ten_thousand_made_up_streams_do_not_grow_the_converter(tmp_path):
    source = MinimalSource(SRC)
    # The real chunks after the flood carry the t_pub of before it: not an overload to shed here.
    proc, port, log = start_converter(tmp_path, source, rest="[alignment]\nmax_lag_s = 120.0\n")
    try:
        with open_session(loopback(None, [port])) as z:
            sub = QueueSubscriber(z, ["mntes/lab/power/**", "mntes/lab/status/**", "mntes/lab/provenance"])
            _wait(sub, lambda m: any(isinstance(x, Provenance) for x in m), 60)
            real = list(source.batches(time.time_ns(), duration_s=1.0))
            publish(z, real[:5], speed=0, wait_keys=[keys.counts_key("lab", 0, 0)])
            _wait(sub, lambda m: sum(isinstance(x, PowerChunk) for x in m) >= 10, 30)
            before = mem_mb(proc.pid)
            c = CountsChunk.from_bytes(next(p for k, p in real[0][1] if "/counts/" in k))
            pubs = Publishers(z)
            for i in range(10_000):
                b, m = 1 + i // 100, i % 100
                fake = CountsChunk("lab", b, m, c.channels, 4096 * i, c.t0_ns, c.sample_rate_hz,
                                   c.counts_i, c.counts_q, c.t_pub_ns)
                pubs.put(keys.counts_key("lab", b, m), fake.to_bytes())
                bias = HousekeepingChunk("lab", "bias", i, np.array([c.t0_ns]), np.full((1, 4), 1e-6), "V",
                                         board=b, module=m, channels=np.arange(4, dtype=np.int32))
                pubs.put(keys.hk_key("lab", keys.bias_sensor(b, m)), bias.to_bytes())
            # The real streams go on, and are converted, after the flood.
            publish(z, real[5:], speed=0)
            got = _wait(sub, lambda m: any(isinstance(x, StatusMessage) and x.bad_messages.get("unknown_stream", 0)
                                           >= 20_000 and x.chunks_converted >= 20 for x in m), 120)
            after = mem_mb(proc.pid)
            pubs.close()
            sub.close()
        status = [x for x in got if isinstance(x, StatusMessage)][-1]
        assert status.chunks_converted == 20
        # The real streams lost nothing; the made-up ones are in the ledger as rejected (one bounded entry), and
        # counted lost: they came in and no power came out.
        assert all(status.ledger[s] == {"received": 10, "done": 10} for s in ("0/0", "0/1"))
        assert status.ledger["other"] == {"received": 10_000, "rejected": {"unknown_stream": 10_000}}
        assert status.chunks_lost == status.chunks_rejected == 10_000
        print(f"converter RSS {before:.0f} -> {after:.0f} MB under the flood")
        assert after - before < BUDGET_MB, f"RSS {before:.0f} -> {after:.0f} MB"
    finally:
        proc.terminate()
        proc.wait(30)
    assert "Traceback" not in log.read_text()


def test_a_subscriber_queue_bounded_in_bytes_blocks_upstream_and_loses_nothing():
    """The recorder's policy under overload: hold at most max_bytes, slow the publisher (BLOCK), drop nothing."""
    import threading

    port = free_tcp_port()
    # 300 MB offered: more than zenoh and TCP buffer (~57 MB measured), so the publisher must wait.
    n, size, budget = 1500, 200_000, 1_000_000
    with open_session(loopback(port)) as zs, open_session(loopback(None, [port])) as zp:
        sub = QueueSubscriber(zs, ["mntes/t/big/**"], maxsize=4096, max_bytes=budget)
        pubs = Publishers(zp)
        assert pubs.wait_matching(["mntes/t/big/x"], 30.0)
        done = threading.Event()

        def publish_all():
            for i in range(n):
                pubs.put("mntes/t/big/x", i.to_bytes(4, "little") + bytes(size))
            done.set()

        threading.Thread(target=publish_all, daemon=True).start()
        time.sleep(2.0)  # nobody reads: the queue fills to its byte budget and the publisher waits
        assert not done.is_set() and sub.queued_bytes <= budget and sub.qsize() <= budget // size
        got = []
        deadline = time.monotonic() + 60
        while len(got) < n and time.monotonic() < deadline:
            item = sub.get(timeout_s=0.1)
            if item is not None:
                got.append(int.from_bytes(item[1][:4], "little"))
        assert got == list(range(n)) and sub.high_water_bytes <= budget and sub.dropped_on_close == 0
        pubs.close()
        sub.close()
