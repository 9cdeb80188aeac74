"""A converter process under rounds of a malformed-message flood over real zenoh (loopback): memory stays bounded.

Measured before (issue 33), 1,500 malformed 400 kB messages a round, 2-core machine at load 8-11: the
converter's RSS after round 1 and after the last, 269 -> 335 MB (5 rounds), 239 -> 403 (6), 256 -> 456 (3),
never given back. Two causes: the receive queue was bounded in messages only (4096: up to 4096 x their
size whenever the converter fell behind the flood), and glibc keeps what a burst freed in its heaps.
Now the queue is bounded in bytes too ([converter] queue_mb; beyond, back-pressure) and an idle converter
gives freed heap back (service/heap.py trim_heap).
"""

from __future__ import annotations

import os
import time

from converter_proc import mem_mb, start_converter

from mntes_stream.io import keys
from mntes_stream.io.messages import Provenance, StatusMessage, decode
from mntes_stream.io.transport import Publishers, QueueSubscriber, loopback, open_session
from mntes_stream.service.source import MinimalSource, SourceConfig

SRC = SourceConfig(modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1)
ROUNDS, PER_ROUND, SIZE = 5, 1500, 400_000  # 600 MB a round: 37 times the queue's budget
QUEUE_MB = 16  # [converter] queue_mb: the queue holds this much, a batch out of it as much again
PEAK_MB = 2 * QUEUE_MB + 160  # peak RSS (VmHWM) over RSS before: + zenoh's buffers, the heap's pad (measured +73..143)
SETTLED_MB = 112  # RSS after the last round (idle: trimmed) over RSS before (measured +53..78; before: +145..266)
SETTLE_S = 2.5  # idle this long after a round: the converter trims its heap every 2 s when idle


def test_rounds_of_malformed_messages_do_not_grow_the_converter(tmp_path):
    proc, port, log = start_converter(tmp_path, MinimalSource(SRC), converter=f"queue_mb = {QUEUE_MB}\n")
    rss = []
    try:
        with open_session(loopback(None, [port])) as z:
            sub = QueueSubscriber(z, ["mntes/lab/status/**", "mntes/lab/provenance"])
            deadline = time.monotonic() + 120
            while not any(isinstance(decode(i[1]), Provenance) for i in [sub.get(timeout_s=0.1)] if i):
                assert time.monotonic() < deadline and proc.poll() is None, log.read_text()[-2000:]
            time.sleep(SETTLE_S)
            before, peak_before = mem_mb(proc.pid), mem_mb(proc.pid, "VmHWM")
            pubs = Publishers(z)
            key = keys.counts_key("lab", 0, 0)
            garbage = b"\xc1" + os.urandom(SIZE - 1)  # 0xc1: never valid msgpack
            for r in range(1, ROUNDS + 1):
                for _ in range(PER_ROUND):
                    pubs.put(key, garbage)
                # The round is over when the converter has counted all of it (status every 0.5 s).
                deadline, malformed = time.monotonic() + 60, 0
                while malformed < r * PER_ROUND:
                    assert time.monotonic() < deadline, f"round {r}: {malformed} counted"
                    item = sub.get(timeout_s=0.1)
                    if item is not None and isinstance(st := decode(item[1]), StatusMessage):
                        malformed = st.bad_messages.get("malformed", 0)
                time.sleep(SETTLE_S)
                rss.append(mem_mb(proc.pid))
            peak = mem_mb(proc.pid, "VmHWM")  # since the start; the start's own peak is about its RSS
            pubs.close()
            sub.close()
        assert malformed == ROUNDS * PER_ROUND  # every one counted, none lost on the way
        figures = (f"RSS {before:.0f} MB before the flood (peak {peak_before:.0f}), {[round(x) for x in rss]} after "
                   f"each round, peak {peak:.0f}")
        print(figures)
        assert peak - before < PEAK_MB, figures
        assert rss[-1] - before < SETTLED_MB, figures
    finally:
        proc.terminate()
        proc.wait(30)
    assert "Traceback" not in log.read_text()
