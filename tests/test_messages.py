"""Stream messages: round trips, JSON Schema agreement, and rejection of bad input."""

from __future__ import annotations

import dataclasses

import msgpack
import numpy as np
import pytest
import schema_check
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from mntes_stream.core.ids import detector_id
from mntes_stream.errors import SchemaError
from mntes_stream.io import messages as m
from mntes_stream.io.codec import json_schema

I32 = st.integers(-(2**31), 2**31 - 1)
T_NS = st.integers(0, 2**62)
SETUP = st.from_regex(r"\A[A-Za-z0-9_.\-]{1,12}\Z")
SMALL = st.integers(0, 2**31)


@st.composite
def times(draw, n_samp):
    if draw(st.booleans()):
        return {"t0_ns": draw(T_NS), "sample_rate_hz": draw(st.floats(1e-3, 1e6))}
    start = draw(T_NS)
    steps = draw(st.lists(st.integers(0, 10**9), min_size=n_samp, max_size=n_samp))
    return {"t0_ns": None, "sample_rate_hz": None, "t_ns": start + np.cumsum(np.array(steps, dtype=np.int64))}


@st.composite
def channels(draw, max_ch=6):
    return np.array(draw(st.lists(st.integers(0, 4095), max_size=max_ch, unique=True)), dtype=np.int32)


@st.composite
def counts_chunks(draw):
    ch = draw(channels())
    n = draw(st.integers(0, 7))
    ints = st.lists(I32, min_size=ch.size * n, max_size=ch.size * n)
    return m.CountsChunk(
        setup=draw(SETUP), board=draw(SMALL), module=draw(SMALL), channels=ch, seq=draw(T_NS),
        counts_i=np.array(draw(ints), dtype=np.int64).reshape(ch.size, n),
        counts_q=np.array(draw(ints), dtype=np.int32).reshape(ch.size, n),
        t_pub_ns=draw(T_NS), **draw(times(n)),
    )


@st.composite
def hk_chunks(draw):
    sensor = draw(st.sampled_from(sorted(m.SENSOR_UNITS)))
    n = draw(st.integers(0, 6))
    t = np.cumsum(np.array(draw(st.lists(st.integers(1, 10**10), min_size=n, max_size=n)), dtype=np.int64))
    extra = {}
    width = None
    if sensor in m.PER_CHANNEL_SENSORS:
        ch = draw(channels())
        width = ch.size
        extra = {"board": draw(SMALL), "module": draw(SMALL), "channels": ch}
    shape = (n,) if width is None else (n, width)
    vals = st.floats(allow_nan=True, allow_infinity=True)
    value = np.array(draw(st.lists(vals, min_size=int(np.prod(shape)), max_size=int(np.prod(shape))))).reshape(shape)
    return m.HousekeepingChunk(draw(SETUP), sensor, draw(T_NS), t, value, m.SENSOR_UNITS[sensor], **extra)


@st.composite
def power_chunks(draw):
    ch = draw(channels())
    n = draw(st.integers(0, 7))
    board, module = draw(SMALL), draw(SMALL)
    size = ch.size * n
    p = draw(st.lists(st.floats(allow_nan=True), min_size=size, max_size=size))
    f = draw(st.lists(st.integers(0, 2**16 - 1), min_size=size, max_size=size))
    return m.PowerChunk(
        setup=draw(SETUP), board=board, module=module, channels=ch,
        detector_ids=[detector_id(board, module, c) for c in ch], seq=draw(T_NS),
        p_opt_w=np.array(p, dtype=float).reshape(ch.size, n), flags=np.array(f, dtype=np.uint16).reshape(ch.size, n),
        table_identity=draw(st.text(max_size=20)), converter_kind=draw(st.sampled_from(["exact", "table", "linear"])),
        source_t_pub_ns=draw(T_NS), t_pub_ns=draw(T_NS), **draw(times(n)),
    )


COUNT_MAPS = st.dictionaries(st.text(max_size=10), st.integers(0, 2**40), max_size=4)
OPT_MS = st.none() | st.floats(0, 1e6)


