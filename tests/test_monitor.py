"""The monitor's pure core: decimation, spectra, HWP harmonics, channel states, health, text table."""

from __future__ import annotations

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from mntes_stream.core import flags as fl
from mntes_stream.errors import ConfigError
from mntes_stream.io.messages import HousekeepingChunk, PowerChunk, StatusMessage, detector_ids_for
from mntes_stream.monitor.aggregate import STATE_NAMES, Aggregator, MonitorConfig
from mntes_stream.monitor.analysis import decimate_minmax, estimate_f_hwp, log_bin, welch_psd
from mntes_stream.monitor.text import render_text

FS = 100.0
T0 = 1_700_000_000_000_000_000


# ------------------------------------------------------------------ decimation


@settings(max_examples=60, deadline=None)
@given(
    y=hnp.arrays(np.float64, st.integers(1, 700), elements=st.floats(-1e3, 1e3) | st.just(np.nan)),
    max_points=st.integers(2, 200),
)
def test_minmax_decimation_keeps_every_bucket_extreme(y, max_points):
    t = np.arange(y.size, dtype=np.int64) * 10
    td, yd = decimate_minmax(t, y, max_points)
    assert td.shape == yd.shape and td.size <= max(max_points, 2)
    if y.size <= max_points:
        np.testing.assert_array_equal(yd, y)
        return
    # Independent reference: split into the same buckets and take nanmin / nanmax.
    n_buckets = max_points // 2
    size = -(-y.size // n_buckets)
    for b, start in enumerate(range(0, y.size, size)):
        chunk = y[start:start + size]
        finite = chunk[np.isfinite(chunk)]
        lo, hi = yd[2 * b], yd[2 * b + 1]
        if finite.size:
            assert lo == finite.min() and hi == finite.max()
        else:
            assert np.isnan(lo) and np.isnan(hi)
        assert td[2 * b] == t[start]
    assert np.all(np.diff(td) >= 0)


def test_minmax_decimation_of_several_traces_matches_one_by_one():
    rng = np.random.default_rng(1)
    y = rng.standard_normal((3, 5000))
    t = np.arange(5000)
    td, yd = decimate_minmax(t, y, 300)
    for i in range(3):
        t1, y1 = decimate_minmax(t, y[i], 300)
        np.testing.assert_array_equal(td, t1)
        np.testing.assert_array_equal(yd[i], y1)
    assert yd.max() == y.max() and yd.min() == y.min()


# ------------------------------------------------------------------ spectra


def test_welch_white_noise_level_and_line_power():
    rng = np.random.default_rng(2)
    n = 30 * int(FS)
    sigma, amp, f_line = 2.0, 3.0, 5.0
    t = np.arange(n) / FS
    y = sigma * rng.standard_normal((2, n)) + amp * np.sin(2 * np.pi * f_line * t)
    y[1, ::7] = np.nan  # flagged samples: filled, the row still has a spectrum
    f, p = welch_psd(y, FS)
    df = f[1] - f[0]
    white = np.median(p[0, (f > 10) & (f < 40)])
    assert white == pytest.approx(2 * sigma**2 / FS, rel=0.1)  # one-sided density of white noise
    line = (f > f_line - 4 * df) & (f < f_line + 4 * df)
    assert np.sum(p[0, line] - white) * df == pytest.approx(amp**2 / 2, rel=0.05)  # Parseval: mean square of the sine
    assert np.all(np.isfinite(p[1]))
    # A row with fewer than half its samples valid has no spectrum (NaN), not a made-up one.
    y[1, : n * 2 // 3] = np.nan
    _, p = welch_psd(y, FS)
    assert np.all(np.isnan(p[1])) and np.all(np.isfinite(p[0]))


def test_log_bin_keeps_sparse_bins_and_averages_dense_ones():
    f = np.arange(0, 2049) * 0.05
    p = np.vstack([1.0 + f, 2.0 + 0 * f])
    fb, pb = log_bin(f, p, 300)
    assert fb.size <= 300 and np.all(np.diff(fb) > 0)
    np.testing.assert_allclose(pb[1], 2.0)
    # Each output point is the mean over the bins of its band: p = 1 + f is linear, so p_out = 1 + f_out.
    np.testing.assert_allclose(pb[0], 1.0 + fb, rtol=1e-12)
    # The lowest frequencies (HWP lines) keep their own bins.
    np.testing.assert_array_equal(fb[:10], f[1:11])


@pytest.mark.parametrize("f_hwp, harmonics", [(0.77, {2: 1.0}), (0.65, {1: 0.5, 4: 1.0}), (1.02, {2: 1.0, 4: 0.3})])
def test_estimate_f_hwp_finds_the_comb(f_hwp, harmonics):
    rng = np.random.default_rng(3)
    n = int(60 * FS)
    t = np.arange(n) / FS
    y = 0.3 * rng.standard_normal((4, n))
    for h, a in harmonics.items():
        y += a * np.sin(2 * np.pi * h * f_hwp * t + rng.uniform(0, 6, (4, 1)))
    f, p = welch_psd(y, FS)
    est = estimate_f_hwp(f, p)
    assert est == pytest.approx(f_hwp, abs=0.2 * (f[1] - f[0]))


def test_estimate_f_hwp_without_lines_or_resolution_finds_nothing():
    rng = np.random.default_rng(4)
    f, p = welch_psd(rng.standard_normal((4, 6000)), FS)
    assert estimate_f_hwp(f, p) is None
    # 6 s of a clear 2f line: bins of 0.2 Hz cannot tell 0.77 Hz from its neighbours.
    t = np.arange(600) / FS
    f, p = welch_psd(np.sin(2 * np.pi * 1.54 * t) + 0.1 * rng.standard_normal(600), FS, segments=1)
    assert f[1] > 0.55 / 4 and estimate_f_hwp(f, p) is None


# ------------------------------------------------------------------ aggregation


def power_chunk(module, seq, n=50, channels=8, flags=None, p=None, t0_ns=None, t_pub_ns=None, board=0):
    ch = np.arange(channels, dtype=np.int32)
    t0_ns = T0 + int(seq * n / FS * 1e9) if t0_ns is None else t0_ns
    if p is None:
        k = seq * n + np.arange(n)
        p = 0.5e-12 + 1e-14 * np.sin(2 * np.pi * 1.54 * k / FS) + 1e-16 * np.arange(channels)[:, None]
    f = np.zeros((channels, n), np.uint16) if flags is None else flags
    p = np.where((f & fl.UNUSABLE) != 0, np.nan, p)
    return PowerChunk("lab", board, module, ch, detector_ids_for(board, module, ch), seq, t0_ns, FS, p, f,
                      "tables-x", "table", t0_ns, t0_ns + 1000 if t_pub_ns is None else t_pub_ns)


def state_flags(n=50, channels=8):
    f = np.zeros((channels, n), np.uint16)
    f[1] = fl.SATURATED
    f[2, : n // 2] = fl.SUPERCONDUCTING
    f[2, n // 2: n // 2 + 10] = fl.SATURATED  # fewer than the superconducting samples
    f[3, : n // 5] = fl.HK_STALE             # 20% > flag_frac
    f[4, :2] = fl.OUT_OF_TABLE               # 4% < flag_frac: still in transition
    f[5, : n // 3] = fl.SATURATED            # a third of the time saturated (a bright source crossing)
    f[6, :3] = fl.SATURATED                  # 6%: transition
    f[6, 3:6] = fl.GAP
    return f


def test_channel_states_from_flags_and_silence():
    agg = Aggregator(MonitorConfig(silent_s=2.0))
    t_recv = T0
    agg.add_power(power_chunk(0, 0, flags=state_flags()), t_recv)
    agg.add_power(power_chunk(1, 0), t_recv)
    agg.tick(t_recv + int(0.5e9))
    names = {d: agg.state_of(d) for d in agg.detector_ids()}
    assert names["b0m0c000"] == "transition"
    assert names["b0m0c001"] == "saturated"
    assert names["b0m0c002"] == "superconducting"
    assert names["b0m0c003"] == "flagged"
    assert names["b0m0c004"] == "transition"
    assert names["b0m0c005"] == "saturated"
    assert names["b0m0c006"] == "transition"
    # Power missing without any flag is not trusted either.
    p = np.full((8, 50), 0.5e-12)
    p[7] = np.nan
    agg.add_power(power_chunk(1, 1, p=p), t_recv)
    agg.tick(t_recv + int(0.6e9))
    assert agg.state_of("b0m1c007") == "flagged" and agg.state_of("b0m1c006") == "transition"
    assert all(names[f"b0m1c{c:03d}"] == "transition" for c in range(8))
    # A tick without new samples keeps the states; only module 1 keeps talking.
    agg.add_power(power_chunk(1, 2), t_recv + int(1.5e9))
    tick = agg.tick(t_recv + int(1.0e9))
    assert agg.state_of("b0m0c001") == "saturated"
    tick = agg.tick(t_recv + int(2.6e9))
    assert agg.state_of("b0m0c001") == "silent" and agg.state_of("b0m1c001") == "transition"
    assert tick["codes"] == "4" * 8 + "0" * 8
    assert tick["state_counts"] == {"transition": 8, "saturated": 0, "superconducting": 0, "flagged": 0, "silent": 8}
    # Back to life with clean data: transition again.
    agg.add_power(power_chunk(0, 5), t_recv + int(3e9))
    agg.tick(t_recv + int(3.1e9))
    assert agg.state_of("b0m0c001") == "transition"


def test_ring_holds_the_last_history_in_order_and_ignores_late_chunks():
    agg = Aggregator(MonitorConfig(history_s=3.0))
    chunks = [power_chunk(0, s) for s in range(10)]  # 10 x 0.5 s = 5 s > 3 s of history
    for c in chunks:
        agg.add_power(c, c.t_pub_ns)
    buf = agg.modules[(0, 0)]
    t, p = buf.read(np.arange(8))
    t_all = np.concatenate([c.times_ns() for c in chunks])
    p_all = np.concatenate([c.p_opt_w for c in chunks], axis=1)
    assert t.size == buf.capacity == 300
    np.testing.assert_array_equal(t, t_all[-300:])
    np.testing.assert_allclose(p, p_all[:, -300:], rtol=1e-7)  # stored as float32
    # A late chunk (older than the newest) is counted, not drawn.
    agg.add_power(power_chunk(0, 9), chunks[-1].t_pub_ns)
    np.testing.assert_array_equal(buf.read(np.arange(1))[0], t_all[-300:])
    assert buf.late == 1
    # A stream that starts over far in the past (a replay looping) replaces the history.
    restart = power_chunk(0, 0, t0_ns=T0 - int(60e9))
    agg.add_power(restart, restart.t_pub_ns)
    np.testing.assert_array_equal(buf.read(np.arange(1))[0], restart.times_ns())
    assert buf.restarts == 1


def test_view_streams_spectrum_and_latency_marker():
    agg = Aggregator(MonitorConfig(history_s=30.0, max_points=200))
    for s in range(40):  # 20 s at 100 Hz, a 2f line at 1.54 Hz
        agg.add_power(power_chunk(0, s, t_pub_ns=T0 + s), T0)
    agg.tick(T0)
    view = agg.view(["b0m0c002", "nope", "b0m0c002", "b0m0c005"])
    assert view["selection"] == ["b0m0c002", "b0m0c005"] and view["unknown"] == ["nope"]
    assert view["newest_t_pub_ns"] == T0 + 39
    s = view["streams"][0]
    assert s["id"] == "b0m0c002" and len(s["t_ms"]) == len(s["p_pw"]) <= 200
    _, p = agg.modules[(0, 0)].read(np.array([2]))
    assert max(s["p_pw"]) == pytest.approx(np.nanmax(p) * 1e12, abs=1e-6)
    assert min(s["p_pw"]) == pytest.approx(np.nanmin(p) * 1e12, abs=1e-6)
    sp = view["spectrum"]
    assert sp["f_hwp_source"] == "configured" and sp["harmonics_hz"] == pytest.approx([0.77, 1.54, 3.08])
    f = np.array(sp["channels"][0]["f_hz"])
    asd = 10 ** np.array(sp["channels"][0]["log10_asd"])
    assert f.size <= agg.config.spectrum_points
    assert abs(f[np.argmax(asd)] - 1.54) < 0.1  # the line is where it was put
    est = agg.view(["b0m0c002"], None)["spectrum"]
    assert est["f_hwp_source"] == "estimated" and est["f_hwp_hz"] == pytest.approx(0.77, abs=0.02)
    json.dumps(view, allow_nan=False)


def test_health_rates_losses_and_stale_housekeeping():
    agg = Aggregator(MonitorConfig(hk_stale_s=2.0))
    agg.tick(T0)
    for s in (0, 1, 2, 5, 6):  # seq 3 and 4 lost
        agg.add_power(power_chunk(0, s, t_pub_ns=T0 - 3_000_000), T0)
    hk = HousekeepingChunk("lab", "t_bath", 0, np.array([T0, T0 + 10**8]), np.array([0.1, 0.1001]), "K")
    agg.add_hk(hk, T0)
    base = dict(setup="lab", service="converter", uptime_s=1.0, interval_s=1.0)
    agg.add_status(StatusMessage(t_ns=T0, chunks_received=10, **base), T0)
    agg.add_status(StatusMessage(t_ns=T0 + 2 * 10**9, chunks_received=50, rate_chunks_per_s=19.5, **base), T0)
    agg.add_bad("malformed")
    tick = agg.tick(T0 + 10**9)
    h = tick["health"]
    assert h["monitor"]["lost_chunks"] == 2 and h["monitor"]["power_chunks"] == 5
    assert h["monitor"]["chunks_per_s"] == pytest.approx(5.0)
    assert h["monitor"]["latency_p50_ms"] == pytest.approx(3.0)
    assert h["monitor"]["bad_messages"] == {"malformed": 1}
    conv = h["services"][0]
    assert conv["in_chunks_per_s"] == pytest.approx(20.0) and conv["out_chunks_per_s"] == 19.5
    assert h["hk"]["t_bath"]["value"] == 0.1001 and not h["hk"]["t_bath"]["stale"]
    assert h["hk"]["b_field"]["stale"]  # never received
    assert tick["hk"]["t_bath"]["value"] == [0.1, 0.1001]
    assert agg.tick(T0 + 4 * 10**9)["health"]["hk"]["t_bath"]["stale"]
    agg.report_render(T0, T0 + 250_000_000)
    agg.report_render(T0, T0 + 350_000_000)
    assert agg.tick(T0)["health"]["page_latency_ms"] == {"n": 2, "p50": 300.0, "max": 350.0, "last": 350.0}


def test_text_table_is_bounded_and_names_channels():
    agg = Aggregator()
    for m in range(3):
        agg.add_power(power_chunk(m, 0, channels=40, flags=np.full((40, 50), fl.SATURATED, np.uint16)), T0)
    text = render_text(agg, agg.tick(T0 + 10**8), max_listed=5)
    assert "saturated 120" in text and "b0m0c000 saturated" in text and "(+115 more)" in text
    assert len(text.splitlines()) <= 10


def test_default_selection_prefers_channels_in_transition():
    agg = Aggregator()
    agg.add_power(power_chunk(0, 0, flags=state_flags()), T0)
    agg.tick(T0)
    sel = agg.default_selection(3)
    assert sel == ["b0m0c000", "b0m0c004", "b0m0c006"]
    assert all(agg.state_of(d) == "transition" for d in sel)


def test_a_default_selection_settles_only_on_channels_in_transition():
    """CI saw a page keep [b0m0c000, b0m1c000, b0m2c000] with b0m2c000 saturated: the default was fixed at the
    first tick with any channel in transition, when the others were not yet classified so."""
    agg = Aggregator()
    flags = np.full((8, 50), fl.HK_STALE, np.uint16)
    flags[0] = 0  # only one channel usable yet (housekeeping not heard at the start)
    agg.add_power(power_chunk(0, 0, flags=flags), T0)
    agg.add_power(power_chunk(2, 0, channels=1, flags=np.full((1, 50), fl.SATURATED, np.uint16)), T0)
    agg.tick(T0)
    sel = agg.default_selection(3)
    assert sel == ["b0m0c000", "b0m2c000", "b0m0c001"]  # then any channel, module by module
    assert not agg.selection_settled(sel)
    agg.add_power(power_chunk(0, 1), T0 + 10**8)
    agg.add_power(power_chunk(2, 1, channels=1, flags=np.full((1, 50), fl.SATURATED, np.uint16)), T0 + 10**8)
    agg.tick(T0 + 10**8)
    sel = agg.default_selection(3)
    assert sel == ["b0m0c000", "b0m0c001", "b0m0c002"] and agg.selection_settled(sel)
    assert not agg.selection_settled(sel[:2])  # fewer than asked for: taken again as channels come


def test_config_rejects_nonsense():
    with pytest.raises(ConfigError):
        MonitorConfig(history_s=0)
    with pytest.raises(ConfigError):
        MonitorConfig(f_hwp_hz=-1.0)
    with pytest.raises(ConfigError):
        MonitorConfig(flag_frac=1.5)
    assert STATE_NAMES[0] == "transition"


def test_cli_arguments(capsys):
    from mntes_stream.cli import build_parser
    from mntes_stream.cli.monitor import monitor_config

    parser = build_parser()
    cfg = monitor_config(parser.parse_args(["monitor", "--f-hwp", "auto", "--port", "0"]))
    assert cfg.view.f_hwp_hz is None and cfg.port == 0 and cfg.bind == "127.0.0.1" and cfg.update_s == 0.5
    assert monitor_config(parser.parse_args(["monitor"])).view.f_hwp_hz == 0.77
    cfg = monitor_config(parser.parse_args(["monitor", "--allowed-hosts", "lab-pc", "lab-pc.example.org",
                                            "--long-history-s", "600", "--memory-mb", "400"]))
    assert cfg.allowed_hosts == ("lab-pc", "lab-pc.example.org") and cfg.view.long_history_s == 600
    assert cfg.view.memory_mb == 400
    for bad in (["--f-hwp", "-1"], ["--f-hwp", "x"]):
        with pytest.raises(SystemExit):
            parser.parse_args(["monitor", *bad])
    # Settings flags are checked as they are parsed (cli._common's declared types): one line, exit 2.
    for bad in (["--port", "70000"], ["--update-s", "0"], ["--history-s", "-1"], ["--leakage-detectors", "65"]):
        with pytest.raises(SystemExit):
            parser.parse_args(["monitor", *bad])
    out = capsys.readouterr().err
    assert "--port: expected an integer >= 0 and <= 65535, got '70000'" in out
    assert "--leakage-detectors: expected an integer >= 0 and <= 64, got '65'" in out
    cfg = monitor_config(parser.parse_args(["monitor", "--leakage-detectors", "4", "--leakage-window-s", "30"]))
    assert cfg.view.leakage_detectors == 4 and cfg.view.leakage_window_s == 30


def test_failed_housekeeping_reading_stays_valid_json():
    agg = Aggregator()
    hk = HousekeepingChunk("lab", "b_field", 0, np.array([T0, T0 + 10**8]), np.array([1e-6, np.nan]), "T")
    agg.add_hk(hk, T0)
    tick = agg.tick(T0)
    assert tick["health"]["hk"]["b_field"]["value"] is None  # the newest reading failed
    assert tick["hk"]["b_field"]["value"] == [1e-6, None]
    json.dumps(tick, allow_nan=False)


# ------------------------------------------------------------------ bounded memory, history, freshness, focal plane


def test_a_claimed_rate_costs_what_was_sent_not_what_was_claimed():
    agg = Aggregator()
    ch = np.arange(2, dtype=np.int32)
    chunk = PowerChunk("lab", 9, 0, ch, detector_ids_for(9, 0, ch), 0, T0, 1e6, np.full((2, 20), 1e-12),
                       np.zeros((2, 20), np.uint16), "tables-x", "table", T0, T0)
    agg.add_power(chunk, T0)
    buf = agg.modules[(9, 0)]
    assert buf.capacity == 30 * 200  # history_s x max_rate_hz, not 30 s x 1 MHz
    assert agg.memory()["held_bytes"] < 20_000
    np.testing.assert_array_equal(buf.read(np.arange(2))[0], chunk.times_ns())


def test_memory_budget_evicts_idle_modules_then_refuses():
    cfg = MonitorConfig(memory_mb=1.0, full_rate_channels=0, silent_s=3.0, leakage_detectors=0)
    assert 2 * cfg.module_bytes(8) < 1e6 < 3 * cfg.module_bytes(8)
    agg = Aggregator(cfg)
    agg.add_power(power_chunk(0, 0), T0)
    agg.add_power(power_chunk(1, 0), T0)
    agg.add_power(power_chunk(2, 0), T0)  # no room, nobody idle: refused and counted, no state kept
    assert sorted(agg.modules) == [(0, 0), (0, 1)] and agg.memory()["over_budget"] == 1
    assert agg.state_of("b0m2c000") is None
    agg.add_power(power_chunk(1, 1), T0 + int(3.5e9))
    agg.add_power(power_chunk(2, 1), T0 + int(4e9))  # module 0 has been idle 4 s > silent_s: evicted for it
    assert sorted(agg.modules) == [(0, 1), (0, 2)] and agg.memory()["evicted"] == 1
    assert agg.state_of("b0m0c000") is None and agg.memory()["reserved_bytes"] <= 1e6
    with pytest.raises(ConfigError, match="memory_mb"):
        MonitorConfig(memory_mb=10.0)  # cannot hold 16 full-rate channels for an hour
    with pytest.raises(ConfigError, match="leakage"):
        MonitorConfig(memory_mb=2.0, full_rate_channels=0, leakage_detectors=8)  # nor 8 x 2 leakage rings of 60 s


def test_services_are_capped_the_stalest_evicted():
    agg = Aggregator(MonitorConfig(max_services=3))
    for i in range(5):
        agg.add_status(StatusMessage("lab", f"s{i}", T0, 1.0, 0.2), T0 + i)
    assert sorted(agg.statuses) == ["s2", "s3", "s4"] and agg.memory()["services_evicted"] == 2


def test_downsampled_history_is_the_mean_of_each_bin():
    agg = Aggregator(MonitorConfig(history_s=2.0, long_history_s=60.0, slow_bin_s=1.0))
    chunks = [power_chunk(0, s, n=30) for s in range(40)]  # 12 s at 100 Hz, chunks straddle bins
    for c in chunks:
        agg.add_power(c, T0)
    t_all = np.concatenate([c.times_ns() for c in chunks])
    p_all = np.concatenate([c.p_opt_w for c in chunks], axis=1)
    t_bins, means = agg.modules[(0, 0)].slow.read()
    edges = t_all // 10**9
    closed = np.unique(edges)[:-1]  # the last bin is still open
    want = np.stack([p_all[:, edges == b].mean(axis=1) for b in closed], axis=1)
    np.testing.assert_array_equal(t_bins, closed * 10**9 + 5 * 10**8)
    np.testing.assert_allclose(means, want, rtol=1e-6)


def test_plotted_channels_keep_full_rate_over_the_long_window():
    agg = Aggregator(MonitorConfig(history_s=2.0, long_history_s=20.0, full_rate_channels=1, max_points=5000))
    agg.add_power(power_chunk(0, 0), T0)
    agg.watch(["b0m0c002"])
    chunks = [power_chunk(0, s) for s in range(1, 21)]  # 10 s more
    for c in chunks:
        agg.add_power(c, T0)
    agg.tick(T0)
    view = agg.view(["b0m0c002", "b0m0c005"], window_s=20.0)
    full, slow = view["streams"]
    assert full["resolution"] == "full rate" and slow["resolution"] == "1 s means"
    assert len(full["t_ms"]) == 21 * 50  # every sample since before it was plotted (the short ring held them)
    assert len(slow["t_ms"]) == 10  # closed 1 s bins
    assert len(agg.view(["b0m0c002"])["streams"][0]["t_ms"]) == 200  # the default window: history_s
    agg.watch(["b0m0c005"])  # one full-rate channel at most: the older one falls back to the means
    assert agg.memory()["full_rate_channels"] == ["b0m0c005"] and not agg.modules[(0, 0)].watched.get(2)


def test_freshness_goes_stale_after_three_chunk_intervals_and_says_replay():
    agg = Aggregator(MonitorConfig(stale_min_s=0.2))
    assert agg.tick(T0)["freshness"]["state"] == "waiting"
    for s in range(4):  # one 0.5 s chunk every 0.5 s
        agg.add_power(power_chunk(0, s, t_pub_ns=T0 + s * 500_000_000), T0 + s * 500_000_000 + 1_000_000)
    t_last = T0 + 1_501_000_000
    fr = agg.tick(t_last + 1_400_000_000)["freshness"]
    assert fr["state"] == "live" and fr["chunk_interval_s"] == pytest.approx(0.5)
    assert fr["threshold_s"] == pytest.approx(1.5)
    tick = agg.tick(t_last + 1_600_000_000)
    assert tick["freshness"]["state"] == "stale" and tick["freshness"]["age_s"] == pytest.approx(1.6)
    assert "STALE: no data for 1.6 s (> 1.50 s = 3 chunk intervals of 0.500 s)" in render_text(agg, tick)
    # A replay: published two days before it arrives. Latency is the recording's: last sample -> publication.
    day = 86_400 * 10**9
    rec = power_chunk(1, 0, t_pub_ns=T0 + 500_000_000 + 7_000_000)  # samples end at T0 + 0.49 s
    agg.add_power(rec, T0 + 2 * day)
    tick = agg.tick(T0 + 2 * day + 100_000_000)
    assert tick["freshness"]["state"] == "replay" and tick["freshness"]["newest_t_ns"] == int(rec.times_ns()[-1])
    assert tick["health"]["monitor"]["latency_p50_ms"] == pytest.approx(17.0)
    assert "REPLAY: recorded 2023-11-14 22:13:20 UTC" in render_text(agg, tick)


def test_focal_plane_figures_against_direct_computation():
    rng = np.random.default_rng(5)
    sigma = 2e-15
    p = 0.5e-12 + sigma * rng.standard_normal((8, 2000))
    f = np.zeros((8, 2000), np.uint16)
    f[3, :500] = fl.HK_STALE  # a quarter flagged
    agg = Aggregator()
    agg.add_power(power_chunk(0, 0, n=2000, p=p, flags=f), T0)
    focal = agg.tick(T0)["focal"]
    assert focal["power_pw"][0] == pytest.approx(p[0].mean() * 1e12, rel=1e-3)
    assert focal["power_pw"][3] == pytest.approx(p[3, 500:].mean() * 1e12, rel=1e-3)  # flagged samples are NaN
    assert focal["flag_pct"][3] == pytest.approx(25.0) and focal["flag_pct"][0] == 0
    # White noise: ASD = sigma sqrt(2 / fs), in aW/sqrt(Hz).
    assert focal["noise_aw_rthz"][0] == pytest.approx(sigma * np.sqrt(2 / FS) * 1e18, rel=0.06)
    assert len(focal["power_pw"]) == 8


def test_sky_positions_from_the_parameter_file(tmp_path):
    from mntes_stream.monitor.service import load_positions

    path = tmp_path / "p.toml"
    path.write_text('schema = "mntes-params"\nversion = 1\n[metadata.focal_plane]\nb0m0c000 = [1.5, -2]\n'
                    'b0m0c001 = [0.0, 3.25]\n')
    pos = load_positions(path)
    assert pos == {"b0m0c000": (1.5, -2.0), "b0m0c001": (0.0, 3.25)}
    agg = Aggregator(positions=pos)
    agg.add_power(power_chunk(0, 0, channels=3), T0)
    assert agg.layout()[0]["positions"] == [[1.5, -2.0], [0.0, 3.25], None]
    path.write_text('[metadata.focal_plane]\nb0m0c000 = [1.5, "x"]\n')
    with pytest.raises(ConfigError, match=r"metadata.focal_plane.b0m0c000 must be \[x_deg, y_deg\]"):
        load_positions(path)


def test_ring_grows_wraps_and_filters_like_the_last_samples_appended():
    from mntes_stream.monitor.history import Ring

    rng = np.random.default_rng(7)
    ring = Ring(3, 250)
    ts, vs, t = [], [], 0
    for _ in range(60):
        n = int(rng.integers(1, 40))
        tt = t + np.arange(n, dtype=np.int64) * 10
        t = int(tt[-1]) + 10
        v = rng.standard_normal((3, n)).astype(np.float32)
        ring.append(tt, v)
        ts.append(tt)
        vs.append(v)
        t_all, v_all = np.concatenate(ts)[-250:], np.concatenate(vs, axis=1)[:, -250:]
        got_t, got_v = ring.read()
        np.testing.assert_array_equal(got_t, t_all)
        np.testing.assert_array_equal(got_v, v_all)
        since = int(t_all[len(t_all) // 3]) + 5
        got_t, got_v = ring.read(np.array([2, 0]), since)
        keep = t_all >= since
        np.testing.assert_array_equal(got_t, t_all[keep])
        np.testing.assert_array_equal(got_v, v_all[[2, 0]][:, keep])
    assert ring.nbytes <= Ring.max_nbytes(3, 250)
