"""Housekeeping alignment: property tests against a per-sample reference and exact cases."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mntes_stream.core import flags as fl
from mntes_stream.core.align import HkSeries, align, last_sample_offset_ns, sample_times_ns
from mntes_stream.errors import ConfigError

T0 = 1_700_000_000_000_000_000  # realistic ns epoch: precision must survive it


def reference(t, ht, hv, staleness, valid_range=None):
    """Per-sample loop, written from the module docstring (independent of the vectorised code)."""
    keep = [i for i in range(len(ht)) if np.all(np.isfinite(hv[i]))]
    ht, hv = [int(ht[i]) for i in keep], [np.asarray(hv[i], float) for i in keep]
    bad = [valid_range is not None and not np.all((v >= valid_range[0]) & (v <= valid_range[1])) for v in hv]
    values, flags = [], []
    for ti in map(int, t):
        before = [i for i, x in enumerate(ht) if x <= ti]
        after = [i for i, x in enumerate(ht) if x >= ti]
        f = 0
        if not ht:
            values.append(np.nan), flags.append(fl.HK_MISSING)
            continue
        if before and after:
            p, q = before[-1], after[0]
            if p == q:
                v, age, used = hv[p], 0, [p]
            else:
                w = (ti - ht[p]) / (ht[q] - ht[p])
                v = hv[p] + w * (hv[q] - hv[p])
                age = min(ti - ht[p], ht[q] - ti)
                used = [p, q]
        elif before:
            p = before[-1]
            v, age, used = hv[p], ti - ht[p], [p]
        else:
            q = after[0]
            v, age, used = hv[q], ht[q] - ti, [q]
            if age > staleness:
                values.append(np.nan * hv[q]), flags.append(fl.HK_MISSING)
                continue
        if age > staleness:
            f |= fl.HK_STALE
        if any(bad[i] for i in used):
            f |= fl.ENV_OUT_OF_RANGE
        values.append(v), flags.append(f)
    return np.array(values, dtype=float), np.array(flags, dtype=np.uint16)


@st.composite
def scenarios(draw, width=None):
    m = draw(st.integers(0, 8))
    ht = T0 + np.cumsum(np.array(draw(st.lists(st.integers(1, 10**9), min_size=m, max_size=m)), dtype=np.int64))
    shape = (m,) if width is None else (m, width)
    vals = st.floats(-1.0, 1.0) | st.sampled_from([np.nan, 5.0])
    hv = np.array(draw(st.lists(vals, min_size=int(np.prod(shape)), max_size=int(np.prod(shape)))), dtype=float).reshape(shape)
    lo = T0 - 2 * 10**9
    hi = T0 + 12 * 10**9
    t = np.array(draw(st.lists(st.integers(lo, hi) | st.sampled_from(list(ht) or [T0]), min_size=1, max_size=12)), dtype=np.int64)
    staleness = draw(st.integers(0, 3 * 10**9))
    return t, ht, hv, staleness


@settings(max_examples=300)
@given(scenarios(), st.booleans())
def test_matches_per_sample_reference(sc, with_range):
    t, ht, hv, staleness = sc
    rng = (-0.5, 0.5) if with_range else None
    a = align(t, ht, hv, staleness, rng)
    v_ref, f_ref = reference(t, ht, hv, staleness, rng)
    np.testing.assert_array_equal(a.flags, f_ref)
    np.testing.assert_allclose(a.value, v_ref, rtol=1e-12, atol=1e-15)
    assert np.all(np.isnan(a.value) == ((a.flags & fl.HK_MISSING) != 0))
    assert not np.any((a.flags & fl.HK_MISSING) & (a.flags & fl.HK_STALE))


@settings(max_examples=100)
@given(scenarios(width=3))
def test_per_channel_readings_align_column_by_column(sc):
    t, ht, hv, staleness = sc
    a = align(t, ht, hv, staleness)
    assert a.value.shape == (t.size, 3)
    v_ref, f_ref = reference(t, ht, hv, staleness)
    v_ref = np.array([np.broadcast_to(v, (3,)) for v in v_ref])
    np.testing.assert_array_equal(a.flags, f_ref)
    np.testing.assert_allclose(a.value, v_ref, rtol=1e-12, atol=1e-15)


@given(st.lists(st.integers(1, 10**9), min_size=2, max_size=10), st.floats(-1e3, 1e3), st.floats(-1e-6, 1e-6), st.data())
def test_linear_housekeeping_is_reproduced_between_readings(steps, a0, slope, data):
    ht = T0 + np.cumsum(np.array(steps, dtype=np.int64))
    hv = a0 + slope * (ht - T0)
    t = np.array(data.draw(st.lists(st.integers(int(ht[0]), int(ht[-1])), min_size=1, max_size=20)), dtype=np.int64)
    out = align(t, ht, hv, staleness_ns=10**10)
    np.testing.assert_allclose(out.value, a0 + slope * (t - T0), rtol=1e-9, atol=1e-9 * (abs(a0) + 1))
    assert not out.flags.any()
    # At the readings themselves: the readings, exactly.
    np.testing.assert_array_equal(align(ht, ht, hv, 0).value, hv)


def test_hold_stale_and_missing():
    ht = np.array([T0, T0 + 10**9])
    hv = np.array([0.1, 0.2])
    t = np.array([T0 - 2 * 10**9, T0 - 10**8, T0 + 5 * 10**8, T0 + 10**9 + 10**8, T0 + 3 * 10**9])
    a = align(t, ht, hv, staleness_ns=5 * 10**8)
    assert np.isnan(a.value[0]) and a.flags[0] == fl.HK_MISSING          # long before the first reading
    assert a.value[1] == 0.1 and a.flags[1] == 0                         # just before: first value
    assert a.value[2] == pytest.approx(0.15) and a.flags[2] == 0         # interpolated (age 0.5 s, not stale)
    assert a.value[3] == 0.2 and a.flags[3] == 0                         # held, fresh
    assert a.value[4] == 0.2 and a.flags[4] == fl.HK_STALE               # held, stale
    none = align(t, [], [], 10**9)
    assert np.all(np.isnan(none.value)) and np.all(none.flags == fl.HK_MISSING)


def test_out_of_range_flags_only_samples_using_the_bad_reading():
    ht = T0 + np.arange(4) * 10**9
    hv = np.array([0.1, 0.1, 9.0, 0.1])
    t = T0 + np.array([0, 5, 10, 15, 20, 25, 30]) * 10**8
    a = align(t, ht, hv, 10**9, valid_range=(0.0, 1.0))
    # At 1.0 s and 3.0 s only the good readings there are used; 1.5-2.5 s involve the 9.0.
    bad = fl.ENV_OUT_OF_RANGE
    assert a.flags.tolist() == [0, 0, 0, bad, bad, bad, 0]


def test_bad_inputs_raise_config_error():
    with pytest.raises(ConfigError):
        align([0], [2, 1], [0.0, 0.0], 10)
    with pytest.raises(ConfigError):
        align([0], [1, 2], [0.0], 10)
    with pytest.raises(ConfigError):
        align([0], [1], [0.0], -1)


@given(st.lists(st.tuples(st.integers(0, 50), st.floats(-1, 1)), min_size=1, max_size=30), st.randoms())
def test_series_is_order_independent_and_last_write_wins(readings, rnd):
    ordered = HkSeries()
    for t, v in readings:
        ordered.add([t], [v])
    shuffled = HkSeries()
    batches = list(readings)
    # Same readings in another order, in batches: for equal times the later write must still win.
    last = {}
    for t, v in readings:
        last[t] = v
    rnd.shuffle(batches)
    for i in range(0, len(batches), 3):
        part = sorted({t: v for t, v in batches[i:i + 3]}.items())
        shuffled.add([t for t, _ in part], [v for _, v in part])
    np.testing.assert_array_equal(ordered.t_ns, sorted(last))
    np.testing.assert_array_equal(ordered.value, [last[t] for t in sorted(last)])
    np.testing.assert_array_equal(shuffled.t_ns, ordered.t_ns)
    assert np.all(np.diff(ordered.t_ns) > 0)


def test_series_retention_bounds_memory():
    s = HkSeries(width=2, retention_ns=10)
    for k in range(100):
        s.add([k], [[k, -k]])
    assert len(s) == 11 and s.t_ns[0] == 89 and s.newest_t_ns == 99
    with pytest.raises(ConfigError):
        s.add([200], [1.0])


def test_sample_times():
    t = sample_times_ns(T0, 152.59, 1000)
    assert t.dtype == np.int64 and t[0] == T0
    np.testing.assert_array_equal(t - T0, np.rint(np.arange(1000) * 1e9 / 152.59).astype(np.int64))


@settings(max_examples=200)
@given(st.one_of(scenarios(), scenarios(width=3)), st.sampled_from([None, (-0.5, 0.5)]))
def test_series_window_gives_the_same_result_as_the_whole_history(sc, valid_range):
    """The series aligns its window without align()'s checks (its history is sorted and finite): the same bytes."""
    t, ht, hv, staleness = sc
    s = HkSeries(None if hv.ndim == 1 else hv.shape[1], retention_ns=10**12)
    s.add(ht, hv)
    whole = align(t, ht, hv, staleness, valid_range)
    windowed = s.align(t, staleness, valid_range)
    for a, b in ((windowed.flags, whole.flags), (windowed.value, whole.value), (windowed.age_ns, whole.age_ns)):
        assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes()  # -0.0 and NaN bits too


