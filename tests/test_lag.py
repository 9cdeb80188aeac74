"""Lag blamed on the process that is behind: the converter's latency split at its receipt of the counts."""

from __future__ import annotations

import re

from mntes_stream.core.convert import make_converter
from mntes_stream.core.lag import who_is_behind
from mntes_stream.io.messages import StatusMessage
from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
from mntes_stream.service.source import MinimalSource, SourceConfig

T0_NS = 1_700_000_000_000_000_000


def _run(delay_of, one_batch: bool = False) -> StatusMessage:
    """A converter fed 2 s of a small array, each batch received at ``delay_of(t_pub_ns)``; its status of the
    largest latency.

    ``one_batch``: everything handed over at once, so every chunk's power leaves with the last chunk's
    receipt (a converter that held what it received)."""
    src = MinimalSource(SourceConfig(modules=2, channels=4, sample_rate_hz=152.6, chunk_s=0.1))
    src.prepare()
    pipe = ConverterPipeline(make_converter("table", {p.detector_id: p for p in src.params}),
                             PipelineConfig(setup=src.config.setup), clock=None)
    received = [[(k, p, delay_of(t)) for k, p in batch] for t, batch in src.batches(T0_NS, 2.0)]
    if one_batch:
        received = [[m for batch in received for m in batch]]
    statuses = []
    for messages in received:
        statuses += [StatusMessage.from_bytes(v) for k, v in pipe.handle_many(messages) if "/status/" in k]
    statuses.append(pipe.status())
    return max((s for s in statuses if s.arrival_p99_ms is not None), key=lambda s: s.latency_p99_ms or 0)


def test_a_source_behind_its_schedule_is_blamed_not_the_converter():
    # Every chunk reaches the converter 5 s after it was due (a simulator short of CPU, a slow link).
    st = _run(lambda t: t + 5_000_000_000)
    assert 4_990 < st.arrival_p99_ms <= 5_001 and 4_990 < st.latency_p99_ms < 5_200
    assert who_is_behind(st.latency_p99_ms, st.arrival_p99_ms).startswith("the source or its link: counts reach the "
                                                                           "converter 5.0 s after they are due")


def test_a_converter_holding_chunks_is_blamed():
    # Counts arrive on time (1 ms after due) but leave as power only with the last one, up to 2 s later.
    st = _run(lambda t: t + 1_000_000, one_batch=True)
    assert st.arrival_p99_ms < 2 and st.latency_p99_ms > 1_500
    who = who_is_behind(st.latency_p99_ms, st.arrival_p99_ms)
    assert re.fullmatch(r"the converter: it holds counts (1\.[89]|2\.0) s before their power leaves", who), who


def test_statuses_of_older_converters_without_arrival_still_decode_and_blame_nobody_wrongly():
    old = StatusMessage(setup="lab", service="converter", t_ns=1, uptime_s=1.0, interval_s=1.0, latency_p99_ms=3000.0)
    again = StatusMessage.from_bytes(old.to_bytes())
    assert again.arrival_p99_ms is None
    assert who_is_behind(again.latency_p99_ms, again.arrival_p99_ms).startswith("the converter")
    assert who_is_behind(None, None) == "" and who_is_behind(999.0, 0.0) == ""
