"""Shards, claims and coverage: the pieces behind converter shards (real zenoh sessions on 127.0.0.1)."""

from __future__ import annotations

import itertools
import time

import numpy as np
import pytest

from mntes_stream.core.shards import Claim, Shard, StreamKey, owned_streams, publisher
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io import keys
from mntes_stream.io.claims import StreamClaims, parse_claim
from mntes_stream.io.messages import CountsChunk, PowerChunk, Provenance, StatusMessage
from mntes_stream.io.paramfile import dump_params
from mntes_stream.io.transport import free_tcp_port, loopback, open_session
from mntes_stream.pipeline import ConverterPipeline, PipelineConfig
from mntes_stream.pipeline.build import owned_part
from mntes_stream.service.converter import ConverterConfig, subscriptions
from mntes_stream.service.coverage import Coverage
from mntes_stream.service.recorder import RecorderConfig
from mntes_stream.service.recorder_sink import shard_filter
from mntes_stream.service.source import MinimalSource, SourceConfig


def test_every_stream_in_exactly_one_shard_whatever_n():
    streams = [(b, m) for b in range(3) for m in range(50)]
    for n in (1, 2, 3, 4, 7):
        parts = [owned_streams(streams, Shard(i, n)) for i in range(n)]
        assert sorted(itertools.chain(*parts)) == sorted(streams)
    # Stable across processes and machines: CRC-32, not Python's salted hash().
    assert [s for s in streams if Shard(1, 4).owns(*s)][:3] == [(0, 1), (0, 3), (0, 8)]
    for bad in ("3/3", "-1/2", "1", "a/b", "0/0"):
        with pytest.raises(ConfigError, match="shard"):
            Shard.parse(bad)


def test_a_stream_key_is_parsed_once_and_spelled_as_keys_spell_it():
    from mntes_stream.core.ledger import OTHER, Ledger, stream_order

    assert StreamKey.parse("3/10") == (3, 10) and str(StreamKey(3, 10)) == "3/10"
    for bad in ("3", "3/", "/1", "a/1", "-1/2", "1/2/3", OTHER):
        assert StreamKey.parse(bad) is None
    # Ledgers keep their "b/m" names (the status messages' format), ordered numerically, other names last.
    led = Ledger()
    for stream in ((0, 10), StreamKey(0, 2), "weird"):
        led.received(stream)
    assert list(led.as_dict()) == ["0/2", "0/10", "weird"]
    assert sorted(["0/10", OTHER, "0/2"], key=stream_order) == ["0/2", "0/10", OTHER]


@pytest.mark.parametrize("cls,kw", [(ConverterConfig, {"params": "p.toml"}), (RecorderConfig, {})])
def test_the_shard_is_parsed_once_at_the_config_boundary(cls, kw):
    import dataclasses
    import pickle

    cfg = cls(shard="1/3", **kw)
    assert cfg.shard_parsed == Shard(1, 3) and cfg.shard == "1/3"  # the text stays what the file said
    assert pickle.loads(pickle.dumps(cfg)).shard_parsed == Shard(1, 3)  # as a spawned service gets it
    assert cls(**kw).shard_parsed == Shard() and dataclasses.replace(cfg, shard="2/3").shard_parsed == Shard(2, 3)
    with pytest.raises(ConfigError, match="shard '1-3'"):
        cls(shard="1-3", **kw)


def test_earliest_claim_publishes():
    a, b, c = Claim(10, "z2", "a"), Claim(20, "z1", "b", standby=True), Claim(10, "z1", "c")
    assert publisher([a, b, c]) == c  # same time: the instance id breaks the tie, the same everywhere
    assert publisher([b]) == b and publisher([]) is None
    key = keys.claim_key("lab", 0, 3, 10, "z2", "standby", "conv")
    assert parse_claim(key) == ((0, 3), Claim(10, "z2", "conv", True))
    assert type(parse_claim(key)[0]) is StreamKey and str(parse_claim(key)[0]) == "0/3"
    assert parse_claim("mntes/lab/claim/0/x/1/z/primary/n") is None and parse_claim("mntes/lab/power/0/1") is None


