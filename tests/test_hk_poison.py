"""Housekeeping that cannot poison (issue 22, item 5): a rejected reading never replaces the last good one.

Measured on the code before this fix, with the real converter pipeline fed the minimal source's messages: a
0 V bias reading (accepted by ``bias_accept_v = (-1, 1)``, inside ``bias_range_v = (0, 1e-3)``, so not even
flagged) was held until the next bias reading, and every sample of the module after it was NaN + INVALID_INPUT
(160 of 160); the samples between the last good reading and it were converted with a bias interpolated towards
0 V, unflagged. -1 V did the same with ENV_OUT_OF_RANGE; a 0 K bath reading made INVALID_INPUT samples and
flagged 152 more; NaN and inf readings were dropped without being counted.

Here every case is compared, bit for bit, with the same messages without the bad reading.
"""

from __future__ import annotations

import numpy as np
import pytest

from mntes_stream.core import flags as fl
from mntes_stream.core.convert import make_converter
from mntes_stream.io import keys
from mntes_stream.io.messages import HousekeepingChunk, decode, detector_ids_for
from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
from mntes_stream.service.source import MinimalSource, SourceConfig

T0 = 1_700_000_000_000_000_000
MS = 10**6
SRC = SourceConfig(modules=2, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1)


@pytest.fixture(scope="module")
def source():
    return MinimalSource(SRC)


@pytest.fixture(scope="module")
def converter(source):
    return make_converter("exact", {p.detector_id: p for p in source.params})


@pytest.fixture(scope="module")
def good_bias_v(source):
    """Module 0's bias, 1 % above nominal: a run that fell back to the nominal bias would differ."""
    nominal = {p.detector_id: p.v_thev_v for p in source.params}
    return np.array([1.01 * nominal[d] for d in detector_ids_for(0, 0, np.arange(4))])


def _messages(source, steps):
    out = []
    for t_pub, batch in source.batches(T0):
        out.extend((key, payload, t_pub) for key, payload in batch)
        if t_pub >= T0 + steps * 100 * MS:
            return out
    return out


def _run(converter, messages, **cfg):
    pipe = ConverterPipeline(converter, PipelineConfig(**cfg), clock=None)
    outs = []
    for key, payload, t in messages:
        outs.extend(pipe.handle(key, payload, t))
    outs += pipe.flush()
    return pipe, {(pw.board, pw.module, pw.seq): pw for pw in (decode(p) for k, p in outs if "/power/" in k)}


def _bias(value_v, t_ns, t_recv_ns, channels=(0, 1, 2, 3)):
    v = np.broadcast_to(np.asarray(value_v, dtype=float), (1, len(channels)))
    hk = HousekeepingChunk("lab", "bias", 0, np.array([t_ns]), v, "V", board=0, module=0,
                           channels=np.array(channels, dtype=np.int32))
    return keys.hk_key("lab", keys.bias_sensor(0, 0)), hk.to_bytes(), t_recv_ns


def _scalar(sensor, value, t_ns, t_recv_ns):
    hk = HousekeepingChunk("lab", sensor, 99, np.array([t_ns]), np.array([value]), "K" if sensor == "t_bath" else "T")
    return keys.hk_key("lab", sensor), hk.to_bytes(), t_recv_ns


def _insert(messages, index, item):
    """``item`` received with the receive time of the message before it: the clock does not move."""
    key, payload, _ = item
    return messages[:index] + [(key, payload, messages[index - 1][2])] + messages[index:]


def _same(got, clean):
    assert got.keys() == clean.keys()
    for k, pw in got.items():
        np.testing.assert_array_equal(pw.flags, clean[k].flags, err_msg=str(k))
        assert pw.p_opt_w.tobytes() == clean[k].p_opt_w.tobytes(), k  # bit for bit, NaN included


@pytest.mark.parametrize("bad_v", [0.0, -1.0, 1e9, -1e-7, np.nan, np.inf])
def test_an_impossible_bias_between_good_ones_is_rejected_and_the_last_good_one_holds(source, converter,
                                                                                     good_bias_v, bad_v):
    msgs = _messages(source, 10)
    clean_msgs = [_bias(good_bias_v, T0, T0)] + msgs[:30] + [_bias(good_bias_v, T0 + 800 * MS, msgs[29][2])] + msgs[30:]
    _, clean = _run(converter, clean_msgs)
    # Between the two good readings, before the chunks it would be used for.
    pipe, got = _run(converter, _insert(clean_msgs, 9, _bias(bad_v, T0 + 350 * MS, 0)))
    assert pipe.status().bad_messages == {"hk_range": 1}
    assert "the last good reading holds" in pipe.status().last_error
    _same(got, clean)
    module0 = [pw for (_, m, _), pw in got.items() if m == 0]
    assert len(module0) == 10 and all(np.isfinite(pw.p_opt_w).all() for pw in module0)
    assert not any((pw.flags & (fl.INVALID_INPUT | fl.HK_STALE | fl.ENV_OUT_OF_RANGE)).any() for pw in module0)


def test_a_rejected_bias_for_other_channels_does_not_reset_the_module_s_bias(source, converter, good_bias_v):
    """A new channel list starts a new bias history, but only for readings that are used."""
    msgs = _messages(source, 6)
    clean_msgs = [_bias(good_bias_v, T0, T0)] + msgs
    _, clean = _run(converter, clean_msgs)
    pipe, got = _run(converter, _insert(clean_msgs, 5, _bias(0.0, T0 + 250 * MS, 0, channels=(0, 1))))
    assert pipe.status().bad_messages == {"hk_range": 1}
    _same(got, clean)


