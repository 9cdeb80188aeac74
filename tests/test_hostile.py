"""Hostile peers on the converter's keys: well-formed messages that used to poison, stall or bloat it.

Each case was measured on the landed code before this fix (issue 18); here each is the converter core
fed the real source's messages plus the hostile ones, compared with the same run without them.
"""

from __future__ import annotations

import numpy as np
import pytest

from mntes_stream.core import flags as fl
from mntes_stream.core.convert import make_converter
from mntes_stream.io import keys
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk, decode
from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
from mntes_stream.service.source import MinimalSource, SourceConfig

T0 = 1_700_000_000_000_000_000
SRC = SourceConfig(modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1)


@pytest.fixture(scope="module")
def source():
    return MinimalSource(SRC)


@pytest.fixture(scope="module")
def converter(source):
    return make_converter("exact", {p.detector_id: p for p in source.params})


def _messages(source, steps):
    out = []
    for t_pub, batch in source.batches(T0):
        out.extend((key, payload, t_pub) for key, payload in batch)
        if t_pub >= T0 + steps * 10**8:
            return out
    return out


def _power(outs):
    return {(pw.board, pw.module, pw.seq): pw for pw in (decode(p) for k, p in outs if "/power/" in k)}


def _run(converter, messages, **cfg):
    pipe = ConverterPipeline(converter, PipelineConfig(**cfg), clock=None)
    outs = []
    for key, payload, t in messages:
        outs.extend(pipe.handle(key, payload, t))
    return pipe, _power(outs + pipe.flush())


def _bias(module, value_v, t_ns, board=0):
    hk = HousekeepingChunk("lab", "bias", 0, np.array([t_ns]), np.full((1, 4), value_v), "V",
                           board=board, module=module, channels=np.arange(4, dtype=np.int32))
    return keys.hk_key("lab", keys.bias_sensor(board, module)), hk.to_bytes()


def test_a_1e9_volt_bias_is_rejected_and_the_module_keeps_converting(source, converter):
    msgs = _messages(source, 10)
    _, clean = _run(converter, msgs)
    k, p = _bias(0, 1e9, T0 + 3 * 10**8)
    hostile = msgs[:20] + [(k, p, T0 + 3 * 10**8)] + msgs[20:]
    pipe, got = _run(converter, hostile)
    assert pipe.status().bad_messages["hk_range"] == 1
    assert got.keys() == clean.keys()
    for key, pw in got.items():  # not one NaN more than without the bad reading
        assert np.array_equal(np.isnan(pw.p_opt_w), np.isnan(clean[key].p_opt_w))
        np.testing.assert_array_equal(pw.p_opt_w, clean[key].p_opt_w)


@pytest.mark.parametrize("sensor,value", [("t_bath", 1e300), ("t_bath", -1.0), ("b_field", 1e6)])
def test_impossible_environment_readings_are_rejected_not_held(source, converter, sensor, value):
    msgs = _messages(source, 6)
    hk = HousekeepingChunk("lab", sensor, 99, np.array([T0 + 2 * 10**8]), np.array([value]), "K" if sensor == "t_bath" else "T")
    pipe, got = _run(converter, msgs[:10] + [(keys.hk_key("lab", sensor), hk.to_bytes(), T0 + 2 * 10**8)] + msgs[10:])
    assert pipe.status().bad_messages["hk_range"] == 1
    assert not any((pw.flags & fl.ENV_OUT_OF_RANGE).any() for pw in got.values())