@st.composite
def statuses(draw):
    ints = {f.name: draw(st.integers(0, 2**50)) for f in dataclasses.fields(m.StatusMessage) if f.type == "int"}
    return m.StatusMessage(
        setup=draw(SETUP), service=draw(st.text(max_size=10)), uptime_s=draw(st.floats(0, 1e9)),
        interval_s=draw(st.floats(0, 1e3)), bad_messages=draw(COUNT_MAPS), flag_counts=draw(COUNT_MAPS),
        hk_age_s=draw(st.dictionaries(st.sampled_from(["t_bath", "b_field"]), st.floats(-1e3, 1e3))),
        rate_chunks_per_s=draw(st.floats(0, 1e6)), rate_msamples_per_s=draw(st.floats(0, 1e3)),
        latency_p50_ms=draw(OPT_MS), latency_p99_ms=draw(OPT_MS), latency_max_ms=draw(OPT_MS),
        last_error=draw(st.text(max_size=30)), **ints,
    )


@st.composite
def provenances(draw):
    return m.Provenance(draw(SETUP), draw(st.text()), draw(st.text(max_size=40)), "exact", "0.1.0", draw(T_NS))


ANY_MESSAGE = st.one_of(counts_chunks(), hk_chunks(), power_chunks(), statuses(), provenances())


def _same(a, b):
    assert type(a) is type(b)
    for f in dataclasses.fields(a):
        x, y = getattr(a, f.name), getattr(b, f.name)
        if isinstance(x, np.ndarray) or isinstance(y, np.ndarray):
            assert x.dtype == y.dtype and x.shape == y.shape, f.name
            np.testing.assert_array_equal(x, y, err_msg=f.name)
        else:
            assert x == y, f.name


@settings(max_examples=150, suppress_health_check=[HealthCheck.too_slow])
@given(ANY_MESSAGE)
def test_round_trip_and_schema(msg):
    payload = msg.to_bytes()
    schema_check.validate_payload(payload)
    _same(type(msg).from_bytes(payload), msg)
    _same(m.decode(payload), msg)


@settings(max_examples=60, suppress_health_check=[HealthCheck.too_slow])
@given(power_chunks())
def test_unchecked_construction_encodes_the_same_bytes(msg):
    """What the converter builds with unchecked() (its own, already checked values) is the checked message."""
    values = {f.name: getattr(msg, f.name) for f in dataclasses.fields(msg)}
    assert m.PowerChunk.unchecked(**values).to_bytes() == msg.to_bytes()
    del values["t_ns"]
    with pytest.raises(SchemaError, match="every field"):
        m.PowerChunk.unchecked(**values)


def test_every_field_is_in_its_schema_and_back():
    for name, cls in m.MESSAGE_TYPES.items():
        props = set(json_schema(name)["properties"]) - {"schema", "version"}
        assert props == {f.name for f in dataclasses.fields(cls)}, name


JUNK = st.recursive(
    st.none() | st.booleans() | st.integers(-(2**63), 2**64 - 1) | st.floats() | st.text(max_size=8) | st.binary(max_size=16),
    lambda inner: st.lists(inner, max_size=3) | st.dictionaries(st.text(max_size=5), inner, max_size=3),
    max_leaves=6,
)


def _mutate(data, msg: dict) -> dict:
    msg = dict(msg)
    key = data.draw(st.sampled_from(sorted(msg) + ["extra_field"]))
    action = data.draw(st.sampled_from(["delete", "junk", "array_field"]))
    if action == "delete":
        msg.pop(key, None)
    elif action == "array_field" and isinstance(msg.get(key), dict) and "dtype" in msg[key]:
        arr = dict(msg[key])
        sub = data.draw(st.sampled_from(["dtype", "shape", "data"]))
        arr[sub] = data.draw(JUNK | st.sampled_from(["<f4", ">i4", "<i8", "<u2"]) | st.just([1, 2]))
        msg[key] = arr
    else:
        msg[key] = data.draw(JUNK)
    return msg


@settings(max_examples=150, suppress_health_check=[HealthCheck.too_slow])
@given(ANY_MESSAGE, st.data())
def test_mutated_messages_raise_schema_error_only(msg, data):
    """Decoding never raises anything but SchemaError, and never accepts what the schema rejects."""
    raw = schema_check.unpack(msg.to_bytes())
    bad = _mutate(data, raw)
    payload = msgpack.packb(bad, use_bin_type=True)
    schema_rejects = bool(schema_check.errors(bad))
    try:
        decoded = type(msg).from_bytes(payload)
    except SchemaError as exc:
        assert exc.reason in m.REASONS
        return
    assert not schema_rejects, (bad, schema_check.errors(bad))
    schema_check.validate_payload(decoded.to_bytes())


@given(st.binary(max_size=64))
def test_random_bytes_raise_schema_error(payload):
    for cls in m.MESSAGE_TYPES.values():
        with pytest.raises(SchemaError):
            cls.from_bytes(payload)


