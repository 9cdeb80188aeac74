"""The converter core without zenoh: alignment, hold-back, sequence accounting, bad input, provenance."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from mntes_stream.core import flags as fl
from mntes_stream.core.convert import EnvironmentBlock, make_converter
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk, Provenance, StatusMessage, decode
from mntes_stream.io.paramfile import parse_params
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


def _messages(source, steps, t_start=T0):
    out = []
    for t_pub, batch in source.batches(t_start):
        out.extend((key, payload, t_pub) for key, payload in batch)
        if t_pub >= t_start + steps * 10**8:
            return out
    return out


def _run(pipe, messages):
    outs = []
    for key, payload, t in messages:
        outs.extend(pipe.handle(key, payload, t))
    return outs


def _split(outs):
    power = [decode(p) for k, p in outs if "/power/" in k]
    status = [decode(p) for k, p in outs if "/status/" in k]
    return power, status


def _hk_series(messages, sensor):
    t, v = [], []
    for key, payload, _ in messages:
        if key.endswith("/hk/" + sensor):
            hk = HousekeepingChunk.from_bytes(payload)
            t.extend(hk.t_ns.tolist()), v.extend(hk.value.tolist())
    return np.array(t), np.array(v)


def _interp(t, ht, hv):
    # Relative times: float64 ns since 1970 has a resolution of 256 ns.
    return np.interp(t - T0, ht - T0, hv)


def test_power_equals_library_conversion_and_truth(source, converter):
    msgs = _messages(source, 25)
    pipe = ConverterPipeline(converter, PipelineConfig(status_interval_s=0.5))
    power, status = _split(_run(pipe, msgs) + pipe.flush())
    counts = [CountsChunk.from_bytes(p) for k, p, _ in msgs if "/counts/" in k]
    assert len(power) == len(counts) == 50
    assert pipe.pending == 0 and len(status) >= 5
    tb_t, tb_v = _hk_series(msgs, "t_bath")
    b_t, b_v = _hk_series(msgs, "b_field")
    by_id = {(c.board, c.module, c.seq): c for c in counts}
    for pw in power:
        c = by_id[(pw.board, pw.module, pw.seq)]
        t = c.times_ns()
        np.testing.assert_array_equal(pw.times_ns(), t)
        # Independent alignment (numpy's interp) and the library conversion.
        env = EnvironmentBlock(t_bath_k=_interp(t, tb_t, tb_v), b_field_t=_interp(t, b_t, b_v))
        ref = converter.convert(pw.detector_ids, c.counts_i, c.counts_q, env)
        np.testing.assert_array_equal(pw.flags, ref.flags)
        np.testing.assert_allclose(pw.p_opt_w, ref.p_opt_w, rtol=1e-12, atol=0)
        truth = source.truth_p_opt_w(pw.board, pw.module, t, T0)
        assert np.max(np.abs(pw.p_opt_w - truth)) < 1e-18  # counts quantisation: ~3e-19 W
        assert pw.table_identity == converter.identity and pw.converter_kind == "exact"
        assert pw.source_t_pub_ns == c.t_pub_ns
    last = status[-1]
    assert last.chunks_received == last.chunks_converted == 50
    assert last.chunks_lost == last.chunks_duplicated == last.chunks_out_of_order == 0
    assert last.bad_messages == {} and last.samples_converted == 50 * 4 * 20
    assert sum(last.flag_counts.values()) == 0 and last.hk_missing_samples == last.hk_stale_samples == 0


def test_sequence_accounting(source, converter):
    msgs = [m for m in _messages(source, 10) if m[0].endswith("counts/0/0") or "/hk/" in m[0]]
    counts = [m for m in msgs if "/counts/" in m[0]]
    hk = [m for m in msgs if "/hk/" in m[0]]
    order = [0, 1, 3, 2, 2, 5, 6, 6, 4, 8]   # 3 before 2 (late), 2 and 6 twice, 7 and 9 never
    pipe = ConverterPipeline(converter)
    outs = _run(pipe, hk)
    for seq in order:
        key, payload, t = counts[seq]
        outs += pipe.handle(key, payload, t)
    power, _ = _split(outs + pipe.flush())
    st = pipe.status()
    assert sorted(p.seq for p in power) == [0, 1, 2, 3, 4, 5, 6, 8]
    assert st.chunks_received == 10 and st.chunks_converted == 8
    assert st.chunks_duplicated == 2
    assert st.chunks_out_of_order == 2          # 2 after 3, 4 after 6
    assert st.chunks_lost == 1                  # 7 (9 was never due: nothing after it)


def test_chunks_wait_for_bracketing_housekeeping_then_time_out(source, converter):
    msgs = _messages(source, 3)
    counts = [m for m in msgs if "/counts/" in m[0]]
    hk = [m for m in msgs if "/hk/" in m[0]]
    cfg = PipelineConfig(hk_wait_s=0.5, hk_staleness_s=0.05)
    pipe = ConverterPipeline(converter, cfg)
    # Counts of step 0 before any housekeeping: held.
    k, p, t = counts[0]
    assert not [o for o in pipe.handle(k, p, t) if "/power/" in o[0]]
    assert pipe.pending == 1
    # The hk of steps 0 and 1 (readings at 0.0 s, 0.1 s) bracket it: released, nothing flagged.
    outs = []
    for k, p, t in hk[:4]:
        outs += pipe.handle(k, p, t)
    (pw,) = _split(outs)[0]
    assert pw.seq == 0 and not pw.flags.any()
    # A later chunk with no newer housekeeping waits hk_wait_s, then goes out held-and-stale.
    k, p, t = counts[-1]
    assert not _split(pipe.handle(k, p, t))[0]
    assert not _split(pipe.tick(t + 4 * 10**8))[0]
    (late,) = _split(pipe.tick(t + 5 * 10**8))[0]
    # Newest reading at 0.2 s: samples more than 0.05 s after it are stale: flagged, power NaN (hk_stale_power).
    stale = (late.times_ns() - (T0 + 2 * 10**8)) > 5 * 10**7
    assert stale.any() and not stale.all()
    np.testing.assert_array_equal(late.flags, np.where(stale, fl.HK_STALE, 0)[None, :].repeat(4, axis=0))
    np.testing.assert_array_equal(np.isnan(late.p_opt_w), np.broadcast_to(stale, late.p_opt_w.shape))
    assert pipe.status().hk_stale_samples > 0


def test_missing_housekeeping_flags_and_nan(source, converter):
    msgs = [m for m in _messages(source, 3) if "/counts/" in m[0]]
    pipe = ConverterPipeline(converter, PipelineConfig(hk_wait_s=0.0))
    power, _ = _split(_run(pipe, msgs))
    assert len(power) == len(msgs)
    for pw in power:
        assert np.all(pw.flags & fl.HK_MISSING) and np.all(np.isnan(pw.p_opt_w))
    st = pipe.status()
    assert st.hk_missing_samples == len(msgs) * 20 and st.flag_counts["hk_missing"] == len(msgs) * 80
    # Field not required: without field readings the default (0 T) is used, unflagged.
    pipe = ConverterPipeline(converter, PipelineConfig(hk_wait_s=0.0, required_hk=("t_bath",)))
    tb = [m for m in _messages(source, 3) if m[0].endswith("t_bath")]
    power, _ = _split(_run(pipe, tb + msgs))
    assert power and not any(pw.flags.any() for pw in power)


def test_bad_messages_are_counted_and_the_stream_continues(source, converter):
    msgs = _messages(source, 4)
    good = [m for m in msgs]
    k0, p0, t0 = next(m for m in msgs if "/counts/0/0" in m[0])
    raw = msgpack.unpackb(p0)
    bad = [
        (k0, b"\x93\x01", t0),                                                       # not a map
        (k0, b"\xc1garbage", t0),                                                    # not msgpack
        (k0, msgpack.packb(dict(raw, version=99)), t0),                              # future version
        (k0, msgpack.packb(dict(raw, schema="mntes.nope")), t0),                     # unknown schema
        (k0, msgpack.packb(dict(raw, counts_i={"dtype": "<i4", "shape": [4, 20], "data": b"x"})), t0),
        (keys.counts_key("lab", 0, 1), p0, t0),                                      # payload of module 0 on module 1's key
        (keys.counts_key("other", 0, 0), p0, t0),                                    # another setup
        (keys.power_key("lab", 0, 0), p0, t0),                                       # not an input
        ("not/an/mntes/key", p0, t0),
        (keys.hk_key("lab", "t_bath"), p0, t0),                                      # counts on an hk key
    ]
    pipe = ConverterPipeline(converter)
    outs = _run(pipe, bad[:5] + good + bad[5:])
    power, _ = _split(outs + pipe.flush())
    st = pipe.status()
    assert len(power) == 8  # every good chunk, none of the bad
    assert st.bad_messages == {"malformed": 2, "wrong_version": 1, "unknown_schema": 1, "invalid": 1,
                               "wrong_key": 4, "wrong_schema": 1}
    assert st.last_error.startswith("wrong_schema")
    assert "internal_error" not in st.bad_messages


def test_unknown_channels_are_flagged_nan_and_counted(source, converter):
    msgs = _messages(source, 2)
    extra = []
    for k, p, t in msgs:
        if k.endswith("counts/0/1"):
            c = CountsChunk.from_bytes(p)
            # Channels 2 and 99: one known, one without parameters; and a module nobody knows.
            ci, cq = c.counts_i[[2, 3]], c.counts_q[[2, 3]]
            c2 = CountsChunk("lab", 0, 1, [2, 99], c.seq + 100, c.t0_ns, c.sample_rate_hz, ci, cq, c.t_pub_ns)
            c3 = CountsChunk("lab", 7, 7, [0, 1], c.seq, c.t0_ns, c.sample_rate_hz, ci, cq, c.t_pub_ns)
            extra += [(k, c2.to_bytes(), t), (keys.counts_key("lab", 7, 7), c3.to_bytes(), t)]
    pipe = ConverterPipeline(converter)
    power, _ = _split(_run(pipe, msgs + extra) + pipe.flush())
    mixed = [pw for pw in power if pw.seq >= 100]
    assert mixed and not [pw for pw in power if pw.board == 7]  # a module nobody knows gets no power...
    for pw in mixed:
        assert not pw.flags[0].any() and np.all(np.isfinite(pw.p_opt_w[0]))
        assert np.all(pw.flags[1] & fl.UNKNOWN_CHANNEL) and np.all(np.isnan(pw.p_opt_w[1]))
    st = pipe.status()
    assert st.unknown_channel_samples == 20 * len(mixed)
    n_alien = sum(1 for k, _, _ in extra if k.endswith("counts/7/7"))
    assert st.bad_messages["unknown_stream"] == n_alien  # ...and no state: counted at the door, said in last_error
    assert (7, 7) not in pipe._sequence.streams and (7, 7) not in pipe._sequence.pace


def test_converter_failure_flags_the_chunk_only(source):
    class Broken:
        kind, identity, detector_ids = "broken", "x", ("b0m0c000",)

        def convert(self, ids, ci, cq, env):
            raise RuntimeError("kaput")

    pipe = ConverterPipeline(Broken(), PipelineConfig(hk_wait_s=0.0))
    power, _ = _split(_run(pipe, _messages(source, 2)))
    assert power and all(np.all(pw.flags & fl.INVALID_INPUT) and np.all(np.isnan(pw.p_opt_w)) for pw in power)
    assert pipe.status().bad_messages["convert_failed"] == len(power)


def test_bias_housekeeping_is_used_per_channel(source, converter):
    msgs = _messages(source, 3)
    params = {p.detector_id: p for p in source.params}
    v = np.array([params[f"b0m0c{c:03d}"].v_thev_v for c in range(4)]) * np.array([1.0, 1.01, 0.99, 1.0])
    bias = HousekeepingChunk("lab", "bias", 0, [T0 - 10**9], v[None, :3], "V", board=0, module=0, channels=[0, 1, 2])
    pipe = ConverterPipeline(converter)
    power, _ = _split(_run(pipe, [(keys.hk_key("lab", "bias/0/0"), bias.to_bytes(), T0)] + msgs) + pipe.flush())
    tb_t, tb_v = _hk_series(msgs, "t_bath")
    b_t, b_v = _hk_series(msgs, "b_field")
    counts = {(c.module, c.seq): c for c in (CountsChunk.from_bytes(p) for k, p, _ in msgs if "/counts/" in k)}
    for pw in power:
        c = counts[(pw.module, pw.seq)]
        t = c.times_ns()
        # Module 0: channels 0-2 at the published bias, channel 3 (not in the reading) nominal.
        v_used = v if pw.module == 0 else None
        env = EnvironmentBlock(_interp(t, tb_t, tb_v), _interp(t, b_t, b_v), v_thev_v=v_used)
        ref = converter.convert(pw.detector_ids, c.counts_i, c.counts_q, env)
        np.testing.assert_array_equal(pw.flags, ref.flags)
        np.testing.assert_allclose(pw.p_opt_w, ref.p_opt_w, rtol=1e-12)
    assert any(pw.module == 0 for pw in power)


def test_offline_clock_is_reproducible_and_provenance_is_complete(source, converter):
    msgs = _messages(source, 5)
    a = ConverterPipeline(converter, clock=None)
    b = ConverterPipeline(converter, clock=None)
    assert _run(a, msgs) + a.flush() == _run(b, msgs) + b.flush()
    prov = Provenance.from_bytes(a.provenance_bytes())
    assert a.provenance_bytes() == a.provenance_bytes()
    assert prov.table_identity == converter.identity and prov.converter_kind == "exact"
    import tomllib

    back = parse_params(tomllib.loads(prov.params_toml))
    assert {k: p.to_dict() for k, p in back.items()} == {p.detector_id: p.to_dict() for p in source.params}


def test_status_cadence_and_schema(source, converter):
    msgs = _messages(source, 35)
    pipe = ConverterPipeline(converter, PipelineConfig(status_interval_s=1.0))
    _, status = _split(_run(pipe, msgs))
    assert len(status) == 3  # first message at 0.1 s, last at 3.5 s: due at 1.1, 2.1, 3.1 s
    assert all(isinstance(s, StatusMessage) for s in status)
    assert all(s.interval_s == pytest.approx(1.0) for s in status)
    assert status[-1].rate_chunks_per_s == pytest.approx(20.0, rel=0.11)
    assert set(status[-1].hk_age_s) == {"t_bath", "b_field"}


@pytest.mark.parametrize("bad", [
    {"required_hk": ("pressure",)}, {"required_hk": "t_bath"}, {"hk_staleness_s": -1}, {"hk_stalenes_s": 1},
    {"setup": "a/b"}, {"setup": 3}, {"max_pending": 2.5}, {"max_pending": True}, {"max_pending": 0},
    {"t_bath_default_k": float("nan")}, {"t_bath_default_k": 0.0}, {"b_field_default_t": float("inf")},
    {"hk_wait_s": float("nan")}, {"hk_wait_s": float("inf")}, {"hk_wait_s": "1"}, {"status_interval_s": 0},
    {"hk_retention_s": 0}, {"hk_max_ahead_s": -1.0}, {"t_bath_range_k": [0.2, 0.05]},
    {"t_bath_range_k": [0.05, float("nan")]}, {"bias_range_v": [0.0]}, {"b_field_range_t": "ab"},
])
def test_config_validation(bad):
    from mntes_stream.core.settings import build
    from mntes_stream.errors import ConfigError

    with pytest.raises(ConfigError):
        build(PipelineConfig, bad)


def test_config_normalises():
    from mntes_stream.core.settings import build

    cfg = build(PipelineConfig, {"t_bath_range_k": [0.05, 0.2], "required_hk": ["t_bath"], "hk_wait_s": 1,
                                 "hk_staleness_s": 5})
    assert cfg.t_bath_range_k == (0.05, 0.2) and cfg.required_hk == ("t_bath",)
    assert isinstance(cfg.hk_wait_s, float) and cfg.hk_staleness_s == 5.0
    for name in ("hk_staleness_s", "bias_staleness_s"):  # every environment input goes stale some time
        with pytest.raises(ConfigError, match=name):
            build(PipelineConfig, {name: float("inf")})
    assert PipelineConfig().setup == keys.DEFAULT_SETUP


def test_housekeeping_arriving_between_modules_of_one_step_is_used(source, converter):
    """Modules of a step share sample times (alignment is cached per step): new readings must still count."""
    msgs = _messages(source, 3)
    hk = [m for m in msgs if "/hk/" in m[0]]
    c0, c1 = [m for m in msgs if "/counts/" in m[0]][-2:]   # both modules, last step
    pipe = ConverterPipeline(converter, PipelineConfig(hk_wait_s=0.0, hk_staleness_s=0.06))
    _run(pipe, hk[:2])                                     # readings up to 0.1 s only
    (early,) = _split(pipe.handle(*c0))[0]
    _run(pipe, hk[2:])                                     # the rest, up to 0.3 s
    (late,) = _split(pipe.handle(*c1))[0]
    assert np.all(early.flags & fl.HK_STALE)
    assert not late.flags.any()


# ---------------------------------------------------------------------------- robustness


def _hk_msg(sensor, t_ns, value, seq=0, setup="lab"):
    hk = HousekeepingChunk(setup, sensor, seq, t_ns, value, {"t_bath": "K", "b_field": "T"}[sensor])
    return keys.hk_key(setup, sensor), hk.to_bytes()


def _reference_power(converter, msgs, pw, counts):
    """The library conversion of one power chunk's counts with independently interpolated housekeeping."""
    tb_t, tb_v = _hk_series(msgs, "t_bath")
    b_t, b_v = _hk_series(msgs, "b_field")
    c = counts[(pw.board, pw.module, pw.seq)]
    t = c.times_ns()
    env = EnvironmentBlock(_interp(t, tb_t, tb_v), _interp(t, b_t, b_v))
    return converter.convert(pw.detector_ids, c.counts_i, c.counts_q, env)


