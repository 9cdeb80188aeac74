"""The converter core without zenoh: alignment, hold-back, sequence accounting, bad input, provenance."""

from __future__ import annotations

import msgpack
import numpy as np
import pytest

from mntes_stream.core import flags as fl
from mntes_stream.core.convert import EnvironmentBlock, make_converter
from mntes_stream.io import keys
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk, Provenance, StatusMessage, decode
from mntes_stream.io.paramfile import parse_params
from mntes_stream.service.pipeline import ConverterPipeline, PipelineConfig
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
    # Newest reading at 0.2 s: samples more than 0.05 s after it are stale, the value still given.
    stale = (late.times_ns() - (T0 + 2 * 10**8)) > 5 * 10**7
    assert stale.any() and not stale.all()
    np.testing.assert_array_equal(late.flags, np.where(stale, fl.HK_STALE, 0)[None, :].repeat(4, axis=0))
    assert np.all(np.isfinite(late.p_opt_w))
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
    alien = [pw for pw in power if pw.board == 7]
    assert mixed and alien
    for pw in mixed:
        assert not pw.flags[0].any() and np.all(np.isfinite(pw.p_opt_w[0]))
        assert np.all(pw.flags[1] & fl.UNKNOWN_CHANNEL) and np.all(np.isnan(pw.p_opt_w[1]))
    for pw in alien:
        assert np.all(pw.flags & fl.UNKNOWN_CHANNEL) and np.all(np.isnan(pw.p_opt_w))
    st = pipe.status()
    assert st.unknown_channel_samples == 20 * (len(mixed) + 2 * len(alien))


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


def test_config_validation():
    from mntes_stream.errors import ConfigError

    with pytest.raises(ConfigError):
        PipelineConfig(required_hk=("pressure",))
    with pytest.raises(ConfigError):
        PipelineConfig(hk_staleness_s=-1)
    with pytest.raises(ConfigError):
        PipelineConfig.from_dict({"hk_stalenes_s": 1})
    with pytest.raises(ConfigError):
        PipelineConfig(setup="a/b")
    assert PipelineConfig.from_dict({"t_bath_range_k": [0.05, 0.2]}).t_bath_range_k == (0.05, 0.2)


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