def test_sample_times_never_wrap():
    """int64 arithmetic wraps silently: a chunk whose last sample is beyond int64 ns must raise instead."""
    i64 = np.iinfo(np.int64).max
    assert sample_times_ns(i64 - 10**9, 1.0, 2)[-1] == i64           # the very last representable time
    for t0, rate, n in [(i64 - 10, 1.0, 2), (0, 1e-300, 2), (T0, 1e-9, 10**6), (0, float("nan"), 2),
                        (0, 0.0, 2), (0, -1.0, 2), (2**63, 1.0, 1), (0, 1e-300, 1)]:
        with pytest.raises(ConfigError):
            sample_times_ns(t0, rate, n)
    assert sample_times_ns(i64, 1.0, 1).tolist() == [i64]            # one sample: no span at all
    assert last_sample_offset_ns(152.59, 1000) == int(sample_times_ns(0, 152.59, 1000)[-1])


def test_series_prunes_against_the_callers_clock():
    """One reading stamped far ahead must not push the history out (HkSeries.add with now_ns)."""
    s = HkSeries(retention_ns=10 * 10**9)
    for k in range(20):
        s.add([T0 + k * 10**9], [0.1], now_ns=T0 + k * 10**9)
    s.add([T0 + 10**18], [9.0], now_ns=T0 + 19 * 10**9)               # a bogus future reading
    assert len(s) == 12 and s.t_ns[0] == T0 + 9 * 10**9                # history behind the clock kept
    a = s.align([T0 + 15 * 10**9], 10**9)
    assert a.value[0] == 0.1 and a.flags[0] == 0
    # Without a clock the newest reading is the clock: the documented hazard.
    legacy = HkSeries(retention_ns=10 * 10**9)
    legacy.add(T0 + np.arange(20) * 10**9, np.full(20, 0.1))
    legacy.add([T0 + 10**18], [9.0])
    assert len(legacy) == 1
    # The newest reading always stays, however old: a silent sensor's value holds (stale).
    quiet = HkSeries(retention_ns=10)
    quiet.add([5, 6], [0.1, 0.2], now_ns=10**12)
    assert quiet.t_ns.tolist() == [6]


@given(st.lists(st.tuples(st.integers(0, 40), st.floats(-1, 1)), min_size=1, max_size=40),
       st.integers(1, 7), st.randoms())
def test_unsorted_batches_with_repeated_times_keep_the_last_write(readings, batch, rnd):
    """Per-channel series, unsorted batches that repeat times: the history equals a dict of last writes."""
    s = HkSeries(width=2)
    last = {}
    for i in range(0, len(readings), batch):
        part = readings[i:i + batch]
        rnd.shuffle(part)
        for t, v in part:
            last[t] = v
        s.add([t for t, _ in part], [[v, -v] for _, v in part])
    times = sorted(last)
    np.testing.assert_array_equal(s.t_ns, times)
    np.testing.assert_array_equal(s.value, [[last[t], -last[t]] for t in times])