@pytest.mark.parametrize("offset_s", [1e6, 60.0, -1e6, -1.7e9])
def test_housekeeping_far_from_the_data_clock_is_rejected_and_counted(source, converter, offset_s):
    """One reading stamped far in the future (or absurdly far in the past) must not wipe the history."""
    msgs = _messages(source, 12)
    i = next(j for j, m in enumerate(msgs) if "/counts/" in m[0] and CountsChunk.from_bytes(m[1]).seq == 4)
    t_recv = msgs[i][2]
    key, bad = _hk_msg("t_bath", [t_recv + int(offset_s * 1e9)], [0.1], seq=999)
    pipe = ConverterPipeline(converter, PipelineConfig(status_interval_s=0.5))
    power, status = _split(_run(pipe, msgs[:i] + [(key, bad, t_recv)] + msgs[i:]) + pipe.flush())
    counts = {(c.board, c.module, c.seq): c for c in (CountsChunk.from_bytes(p) for k, p, _ in msgs if "/counts/" in k)}
    assert len(power) == len(counts) == 24
    for pw in power:  # every chunk, before and after the bad reading, as if it had never come
        ref = _reference_power(converter, msgs, pw, counts)
        np.testing.assert_array_equal(pw.flags, ref.flags)
        np.testing.assert_allclose(pw.p_opt_w, ref.p_opt_w, rtol=1e-12, atol=0)
        assert not pw.flags.any()
    st = status[-1]
    assert st.bad_messages == {"hk_time": 1} and st.last_error.startswith("hk_time")
    assert st.hk_missing_samples == 0 and st.hk_received == 12 * 2 + 1