@pytest.mark.parametrize("t_pub_ns", [0, 1 << 62])
def test_one_stream_with_a_wild_t_pub_does_not_stale_real_housekeeping(t_pub_ns):
    """A known module whose publisher stamps t_pub_ns = 0 (or far ahead) and floods: one stream, one vote."""
    src = MinimalSource(SourceConfig(modules=3, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1))
    conv = make_converter("exact", {p.detector_id: p for p in src.params})
    out = []
    for key, payload, t in _messages(src, 10):
        if not key.endswith("counts/0/1"):
            out.append((key, payload, t))
            continue
        c = CountsChunk.from_bytes(payload)
        for j in range(5):  # five chunks for every honest one: most of the recent delays are its
            bad = CountsChunk(c.setup, c.board, c.module, c.channels, 5 * c.seq + j, c.t0_ns, c.sample_rate_hz,
                              c.counts_i, c.counts_q, t_pub_ns)
            out.append((key, bad.to_bytes(), t))
    pipe, got = _run(conv, out, overload="keep")
    st = pipe.status()
    assert "hk_time" not in st.bad_messages, st.bad_messages
    honest = [pw for (b, m, _), pw in got.items() if m != 1]
    assert len(honest) == 2 * 10 and not any((pw.flags & (fl.HK_STALE | fl.HK_MISSING)).any() for pw in honest)


def test_made_up_modules_get_no_state_and_are_counted(source, converter):
    msgs = _messages(source, 3)
    c = next(CountsChunk.from_bytes(p) for k, p, _ in msgs if "/counts/" in k)
    flood = []
    for i in range(2000):  # (the live RSS test floods 10,000 streams through zenoh)
        b, m = 1 + i // 100, i % 100
        fake = CountsChunk("lab", b, m, c.channels, 10**6 + i, c.t0_ns, c.sample_rate_hz, c.counts_i, c.counts_q,
                           c.t_pub_ns)
        flood.append((keys.counts_key("lab", b, m), fake.to_bytes(), T0))
        flood.append((*_bias(m, 1e-6, T0, board=b), T0))
    pipe, got = _run(converter, flood + msgs)
    st = pipe.status()
    assert st.bad_messages["unknown_stream"] == 4000
    assert set(pipe._sequence.streams) <= {(0, 0), (0, 1)} and len(pipe.hk._bias) == 0
    assert {(b, m) for b, m, _ in got} == {(0, 0), (0, 1)}
    assert "unknown_stream" in st.last_error


def test_an_oversized_housekeeping_message_is_rejected_whole(source, converter):
    msgs = _messages(source, 4)
    n = 2_000_000
    big = HousekeepingChunk("lab", "t_bath", 7, T0 - np.arange(n, 0, -1, dtype=np.int64) * 1000, np.full(n, 0.1), "K")
    pipe, got = _run(converter, [(keys.hk_key("lab", "t_bath"), big.to_bytes(), T0)] + msgs)
    assert pipe.status().bad_messages["too_large"] == 1
    assert len(pipe.hk.sensors["t_bath"]) < 100 and got


def _late_messages(source, steps):
    """From the 10th step on, everything is received 5 s late and later (the converter fell behind)."""
    out = []
    for key, payload, t in _messages(source, steps):
        lag = 0 if t < T0 + 10 * 10**8 else 5 * 10**9 + (t - T0)
        out.append((key, payload, t + lag))
    return out


def _run_overloaded(converter, messages, set_aside_bytes=256 << 20):
    """As _run, the service having declared a real overload (``overloaded``) from the first message."""
    pipe = ConverterPipeline(converter, PipelineConfig(max_lag_s=2.0), clock=None, set_aside_bytes=set_aside_bytes)
    pipe.overloaded = True
    outs = []
    for key, payload, t in messages:
        outs.extend(pipe.handle(key, payload, t))
    live = _power(outs)
    return pipe, live, _power(pipe.flush())


def test_a_stall_or_a_lagging_stream_sheds_nothing_without_a_real_overload(source, converter):
    """Chunks 5 s behind their stream's pace, but the service never declared an overload (a stall, a busy
    machine, an offline run): every chunk is converted live, nothing shed, the ledger balances."""
    late = _late_messages(source, 30)
    pipe, got = _run(converter, late, max_lag_s=2.0)
    n_counts = len([m for m in late if "/counts/" in m[0]])
    st = pipe.status()
    assert len(got) == n_counts and st.chunks_shed == st.chunks_late == st.chunks_lost == 0
    assert "overload" not in st.bad_messages
    tot = pipe.ledger.totals()
    assert tot.received == tot.done == n_counts and pipe.ledger.balanced()