def _counts(**changes):
    base = dict(setup="lab", board=0, module=1, channels=[0, 3], seq=5, t0_ns=10**18, sample_rate_hz=200.0,
                counts_i=np.zeros((2, 4), np.int32), counts_q=np.ones((2, 4), np.int32), t_pub_ns=10**18)
    base.update(changes)
    return m.CountsChunk(**base)


def test_rejection_reasons():
    good = _counts().to_bytes()
    raw = msgpack.unpackb(good)
    cases = {
        "malformed": [b"\xc1", b"", msgpack.packb([1, 2]), msgpack.packb({"a": 1}), "text"],
        "unknown_schema": [msgpack.packb(dict(raw, schema="mntes.nope"))],
        "wrong_version": [msgpack.packb(dict(raw, version=2)), msgpack.packb(dict(raw, version=0))],
        "wrong_schema": [m.Provenance("lab", "", "", "exact", "0", 1).to_bytes()],
        "invalid": [msgpack.packb(dict(raw, seq=-1)), msgpack.packb(dict(raw, extra=1)),
                    msgpack.packb({k: v for k, v in raw.items() if k != "counts_i"})],
    }
    for reason, payloads in cases.items():
        for payload in payloads:
            with pytest.raises(SchemaError) as info:
                m.CountsChunk.from_bytes(payload)
            assert info.value.reason == reason, (reason, payload, info.value)


@pytest.mark.parametrize(
    "make",
    [
        lambda: _counts(counts_i=np.zeros((3, 4), np.int32)),                      # rows != channels
        lambda: _counts(counts_q=np.zeros((2, 5), np.int32)),                      # I/Q shapes differ
        lambda: _counts(counts_i=np.full((2, 4), 2**31)),                          # beyond int32
        lambda: _counts(counts_i=np.zeros((2, 4))),                                # float counts
        lambda: _counts(channels=[1, 1]),                                          # repeated channel
        lambda: _counts(channels=[-1, 2]),
        lambda: _counts(t_ns=np.arange(4)),                                        # both time forms
        lambda: _counts(t0_ns=None, sample_rate_hz=None, t_ns=np.array([3, 2, 1, 0])),
        lambda: _counts(sample_rate_hz=0.0),
        lambda: _counts(sample_rate_hz=float("nan")),
        lambda: _counts(setup="a/b"),
        lambda: _counts(board=True),
        lambda: m.HousekeepingChunk("lab", "t_bath", 0, [1, 2], [0.1, 0.1], "mK"),   # wrong unit
        lambda: m.HousekeepingChunk("lab", "t_bath", 0, [2, 2], [0.1, 0.1], "K"),    # times not increasing
        lambda: m.HousekeepingChunk("lab", "bias", 0, [1], [[1e-6]], "V"),          # bias without channels
        lambda: m.HousekeepingChunk("lab", "b_field", 0, [1], [0.0], "T", board=0),
        lambda: m.HousekeepingChunk("lab", "bias", 0, [1], [[1e-6, 2e-6]], "V", board=0, module=0, channels=[4]),
        lambda: m.HousekeepingChunk("lab", "pressure", 0, [1], [1.0], "Pa"),
        lambda: m.PowerChunk("lab", 0, 1, [2], ["b0m1c003"], 0, 0, 10.0, np.zeros((1, 2)), np.zeros((1, 2), np.uint16),
                             "h", "exact", 0, 0),                                 # id does not match channel
        lambda: m.StatusMessage("lab", "c", 0, -1.0, 1.0),
    ],
)
def test_invalid_construction_raises_schema_error(make):
    with pytest.raises(SchemaError):
        make()


def test_times_convention():
    c = _counts(t0_ns=1_000_000_000, sample_rate_hz=152.59)
    t = c.times_ns()
    assert t.dtype == np.int64 and t[0] == 1_000_000_000
    np.testing.assert_array_equal(t, 1_000_000_000 + np.rint(np.arange(4) * 1e9 / 152.59).astype(np.int64))
    explicit = _counts(t0_ns=None, sample_rate_hz=None, t_ns=np.array([5, 6, 6, 9]))
    np.testing.assert_array_equal(m.CountsChunk.from_bytes(explicit.to_bytes()).times_ns(), [5, 6, 6, 9])