def test_housekeeping_checks_follow_the_recording_clock_in_a_replay(source, converter):
    """A recording replayed a year later: readings are judged by the data clock of the counts, not rejected."""
    year = 365 * 86400 * 10**9
    msgs = [(k, p, t + year) for k, p, t in _messages(source, 6)]
    pipe = ConverterPipeline(converter)
    power, _ = _split(_run(pipe, msgs) + pipe.flush())
    assert len(power) == 12 and not any(pw.flags.any() for pw in power)
    assert pipe.status().bad_messages == {}


def test_housekeeping_out_of_range_and_failed_readings(source, converter):
    msgs = _messages(source, 4)
    hk = [m for m in msgs if "/hk/" in m[0]]
    counts = [m for m in msgs if "/counts/" in m[0]]
    # The bath reading at 0.2 s reads 5 K (outside t_bath_range_k), the one at 0.3 s failed (NaN).
    t_bad = T0 + 2 * 10**8
    edited = []
    for k, p, t in hk:
        h = HousekeepingChunk.from_bytes(p)
        if h.sensor == "t_bath":
            v = h.value.copy()
            v[h.t_ns == t_bad] = 5.0
            v[h.t_ns == T0 + 3 * 10**8] = np.nan
            p = HousekeepingChunk(h.setup, h.sensor, h.seq, h.t_ns, v, h.unit).to_bytes()
        edited.append((k, p, t))
    pipe = ConverterPipeline(converter, PipelineConfig(hk_wait_s=0.0))
    power, _ = _split(_run(pipe, edited + counts) + pipe.flush())
    assert len(power) == 8
    for pw in power:
        t = pw.times_ns()
        # Samples interpolated with the 5 K reading (0.1 s < t < 0.4 s, the NaN one being ignored) are flagged.
        uses_bad = (t > t_bad - 10**8) & (t < t_bad + 2 * 10**8)
        np.testing.assert_array_equal(pw.flags, np.where(uses_bad, fl.ENV_OUT_OF_RANGE, 0)[None, :].repeat(4, axis=0))
    assert pipe.status().flag_counts["env_out_of_range"] > 0
    assert pipe.status().bad_messages == {"hk_range": 1}  # the failed read: rejected and counted, never silent
    # Only failed readings: as if none had come (t_bath required: missing, NaN power).
    pipe = ConverterPipeline(converter, PipelineConfig(hk_wait_s=0.0))
    nan_tb = [_hk_msg("t_bath", [T0, T0 + 10**8], [np.nan, np.nan]) + (T0,)]
    power, _ = _split(_run(pipe, nan_tb + [m for m in hk if m[0].endswith("b_field")] + counts))
    assert power and all(np.all(pw.flags & fl.HK_MISSING) and np.all(np.isnan(pw.p_opt_w)) for pw in power)