@pytest.fixture(scope="module")
def array(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("shards")
    sc = SourceConfig(boards=2, modules=3, channels=4, chunk_s=0.1, hk_interval_s=0.1, cycle_s=1.0)
    dump_params(MinimalSource(sc).params, tmp / "params.toml")
    return tmp, sc


def test_a_shard_loads_only_its_detectors_and_subscribes_only_to_its_keys(array):
    tmp, _ = array
    cfg = ConverterConfig(params=str(tmp / "params.toml"), shard="1/2", table_cache="")
    assert cfg.name == "converter-1of2"  # shards of one setup get names of their own
    params, streams = owned_part(cfg.spec)
    assert streams == owned_streams([(b, m) for b in range(2) for m in range(3)], Shard(1, 2))
    assert sorted({d[:4] for d in params}) == sorted(f"b{b}m{m}" for b, m in streams)
    assert len(params) == 4 * len(streams)
    subs = subscriptions(cfg, streams)
    assert subs[:2] == ["mntes/lab/hk/t_bath", "mntes/lab/hk/b_field"]
    assert sorted(subs[2:]) == sorted([f"mntes/lab/hk/{s}/{b}/{m}" for b, m in streams
                                       for s in ("bias", "readout_flags")]
                                      + [f"mntes/lab/counts/{b}/{m}" for b, m in streams])
    # boards and modules narrow it further; nothing left is an error, said in one line.
    assert owned_part(ConverterConfig(params=str(tmp / "params.toml"), boards=(1,), modules=(2,)).spec)[1] == [(1, 2)]
    with pytest.raises(ConfigError, match="no stream of the parameters"):
        owned_part(ConverterConfig(params=str(tmp / "params.toml"), boards=(7,)).spec)
    # The whole focal plane: every stream, the subscriptions of before.
    whole = ConverterConfig(params=str(tmp / "params.toml"))
    assert len(owned_part(whole.spec)[1]) == 6 and subscriptions(whole, owned_part(whole.spec)[1])[0] == "mntes/lab/hk/**"


def test_owns_travels_in_status_and_provenance_and_is_checked():
    st = StatusMessage(setup="lab", service="c", t_ns=1, uptime_s=0, interval_s=0, owns={"shard": "1/3", "held": ["0/1"]})
    assert StatusMessage.from_bytes(st.to_bytes()).owns == {"shard": "1/3", "held": ["0/1"]}
    plain = StatusMessage(setup="lab", service="c", t_ns=1, uptime_s=0, interval_s=0)
    assert b"owns" not in plain.to_bytes()  # an unsharded converter's bytes are those of before
    prov = Provenance("lab", "", "id", "table", "0", 1, owns={"shard": "0/2", "streams": 3})
    assert Provenance.from_bytes(prov.to_bytes()).owns["streams"] == 3
    with pytest.raises(SchemaError, match="owns"):
        StatusMessage(setup="lab", service="c", t_ns=1, uptime_s=0, interval_s=0, owns={"x": {"nested": 1}})


def test_claims_decide_who_publishes_and_a_withdrawn_claim_hands_over():
    port = free_tcp_port()
    streams = [(0, 0), (0, 1)]
    with open_session(loopback(port)) as za, open_session(loopback(None, [port])) as zb:
        first = StreamClaims(za, "lab", "first", streams)
        time.sleep(0.2)
        second = StreamClaims(zb, "lab", "second", streams[1:], standby=True)
        deadline = time.monotonic() + 5
        while (not first.others() or not second.others()) and time.monotonic() < deadline:
            time.sleep(0.02)
        assert first.publishing() == frozenset(streams)  # claimed first: publishes both
        assert second.publishing() == frozenset()  # the standby holds back ...
        assert [c.name for c in second.others()[(0, 1)]] == ["first"] and first.others()[(0, 1)][0].standby
        version = second.version
        first.close()  # ... until the first withdraws: the standby publishes, told at once
        while second.version == version and time.monotonic() < deadline:
            time.sleep(0.01)
        assert second.publishing() == frozenset({(0, 1)})
        second.close()


def test_coverage_reports_counts_without_power_and_power_gaps():
    cov = Coverage(after_s=1.0)
    for k in range(5):
        cov.add("mntes/lab/counts/0/1", k, float(k))
        cov.add("mntes/lab/counts/0/2", k, float(k))
        if k < 2:
            cov.add("mntes/lab/power/0/1", k, float(k))
        cov.add("mntes/lab/power/0/2", k, float(k))
    assert cov.unconverted(4.5) == ["0/1"]
    cov.add("mntes/lab/power/0/1", 4, 5.0)  # back after seq 2 and 3
    assert cov.summary(5.0) == {"streams": 2, "unconverted": [], "unconverted_why": {}, "power_only": [],
                                "power_gaps": {"0/1": 2}, "power_late": {}}
    assert cov.unconverted(9.0) == []  # counts stopped too: nothing to convert


def test_recorder_shards_split_streams_and_keep_the_rest_once():
    keep = [shard_filter(Shard(i, 2)) for i in range(2)]
    for b, m in itertools.product(range(2), range(5)):
        for topic in (f"mntes/lab/counts/{b}/{m}", f"mntes/lab/power/{b}/{m}", f"mntes/lab/hk/bias/{b}/{m}"):
            assert [k(topic) for k in keep].count(True) == 1
            assert keep[1 - Shard(0, 2).owns(b, m)](topic)
    for topic in ("mntes/lab/hk/t_bath", "mntes/lab/status/converter", "mntes/lab/weird"):
        assert [k(topic) for k in keep] == [True, False]
    assert [k("mntes/lab/provenance") for k in keep] == [True, True]
    assert shard_filter(Shard()) is None
    assert RecorderConfig(shard="1/2").file_prefix == "mntes-shard1of2" and RecorderConfig().file_prefix == "mntes"


def _with_bias_readings(msgs, sc, setup="lab"):
    """The stream with bias readings of module (0, 1) during its second half: steps with and without bias."""
    from mntes_stream.io.messages import HousekeepingChunk

    out, seq = [], 0
    t_half = msgs[len(msgs) // 2][2]
    for k, p, t in msgs:
        out.append((k, p, t))
        if keys.kind_of(k) == "counts" and t >= t_half and k.endswith("/0/1"):
            c = CountsChunk.from_bytes(p)
            ch = np.arange(sc.channels, dtype=np.int32)
            v = np.full((2, ch.size), 1.01) * np.array([[1.0], [0.999]]) * MinimalSource(sc).params[0].v_thev_v
            hk = HousekeepingChunk(setup=setup, sensor="bias", seq=seq, t_ns=np.array([c.t0_ns, c.t0_ns + 10**8]),
                                   value=v, unit="V", board=0, module=1, channels=ch)
            out.append((keys.hk_key(setup, keys.bias_sensor(0, 1)), hk.to_bytes(), t))
            seq += 1
    return out


class _Calls:
    """A real converter, counting its calls."""

    def __init__(self, conv):
        self.conv, self.calls = conv, 0

    def __getattr__(self, name):
        return getattr(self.conv, name)

    def convert(self, *args):
        self.calls += 1
        return self.conv.convert(*args)


@pytest.mark.parametrize("bias,threads", [(False, 1), (True, 1), (True, 3)])
def test_batched_handling_gives_the_power_of_message_by_message(array, bias, threads, monkeypatch):
    """handle_many converts the modules of a step in one call, and a backlog of steps in one call per run of
    steps with the same rows (split across threads if asked): the same power and flags as handle(),
    message by message."""
    from mntes_stream.core.convert import make_converter
    from mntes_stream.pipeline import convert as pipeline_convert

    monkeypatch.setattr(pipeline_convert, "_SPLIT_SAMPLES", 0)  # this small array's runs are split too

    _, sc = array
    src = MinimalSource(sc)
    conv = make_converter("table", {p.detector_id: p for p in src.params})
    msgs = [(k, p, t + 2_000_000) for t, batch in src.batches(10**18, duration_s=2.0) for k, p in batch]
    if bias:
        msgs = _with_bias_readings(msgs, sc)

    def powers(outs):
        return {(pw.board, pw.module, pw.seq): pw for pw in (PowerChunk.from_bytes(p) for k, p in outs
                                                             if keys.kind_of(k) == "power")}

    one = ConverterPipeline(conv, PipelineConfig(), clock=None)
    single = powers([o for m in msgs for o in one.handle(*m)] + one.flush())
    many = ConverterPipeline(conv, PipelineConfig(), clock=None)
    outs = []
    for _, group in itertools.groupby(msgs, key=lambda m: m[2]):
        outs += many.handle_many(list(group))
    stepwise = powers(outs + many.flush())
    backlog = ConverterPipeline(_Calls(conv), PipelineConfig(), clock=None, threads=threads)
    in_order = backlog.handle_many(msgs) + backlog.flush()
    whole = powers(in_order)
    assert len(whole) == len(stepwise) == len(single) == 6 * 21  # 2 s of 15-sample chunks at 152.6 Hz
    for k, pw in single.items():
        for other in (stepwise[k], whole[k]):
            np.testing.assert_array_equal(other.p_opt_w, pw.p_opt_w)
            np.testing.assert_array_equal(other.flags, pw.flags)
            assert other.detector_ids == pw.detector_ids
    assert np.isfinite(pw.p_opt_w).all()
    # Each stream's power comes out in sequence order; the backlog took few converter calls.
    seqs = [(pw.board, pw.module, pw.seq) for pw in (PowerChunk.from_bytes(p) for k, p in in_order
                                                      if keys.kind_of(k) == "power")]
    for stream in {s[:2] for s in seqs}:
        assert [s[2] for s in seqs if s[:2] == stream] == sorted(s[2] for s in seqs if s[:2] == stream)
    # (the last step waits for housekeeping until flush(); with bias, three row layouts, two in the last step;
    # step by step it would take one call per step and layout: 21 or 32)
    assert backlog.converter.calls <= (5 if bias else 2) * threads
    assert (backlog.stages["convert"]._executor is not None) == (threads > 1)
    if bias:
        assert any(np.any(pw.p_opt_w != single[(0, 0, pw.seq)].p_opt_w) for pw in whole.values()
                   if (pw.board, pw.module) == (0, 1))  # the bias readings changed the power


def test_claims_of_a_large_focal_plane():
    """1,200 streams (more claims than zenoh's default reply channel holds): seen at once, handed over at once."""
    port = free_tcp_port()
    streams = [(b, m) for b in range(20) for m in range(60)]
    with open_session(loopback(port)) as za, open_session(loopback(None, [port])) as zb:
        first = StreamClaims(za, "lab", "first", streams)
        second = StreamClaims(zb, "lab", "second", streams, standby=True)
        assert len(second.others()) == len(streams) and not second.publishing()
        first.close()
        deadline = time.monotonic() + 10
        while second.publishing() != frozenset(streams):
            assert time.monotonic() < deadline, len(second.publishing())
            time.sleep(0.01)
        second.close()