@pytest.mark.parametrize("sensor,bad", [("t_bath", np.nan), ("t_bath", np.inf), ("t_bath", 1e300), ("t_bath", 0.0),
                                        ("t_bath", -1.0), ("b_field", np.nan), ("b_field", -np.inf),
                                        ("b_field", 1e6)])
def test_an_impossible_bath_or_field_reading_between_good_ones_is_rejected(source, converter, sensor, bad):
    msgs = _messages(source, 8)
    _, clean = _run(converter, msgs)
    # Off the source's reading grid (a reading at an existing time would replace it), ahead of the chunks.
    pipe, got = _run(converter, _insert(msgs, 4, _scalar(sensor, bad, T0 + 350 * MS, 0)))
    assert pipe.status().bad_messages == {"hk_range": 1}
    _same(got, clean)
    assert not any((pw.flags & (fl.INVALID_INPUT | fl.ENV_OUT_OF_RANGE)).any() for pw in got.values())


@pytest.mark.parametrize("sensor,value,flagged", [("bias", 2e-3, fl.ENV_OUT_OF_RANGE), ("t_bath", 0.6, 0)])
def test_a_plausible_reading_outside_the_range_is_used_and_flagged(source, converter, sensor, value, flagged):
    """Not rejected: physically possible, only beyond the configured range (ENV_OUT_OF_RANGE)."""
    msgs = _messages(source, 8)
    _, clean = _run(converter, msgs)
    item = _bias(value, T0 + 350 * MS, 0) if sensor == "bias" else _scalar(sensor, value, T0 + 350 * MS, 0)
    pipe, got = _run(converter, _insert(msgs, 4, item))
    assert "hk_range" not in pipe.status().bad_messages
    flags = np.concatenate([pw.flags for pw in got.values()], axis=1)
    assert (flags & fl.ENV_OUT_OF_RANGE).any() and not (flags & fl.INVALID_INPUT).any()
    assert any(not np.array_equal(pw.p_opt_w, clean[k].p_opt_w, equal_nan=True) for k, pw in got.items())


@pytest.mark.parametrize("stale_power", ["nan", "keep"])
def test_only_rejected_bias_after_a_good_one_goes_stale_at_the_limit_not_invalid(source, converter, good_bias_v,
                                                                               stale_power):
    """Rejected readings do not refresh the bias: beyond bias_staleness_s the module is HK_STALE (NaN), never
    INVALID_INPUT; before it, the last good reading converts as if the bad ones had never come."""
    msgs = _messages(source, 10)
    good = [_bias(good_bias_v, T0, T0)] + msgs
    hostile = good
    for i, t in ((9, 200), (17, 400), (25, 600)):
        hostile = _insert(hostile, i, _bias(0.0, T0 + t * MS, 0))
    cfg = {"bias_staleness_s": 0.3, "hk_stale_power": stale_power}
    _, clean = _run(converter, good, **cfg)
    pipe, got = _run(converter, hostile, **cfg)
    assert pipe.status().bad_messages == {"hk_range": 3}
    _same(got, clean)
    for (_, module, _), pw in got.items():
        assert not (pw.flags & fl.INVALID_INPUT).any()
        stale = (pw.flags & fl.HK_STALE) != 0
        if module == 1:  # no bias reading at all: the nominal bias, never stale
            assert not stale.any() and np.isfinite(pw.p_opt_w).all()
            continue
        old = np.broadcast_to(pw.times_ns() > T0 + 300 * MS, stale.shape)
        np.testing.assert_array_equal(stale, old)
        np.testing.assert_array_equal(np.isnan(pw.p_opt_w), old if stale_power == "nan" else np.zeros_like(old))
    assert any((pw.flags & fl.HK_STALE).any() for pw in got.values())


def test_a_bath_thermometer_reading_only_garbage_goes_stale_then_nan_never_invalid(source, converter):
    """Every bath reading after 0.3 s is 0 K: held 0.25 s (hk_staleness_s), then NaN + HK_STALE, as without them."""
    msgs = _messages(source, 8)
    cut = T0 + 300 * MS
    hostile, without, n_bad = [], [], 0
    for key, payload, t in msgs:
        if key.endswith("/t_bath"):
            h = HousekeepingChunk.from_bytes(payload)
            late = h.t_ns > cut
            if late.any():
                n_bad += 1
                bad = HousekeepingChunk(h.setup, h.sensor, h.seq, h.t_ns, np.where(late, 0.0, h.value), h.unit)
                hostile.append((key, bad.to_bytes(), t))
                if not late.all():
                    kept = HousekeepingChunk(h.setup, h.sensor, h.seq, h.t_ns[~late], h.value[~late], h.unit)
                    without.append((key, kept.to_bytes(), t))
                continue
        hostile.append((key, payload, t))
        without.append((key, payload, t))
    cfg = {"hk_staleness_s": 0.25, "hk_wait_s": 0.0}
    _, clean = _run(converter, without, **cfg)
    pipe, got = _run(converter, hostile, **cfg)
    assert n_bad >= 5 and pipe.status().bad_messages == {"hk_range": n_bad}
    _same(got, clean)
    stale_seen = 0
    for pw in got.values():
        old = np.broadcast_to(pw.times_ns() > cut + 250 * MS, pw.flags.shape)
        assert not (pw.flags & (fl.INVALID_INPUT | fl.HK_MISSING)).any()
        np.testing.assert_array_equal((pw.flags & fl.HK_STALE) != 0, old)
        np.testing.assert_array_equal(np.isnan(pw.p_opt_w), old)
        stale_seen += int(old.sum())
    assert stale_seen > 0