def test_bias_reading_out_of_range_flags_that_module(source, converter):
    msgs = _messages(source, 3)
    bias = HousekeepingChunk("lab", "bias", 0, [T0 - 10**9], [[5e-3, 1e-6]], "V", board=0, module=1, channels=[0, 1])
    pipe = ConverterPipeline(converter, PipelineConfig(bias_range_v=(0.0, 1e-3)))
    power, _ = _split(_run(pipe, [(keys.hk_key("lab", keys.hk_sensor("bias", 0, 1)), bias.to_bytes(), T0)] + msgs)
                      + pipe.flush())
    assert len(power) == 6
    for pw in power:
        want = fl.ENV_OUT_OF_RANGE if pw.module == 1 else 0
        assert np.all((pw.flags & fl.ENV_OUT_OF_RANGE) == want), pw.module
    assert pipe.status().bad_messages == {}


def test_counts_at_the_int32_rails_are_flagged_not_fatal(source, converter):
    msgs = _messages(source, 2)
    hk = [m for m in msgs if "/hk/" in m[0]]
    k, p, t = next(m for m in msgs if m[0].endswith("counts/0/0"))
    c = CountsChunk.from_bytes(p)
    hi, lo = np.iinfo(np.int32).max, np.iinfo(np.int32).min
    ci, cq = c.counts_i.copy(), c.counts_q.copy()
    ci[0], cq[0] = hi, lo
    ci[1], cq[1] = lo, hi
    ci[2], cq[2] = hi, hi
    rails = CountsChunk(c.setup, c.board, c.module, c.channels, c.seq, c.t0_ns, c.sample_rate_hz, ci, cq, c.t_pub_ns)
    pipe = ConverterPipeline(converter)
    (pw,) = [x for x in _split(_run(pipe, hk + [(k, rails.to_bytes(), t)]) + pipe.flush())[0]]
    ref = _reference_power(converter, msgs, pw, {(c.board, c.module, c.seq): rails})
    np.testing.assert_array_equal(pw.flags, ref.flags)
    assert np.all(pw.flags[:3] & fl.UNUSABLE) and np.all(np.isnan(pw.p_opt_w[:3]))
    np.testing.assert_allclose(pw.p_opt_w[3], ref.p_opt_w[3], rtol=1e-12)
    assert not pw.flags[3].any()
    assert pipe.status().bad_messages == {}