@pytest.mark.parametrize("changes", [
    {"t0_ns": 2**63 - 10, "sample_rate_hz": 1.0},        # the last sample (3 s later) is beyond int64
    {"t0_ns": 0, "sample_rate_hz": 1e-300},              # 1e-300 Hz: sample 1 at 1e309 ns
    {"sample_rate_hz": 1e-4},                             # below the accepted range
    {"sample_rate_hz": 2e6},                              # above it
])
def test_sample_times_that_cannot_exist_are_invalid(changes):
    """Before: t0_ns near INT64_MAX wrapped to negative times, 1e-300 Hz gave INT64_MIN, silently."""
    with pytest.raises(SchemaError) as info:
        _counts(**changes)
    assert info.value.reason == "invalid"
    raw = msgpack.unpackb(_counts().to_bytes())
    for cls in (m.CountsChunk, m.PowerChunk):
        if cls is m.PowerChunk:
            raw = msgpack.unpackb(m.PowerChunk("lab", 0, 1, [2], ["b0m1c002"], 0, 10**18, 200.0, np.zeros((1, 4)),
                                               np.zeros((1, 4), np.uint16), "h", "exact", 0, 0).to_bytes())
        with pytest.raises(SchemaError) as info:
            cls.from_bytes(msgpack.packb(dict(raw, **changes)))
        assert info.value.reason == "invalid"


def test_sample_times_at_the_limits_are_valid():
    lo, hi = m.SAMPLE_RATE_RANGE_HZ
    for rate in (lo, hi):
        assert _counts(sample_rate_hz=rate).times_ns()[0] == 10**18
    last = _counts(t0_ns=2**63 - 1 - 3 * 10**9, sample_rate_hz=1.0).times_ns()
    assert last[-1] == 2**63 - 1 and np.all(np.diff(last) == 10**9)


def test_every_status_field_is_checked_by_exactly_one_rule():
    """A counter added to StatusMessage without a check would travel unvalidated."""
    from dataclasses import fields

    S = m.StatusMessage
    ruled = list(S.RATES + S.LATENCIES + S.COUNTERS) + [
        "setup", "service", "last_error", "bad_messages", "flag_counts", "hk_age_s", "owns", "ledger", "began_at", "conflicts"]
    assert sorted(ruled) == sorted(f.name for f in fields(S))


def test_a_status_says_from_which_seq_a_converter_began_only_when_it_did_not_begin_at_the_start():
    base = dict(setup="lab", service="c", t_ns=1, uptime_s=0.0, interval_s=1.0)
    plain = m.StatusMessage(**base)
    assert "began_at" not in msgpack.unpackb(plain.to_bytes())  # the bytes of before
    began = m.StatusMessage(**base, began_at={"0/1": 196})
    assert m.StatusMessage.from_bytes(began.to_bytes()).began_at == {"0/1": 196}
    schema_check.validate_payload(began.to_bytes())  # status.v1.json declares it
    with pytest.raises(SchemaError):
        m.StatusMessage(**base, began_at={"0/1": "x"})


def test_counts_and_power_carry_names_as_detector_ids():
    """A source's names (dfmux-bridge: the boards') as the rows' ids: round trip, valid against the schemas,
    carried into the converter's power (the lean encoder's bytes equal the checked encoder's); ids that are not
    safe, repeated, of the wrong count, or another channel's b/m/c id are rejected."""
    from mntes_stream.io.lean import CountsDecoder, PowerEncoder

    named = _counts(detector_ids=["Lab0.1.00", "b0m1c003"])  # an unnamed channel keeps its own b/m/c id
    schema_check.validate_payload(named.to_bytes())
    back = m.CountsChunk.from_bytes(named.to_bytes())
    assert back.detector_ids == ("Lab0.1.00", "b0m1c003") and back.row_ids() == back.detector_ids
    assert _counts().row_ids() == ("b0m1c000", "b0m1c003") and _counts().detector_ids is None
    lean = CountsDecoder().decode("mntes/lab/counts/0/1", named.to_bytes())
    assert lean.detector_ids == back.detector_ids
    p, f = np.ones((2, 4)), np.zeros((2, 4), np.uint16)
    raw = PowerEncoder("lab", "t", "exact").encode(back, p, f, 10**18 + 1)
    schema_check.validate_payload(raw)
    power = m.PowerChunk.from_bytes(raw)
    assert power.detector_ids == ("Lab0.1.00", "b0m1c003")
    assert raw == m.PowerChunk("lab", 0, 1, [0, 3], list(back.detector_ids), 5, 10**18, 200.0, p, f, "t", "exact",
                               10**18, 10**18 + 1).to_bytes()
    for bad in (["Lab.a"], ["x", "x"], ["../x", "y"], ["Lab.a", "b0m1c000"], [1, 2], "Lab.a"):
        with pytest.raises(SchemaError):
            _counts(detector_ids=bad)