def test_under_a_real_overload_chunks_behind_are_set_aside_then_converted_late(source, converter):
    """Overloaded: chunks far behind are not converted now but set aside, and converted later as late power
    (same values as live conversion, marked late); the ledger says which were live and which late."""
    late = _late_messages(source, 30)
    _, reference = _run(converter, late, max_lag_s=2.0)
    pipe, live, later = _run_overloaded(converter, late)
    assert live and later and not set(live) & set(later)
    assert max(seq for _, _, seq in live) < min(seq for _, _, seq in later)  # what was on time went live
    assert set(live) | set(later) == set(reference)
    for k, pw in later.items():
        assert pw.late is True and np.array_equal(pw.p_opt_w, reference[k].p_opt_w, equal_nan=True)
    assert all(pw.late is None for pw in live.values())
    st = pipe.status()
    assert st.chunks_late == len(later) and st.chunks_shed == 0 and st.chunks_lost == 0 and st.chunks_set_aside == 0
    assert pipe.ledger.balanced() and pipe.ledger.totals().done == len(live)


def test_a_full_set_aside_budget_sheds_the_oldest_and_the_ledger_says_so(source, converter):
    """Beyond the set-aside budget the oldest set-aside chunks are shed: counted per stream as shed (overload),
    in chunks_lost, never silently; received = converted + late + shed for every stream."""
    late = _late_messages(source, 30)
    one = CountsChunk.from_bytes(next(p for k, p, _ in late if "/counts/" in k))
    pipe, live, later = _run_overloaded(converter, late, set_aside_bytes=3 * 2 * one.counts_i.nbytes)
    st = pipe.status()
    assert st.chunks_shed > 0 and st.bad_messages["overload"] == st.chunks_shed == pipe.counters.chunks_shed
    assert st.chunks_lost == st.chunks_shed and st.chunks_late == len(later) <= 3 * 2  # 3 per stream at most
    for cols in st.ledger.values():
        assert cols["received"] == cols.get("done", 0) + cols.get("late", 0) + sum(cols.get("shed", {}).values())
    assert f"lost {st.chunks_shed} of" in pipe.ledger.line() and "shed" in pipe.ledger.line()


def test_a_bias_reading_goes_stale_after_bias_staleness_s(source, converter):
    """Every environment input has a finite staleness: a bias read once is flagged HK_STALE after bias_staleness_s."""
    msgs = _messages(source, 10)
    k, p = _bias(0, source.params[0].v_thev_v, T0)
    pipe, got = _run(converter, [(k, p, T0)] + msgs, bias_staleness_s=0.3)
    assert got
    for (_, module, _), pw in got.items():
        t = pw.times_ns()
        stale = (pw.flags & fl.HK_STALE) != 0
        if module == 0:  # the reading at T0 holds for 0.3 s, then every sample of the module says it is old
            assert (stale[:, t > T0 + 3 * 10**8]).all() and not stale[:, t <= T0 + 3 * 10**8].any()
        else:  # no reading at all: the nominal bias, not stale
            assert not stale.any()


def test_a_checkpoint_stops_below_the_chunks_still_held(source, converter):
    """What is set aside (or waits for housekeeping) is not converted yet: a restart from the checkpoint must
    convert it again, not take it as done (the checkpoint's number stops below the oldest held chunk)."""
    late = _late_messages(source, 30)
    pipe = ConverterPipeline(converter, PipelineConfig(max_lag_s=2.0), clock=None)
    pipe.overloaded = True
    for key, payload, t in late:
        pipe.handle(key, payload, t)
    assert pipe.set_aside
    held = {}
    for p in pipe._sequence.aside:
        held[(p.chunk.board, p.chunk.module)] = min(held.get((p.chunk.board, p.chunk.module), p.chunk.seq), p.chunk.seq)
    state = pipe.sequence_state()
    assert set(held) <= set(state)
    for stream, first_held in held.items():
        assert state[stream][0] == first_held - 1
    pipe.flush()  # converted now: the checkpoint moves to the newest
    assert all(seq == 29 for seq, _ in pipe.sequence_state().values())