def _renumbered(msg, seq, dt_s=0.0):
    k, p, t = msg
    c = CountsChunk.from_bytes(p)
    return k, CountsChunk(c.setup, c.board, c.module, c.channels, seq, c.t0_ns + int(dt_s * 1e9), c.sample_rate_hz,
                          c.counts_i, c.counts_q, c.t_pub_ns).to_bytes(), t


@pytest.mark.parametrize("name, seqs, resets, lost, out_of_order", [
    # One corrupt number (chunk 3 came as 2**62) then the stream goes on: two resets, nothing lost.
    ("corrupt", [0, 1, 2, 2**62, 4, 5, 6, 7, 8, 9], 2, 0, 0),
    # The int64 rail twice: the status must stay a valid message.
    ("rails", [0, 2**63 - 1, 2, 3, 2**63 - 1 - 2**40, 5, 6, 7, 8, 9], 4, 0, 0),
    # A jump far back (the source restarted at 0 after a long run).
    ("restart", [50000, 50001, 50002, 50003, 50004, 0, 1, 2, 3, 4], 1, 0, 0),
])
def test_huge_sequence_jumps_are_stream_resets(source, converter, name, seqs, resets, lost, out_of_order):
    msgs = [m for m in _messages(source, 10) if m[0].endswith("counts/0/0") or "/hk/" in m[0]]
    counts = [m for m in msgs if "/counts/" in m[0]]
    hk = [m for m in msgs if "/hk/" in m[0]]
    pipe = ConverterPipeline(converter)
    power, _ = _split(_run(pipe, hk + [_renumbered(counts[i], seq) for i, seq in enumerate(seqs)]) + pipe.flush())
    st = StatusMessage.from_bytes(pipe.status().to_bytes())  # the status stays a valid message
    assert sorted(p.seq for p in power) == sorted(seqs) and st.chunks_converted == 10
    assert st.bad_messages == {"seq_reset": resets}
    assert (st.chunks_lost, st.chunks_out_of_order, st.chunks_duplicated) == (lost, out_of_order, 0)


def test_a_restart_reusing_recent_numbers_is_not_a_duplicate(source, converter):
    """A source restarted within 256 chunks sends numbers the converter has just seen, with new samples."""
    msgs = [m for m in _messages(source, 10) if m[0].endswith("counts/0/0") or "/hk/" in m[0]]
    counts = [m for m in msgs if "/counts/" in m[0]]
    hk = [m for m in msgs if "/hk/" in m[0]]
    script = counts[:5] + [counts[2]]                                     # 0-4, then a real duplicate of 2
    script += [_renumbered(counts[5 + i], i) for i in range(5)]           # restart: 0-4 again, later samples
    pipe = ConverterPipeline(converter)
    power, _ = _split(_run(pipe, hk + script) + pipe.flush())
    st = pipe.status()
    assert len(power) == 10 and st.chunks_duplicated == 1
    assert st.bad_messages == {"seq_reset": 1} and st.chunks_lost == st.chunks_out_of_order == 0


def test_a_chunk_that_cannot_be_converted_is_dropped_once_and_counted(source, converter):
    """A failure outside the converter's own guard must not leave the chunk blocking (or re-publishing) the queue."""
    calls = []

    def clock():  # the publication stamp of the third chunk fails
        calls.append(1)
        if len(calls) == 3:
            raise OSError("clock unavailable")
        return T0 + len(calls)

    msgs = _messages(source, 5)
    pipe = ConverterPipeline(converter, PipelineConfig(hk_wait_s=0.0), clock=clock)
    power, _ = _split(_run(pipe, msgs) + pipe.flush())
    seqs = [(p.module, p.seq) for p in power]
    assert len(seqs) == len(set(seqs)) == 9       # 10 chunks, each published at most once, one dropped
    st = pipe.status()
    assert pipe.pending == 0 and st.chunks_pending == 0
    assert st.bad_messages == {"internal_error": 1} and "clock unavailable" in st.last_error
    assert pipe.counters.chunks_failed == 1


def test_the_stages_are_one_declared_list_and_running_them_by_hand_is_handle_many(source, converter):
    """The stages run in their declared order; the same items through them by hand give handle_many's bytes,
    and a stage that fails on a batch is counted (internal_error) without stopping the next batch."""
    from mntes_stream.pipeline.items import END, Flagged, Output
    from mntes_stream.pipeline.pipeline import converter_stages

    msgs = _messages(source, 12)
    a, b = len(msgs) // 3, 2 * len(msgs) // 3
    pipe = ConverterPipeline(converter, PipelineConfig(hk_wait_s=0.0), clock=None)
    assert pipe.stages.names == ["decode", "sequence", "housekeeping", "convert", "flags", "encode", "status"]
    assert [type(s) for s in pipe.stages] == [type(s) for s in converter_stages(
        pipe.books, converter, params=[], modules=None, owns={}, threads=1, set_aside_bytes=1)]
    want = pipe.handle_many(msgs[:a])

    by_hand = ConverterPipeline(converter, PipelineConfig(hk_wait_s=0.0), clock=None)
    items = list(msgs[:a]) + [END]
    for stage in by_hand.stages:
        items = stage(items)
    assert items[-1] is END and [i for i in items if type(i) is tuple] == want
    assert any("/power/" in k for k, _ in want)

    class Broken:
        name = "encode"
        takes, gives = (Flagged,), (Output,)

        def __call__(self, items):
            raise RuntimeError("encoder bug")

    enc = pipe.stages["encode"]
    pipe.stages = pipe.stages.replace(Broken())
    assert not [k for k, _ in pipe.handle_many(msgs[a:b]) if "/power/" in k]
    assert pipe.bad_messages["internal_error"] == 1 and "encoder bug" in pipe.last_error
    pipe.stages = pipe.stages.replace(enc)
    power, _ = _split(pipe.handle_many(msgs[b:]) + pipe.flush())
    assert power and pipe.ledger_now().totals().pending > 0  # the broken batch's chunks: held in the ledger, not lost


def test_a_stage_whose_input_no_earlier_stage_gives_is_refused_when_the_list_is_built(converter):
    """Stages are checked by what they take and give, and parts of the list are run by name."""
    from mntes_stream.errors import ConfigError
    from mntes_stream.pipeline.items import Ready, Stages

    pipe = ConverterPipeline(converter, PipelineConfig(), clock=None)
    stages = list(pipe.stages)
    with pytest.raises(ConfigError, match="stage 'housekeeping' takes Pending, which no stage before it gives"):
        Stages([s for s in stages if s.name != "sequence"])  # nothing books chunks into their sequence
    with pytest.raises(ConfigError, match="stage 'encode' takes Flagged"):
        Stages(stages[:4] + stages[5:])  # encode before flags: no flagged power to encode
    with pytest.raises(ConfigError, match="two stages are named 'convert'"):
        Stages(stages[:4] + stages[3:])
    assert [s.name for s in pipe.stages.span("convert", "encode", (Ready,))] == ["convert", "flags", "encode"]
    assert [s.name for s in pipe.stages.span(until="encode")] == pipe.stages.names[:-1]
    with pytest.raises(ConfigError, match="stage 'convert' takes Ready"):
        pipe.stages.span("convert", "encode")  # fed received messages, not released chunks
    with pytest.raises(ConfigError, match="no stage named 'kernel'"):
        pipe.stages.span(until="kernel")


def test_one_runner_batches_and_switches_the_calibration_as_message_by_message(source, converter):
    """The runner every driver feeds: batched by receive time, the power and flags of message by message, the
    inputs given back in their order; at a switch the old pipeline converts what arrived before it and the new
    one takes over, with its own provenance, each retired once flushed."""
    from mntes_stream.pipeline.runner import Runner

    msgs = _messages(source, 30)

    def powers(writes):
        return {(p.module, p.seq): (p.converter_kind, p.p_opt_w.tobytes(), p.flags.tobytes())
                for p in (decode(pl) for k, pl, _ in writes if "/power/" in k)}

    cfg = PipelineConfig(status_interval_s=0.2)
    one = Runner(lambda k: ConverterPipeline(converter, cfg, clock=None))
    by_message = [w for m in msgs for w in one.feed(*m)] + one.finish()
    batched = Runner(lambda k: ConverterPipeline(converter, cfg, clock=None), batch_s=1.0, inputs=True)
    writes = [w for m in msgs for w in batched.feed(*m)] + batched.finish()
    assert len(powers(by_message)) == 2 * 30 and powers(writes) == powers(by_message)
    assert [w for w in writes if keys.kind_of(w[0]) in ("counts", "hk")] == msgs
    assert sum("/status/" in w[0] for w in writes) < sum("/status/" in w[0] for w in by_message)  # one per batch

    linear = make_converter("linear", {p.detector_id: p for p in source.params})
    t_switch = msgs[len(msgs) // 2][2]
    retired = []
    switching = Runner(lambda k: ConverterPipeline((converter, linear)[k], PipelineConfig(), clock=None),
                       switches=[t_switch], batch_s=1.0, provenance=True, retire=retired.append)
    writes = [w for m in msgs for w in switching.feed(*m)] + switching.finish()
    assert [(decode(p).converter_kind, t) for k, p, t in writes if keys.kind_of(k) == "provenance"] == [
        ("exact", msgs[0][2]), ("linear", t_switch)]
    assert [r.converter for r in retired] == [converter, linear]
    received = {(c.module, c.seq): t for k, p, t in msgs if "/counts/" in k for c in [decode(p)]}
    got = powers(writes)
    assert got.keys() == received.keys()
    for k, (kind, p, f) in got.items():  # each chunk converted by the calibration in force when it arrived
        assert kind == ("exact" if received[k] < t_switch else "linear"), k
        if kind == "exact":
            assert (p, f) == powers(by_message)[k][1:]


@pytest.mark.parametrize("rate_hz", [1569.0117, 1961.265, 2353.518])
def test_the_sources_housekeeping_brackets_each_chunk_in_its_own_step(rate_hz):
    """With hk_interval_s the chunk length (as bench stream sets it), no chunk waits a step for its reading,
    whatever the rounding of the rate's chunk length to ns (it did: every chunk 100 ms late at these rates)."""
    n = round(0.1 * rate_hz)
    src = MinimalSource(SourceConfig(modules=2, channels=4, sample_rate_hz=rate_hz, chunk_s=0.1,
                                     hk_interval_s=n / rate_hz, cycle_s=1.0))
    conv = make_converter("exact", {p.detector_id: p for p in src.params})
    pipe = ConverterPipeline(conv, PipelineConfig(setup=src.config.setup), clock=None)
    lat_ns = []
    for t_pub, batch in src.batches(T0, 2.0):
        for key, payload in batch:
            lat_ns += [decode(p).t_pub_ns - decode(p).source_t_pub_ns
                       for k, p in pipe.handle(key, payload, t_pub + 1_000_000) if "/power/" in k]
    assert len(lat_ns) >= 2 * 19 and set(lat_ns) == {1_000_000}  # released as it arrives, every one


def test_each_streams_power_leaves_in_sequence_when_housekeeping_splits_a_step():
    """A reading arriving between a step's modules (the next step's, ahead: flat out, live) aligns the step's
    modules in two groups; steps split and unsplit alternate, so a stream's chunks sat in two runs of one batch
    and left out of order (bench stream --flat-out: the recorder saw 'power again after a gap' by the thousand).
    Each stream's power leaves in sequence, with the same values as message by message."""
    src = MinimalSource(SourceConfig(modules=4, channels=4, sample_rate_hz=200.0, chunk_s=0.1, hk_interval_s=0.1))
    steps = [[(k, p, t + 1_000_000) for k, p in batch] for t, batch in src.batches(T0, 3.0)]
    counts = [[m for m in st if "/counts/" in m[0]] for st in steps]
    hk = [[m for m in st if "/counts/" not in m[0]] for st in steps] + [[]]
    msgs = list(hk[0])
    for k, c in enumerate(counts):  # the next step's readings ahead: mid-step in even steps, first in odd ones
        msgs += c[:2] + hk[k + 1] + c[2:] if k % 2 == 0 else hk[k + 1] + c
    conv = make_converter("exact", {p.detector_id: p for p in src.params})
    per_step = len(msgs) // len(steps)
    batched = ConverterPipeline(conv, PipelineConfig(setup=src.config.setup), clock=None)
    outs = [o for i in range(0, len(msgs), 8 * per_step) for o in batched.handle_many(msgs[i:i + 8 * per_step])]
    power, _ = _split(outs + batched.flush())
    one_by_one = ConverterPipeline(conv, PipelineConfig(setup=src.config.setup), clock=None)
    reference = {(p.module, p.seq): p for p in _split(_run(one_by_one, msgs) + one_by_one.flush())[0]}
    seqs = {m: [p.seq for p in power if p.module == m] for m in range(4)}
    assert all(s == list(range(len(counts))) for s in seqs.values()), seqs
    assert all(np.array_equal(p.p_opt_w, reference[(p.module, p.seq)].p_opt_w, equal_nan=True)
               and np.array_equal(p.flags, reference[(p.module, p.seq)].flags) for p in power)


def test_chunks_per_kernel_call_is_what_one_converter_call_took_of_a_batch(source, converter):
    """A call per chunk message by message, a few per batch when a batch's steps share their rows (the figure
    ``bench stream`` reports beside the kernel's CPU per chunk)."""
    msgs = _messages(source, 12)
    n_steps = sum(1 for k, _, _ in msgs if "/counts/" in k) // SRC.modules
    one = ConverterPipeline(converter, PipelineConfig(setup="lab", hk_wait_s=0.0), clock=None)
    assert one.chunks_per_kernel_call is None
    _run(one, msgs)
    # Each chunk is released as it comes (its step's housekeeping came first): a call of its own.
    assert one.chunks_per_kernel_call == 1.0
    batched = ConverterPipeline(converter, PipelineConfig(setup="lab", hk_wait_s=0.0), clock=None)
    batched.handle_many(msgs)
    batched.flush()
    assert batched.counters.chunks_converted == n_steps * SRC.modules
    assert batched.chunks_per_kernel_call > 4 * SRC.modules  # a batch of twelve steps: few calls
