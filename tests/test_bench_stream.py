"""``mntes-stream bench stream``: per-process CPU accounting, the real-time rate search, and a run on a tiny array
(real processes, loopback)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from mntes_stream.bench._stream_rate import find_rate, next_rate, trial_passes
from mntes_stream.bench.stream import (
    _cpu_in,
    _cpu_s,
    _per_process,
    _relay_template,
    _rss_growth,
    _rss_mb,
    _stamped,
    _steps,
    repeated,
)


def test_cores_come_from_the_samples_inside_the_window():
    s = 10**9
    samples = [(0, {"a": 0.0, "b": 0.0}), (1 * s, {"a": 0.5, "b": 0.1}), (3 * s, {"a": 2.5, "b": None}),
               (5 * s, {"a": 4.5, "b": 0.9}), (9 * s, {"a": 4.5, "b": 0.9})]
    # Inside [1 s, 5 s]: a used 4.0 s of CPU in 4 s, b 0.8 s.
    assert _cpu_in(samples, 1 * s, 5 * s) == {"a": 1.0, "b": 0.2}
    assert _cpu_in(samples, 5 * s, 9 * s) == {"a": 0.0, "b": 0.0}
    assert _cpu_in(samples, 2 * s, 4 * s) == {}  # one sample is no interval
    assert _cpu_in(samples, None, 4 * s) == {}
    assert _cpu_in([(0, {"a": None}), (s, {"a": 1.0})], 0, s) == {}  # unreadable at the start


def test_cpu_of_a_process_is_read_from_proc():
    if not os.path.exists(f"/proc/{os.getpid()}/stat"):
        pytest.skip("no /proc")
    before = _cpu_s(os.getpid())
    sum(i * i for i in range(2_000_000))  # some CPU of our own
    assert _cpu_s(os.getpid()) > before >= 0
    assert _cpu_s(2**22 + 12345) is None  # no such process


def test_rss_growth_per_half_comes_from_the_last_sample_at_each_point():
    s = 10**9
    samples = [(0, {"a": 100.0, "b": 50.0}), (4 * s, {"a": 180.0, "b": None}), (6 * s, {"a": 200.0, "b": 60.0}),
               (10 * s, {"a": 260.0, "b": 61.0})]
    # [0, 10 s]: middle 5 s -> the sample of 4 s; b unreadable there: left out.
    assert _rss_growth(samples, 0, 10 * s) == {"a": {"start": 100, "middle": 180, "end": 260, "first_half": 80,
                                                      "second_half": 80}}
    assert _rss_growth(samples, 6 * s, 10 * s)["b"] == {"start": 60, "middle": 60, "end": 61, "first_half": 0,
                                                         "second_half": 1}
    if os.path.exists(f"/proc/{os.getpid()}/statm"):
        before = _rss_mb(os.getpid())
        held = b"\x01" * (64 << 20)  # 64 MiB written, so resident
        assert _rss_mb(os.getpid()) - before > 60
        del held
        assert _rss_mb(2**22 + 12345) is None


def test_per_process_rates_are_samples_per_own_cpu_second():
    s = 10**9
    samples = [(0, {"conv": 0.0, "rec0": 0.0, "rec1": 0.0, "sink": 1.0}),
               (2 * s, {"conv": 1.0, "rec0": 0.5, "rec1": 0.25, "sink": 1.0})]
    # 10 M samples/s for 2 s = 20 M samples: the converter took them all in 1 CPU s, each shard half.
    got = _per_process(samples, 0, 2 * s, 10.0, {"conv": 1.0, "rec0": 0.5, "rec1": 0.5})
    assert got["conv"] == {"cpu_s": 1.0, "cores": 0.5, "msamples_per_cpu_s": 20.0}
    assert got["rec0"]["msamples_per_cpu_s"] == 20.0 and got["rec1"]["msamples_per_cpu_s"] == 40.0
    assert got["sink"] == {"cpu_s": 0.0, "cores": 0.0, "msamples_per_cpu_s": None}  # idle: no rate


def test_a_trial_passes_only_with_nothing_lost_shed_or_late_and_a_low_p99():
    good = {"all_services_ok": True, "lost": 0, "converter_shed": 0, "converter_late": 0, "latency_p99_ms": 40.0}
    assert trial_passes(good, 100.0) == (True, "")
    for change, why in (({"lost": 3}, "lost 3"), ({"converter_shed": 2}, "shed 2"), ({"converter_late": 1}, "late 1"),
                        ({"latency_p99_ms": 100.0}, "p99 100.0 ms"), ({"latency_p99_ms": float("nan")}, "p99 nan ms"),
                        ({"all_services_ok": False, "failed_services": ["source"]}, "a service failed (source)")):
        assert trial_passes({**good, **change}, 100.0) == (False, why)


def test_bisection_halves_until_a_pass_then_closes_in():
    assert next_rate(0.0, 10.0, 0.1) == 5.0
    assert next_rate(5.0, 10.0, 0.1) == 7.5
    assert next_rate(9.0, 10.0, 0.1) is None  # within 10 % of the lowest failing
    assert next_rate(0.0, 0.0, 0.1) is None


def test_the_search_finds_the_capacity_within_tolerance_and_budget():
    """The search against a pipeline stand-in that sustains 6.3 M samples/s (the real one is the last test)."""
    import argparse

    capacity = 6.3
    now = [0.0]

    def one_trial(a):
        now[0] += 70.0  # a trial's wall seconds
        rate = a.sample_rate * a.modules * a.channels / 1e6
        return {"all_services_ok": True, "lost": 0, "converter_shed": 0 if rate <= capacity else 5, "converter_late": 0,
                "latency_p99_ms": 30.0 if rate <= capacity else 900.0, "msamples_per_s": rate}

    args = argparse.Namespace(modules=40, channels=128, sustain=60.0, warmup=2.0, budget_s=3600.0, trials=8,
                              tolerance=0.1, p99_ms=100.0, flat_out=True, find_rate=True, keep=None, passthrough_s=3.0,
                              sample_rate=200.0, duration=None)
    lines = []
    res = find_rate(args, {"mode": "flat-out", "msamples_per_s": 9.0, "passthrough_msamples_per_s": 90.0},
                    run_once=one_trial, clock=lambda: now[0], say=lines.append)
    found, failing = res["msamples_per_s"], res["lowest_failing_msamples_per_s"]
    assert found <= capacity < failing and (failing - found) / failing <= 0.1
    assert res["ratio_to_passthrough"] == pytest.approx(found / 90.0, abs=1e-3)
    assert all(t["passed"] == (t["offered_msamples_per_s"] <= capacity) for t in res["trials"])
    assert len(lines) == 2 * len(res["trials"])  # one line as each trial starts, one as it ends
    # A budget for two trials: two run, the search says why it stopped, the best so far is reported.
    now[0], lines[:] = 0.0, []
    res = find_rate(argparse.Namespace(**{**vars(args), "budget_s": 150.0}),
                    {"mode": "flat-out", "msamples_per_s": 9.0, "passthrough_msamples_per_s": 90.0},
                    run_once=one_trial, clock=lambda: now[0], say=lines.append)
    assert len(res["trials"]) == 2 and "stopping" in lines[-1] and res["msamples_per_s"] <= capacity


@pytest.mark.parametrize("duration_s, rate_hz, n", [(60.0, 200.0, 20), (5.0, 152.587890625, 15), (0.35, 200.0, 20),
                                                   (1.0, 19.0, 2), (0.0999, 200.0, 20)])
def test_the_bench_expects_as_many_steps_as_the_source_sends(duration_s, rate_hz, n):
    # The wait for the converter ends on every chunk; counted apart from the source, so they must agree.
    from mntes_stream.service.source import MinimalSource, SourceConfig

    src = MinimalSource(SourceConfig(modules=1, channels=2, sample_rate_hz=rate_hz, chunk_s=n / rate_hz))
    src.prepare()
    sent = sum(1 for _ in src.batches(1_700_000_000_000_000_000, duration_s))
    assert _steps(duration_s, rate_hz, n) == sent > 0


def test_repeated_runs_give_medians_of_the_ratios_and_totals_of_what_went_missing():
    runs = [{"converter_overhead_per_relay": r, "converter_ratio_to_relay": 1 / r, "lost": lost, "converter_shed": 0,
             "msamples_per_s": 2.0, "converter_cpu_us_per_chunk": None, "stalled_s": stalled}
            for r, lost, stalled in ((1.4, 0, None), (1.2, 3, 61.0), (1.3, 0, None))]
    rep = repeated(runs)
    assert rep["runs"] == 3 and rep["per_run"]["lost"] == [0, 3, 0] and rep["per_run"]["stalled_s"] == [None, 61.0, None]
    assert rep["median"]["converter_overhead_per_relay"] == 1.3 and rep["median"]["msamples_per_s"] == 2.0
    assert "converter_cpu_us_per_chunk" not in rep["median"]  # a figure the runs lack has no median
    assert rep["total"] == {"lost": 3, "converter_shed": 0}  # a loss in one run is not hidden by a median of 0


def test_relay_power_is_the_converters_encoding_with_both_times_stamped():
    """The relay's message per chunk: byte for byte what the converter's encoder makes of zeros with these times."""
    import numpy as np

    from mntes_stream.io.lean import PowerEncoder
    from mntes_stream.io.messages import CountsChunk, PowerChunk

    counts = np.arange(3 * 20, dtype=np.int32).reshape(3, 20)

    def chunk(seq, t_pub_ns):
        return CountsChunk(setup="benchrelay", board=1, module=4, channels=np.array([0, 5, 9], np.int32), seq=seq,
                           t0_ns=1_700_000_000_000_000_000 + seq, sample_rate_hz=200.0, counts_i=counts,
                           counts_q=-counts, t_pub_ns=t_pub_ns)

    enc = PowerEncoder("benchrelay", "relay", "relay")
    key, head, mid = t = _relay_template(enc, "benchrelay", chunk(0, 1_764_000_000_000_000_000))
    assert key == "mntes/benchrelay/power/1/4"
    src, now = 1_764_000_000_123_456_789, 1_764_000_000_987_654_321
    msg = _stamped(t, src, now)
    # Only the two times are new: seq and t0_ns stay those of the stream's first chunk.
    assert msg == enc.encode(chunk(0, src), np.zeros((3, 20)), np.zeros((3, 20), np.uint16), t_pub_ns=now)
    pw = PowerChunk.from_bytes(msg)
    assert (pw.source_t_pub_ns, pw.t_pub_ns, pw.p_opt_w.shape, pw.module) == (src, now, (3, 20), 4)


def test_bench_stream_flat_out_and_one_real_time_trial_on_a_tiny_array():
    """Flat out then one real-time trial: every chunk converted and recorded, per-process figures consistent."""
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "bench", "stream", "--modules", "2", "--channels", "8",
                          "--flat-out", "--duration", "120", "--warmup", "0.5", "--passthrough-s", "1", "--relay-s", "0.5",
                          "--threads", "2",
                          "--compression", "lz4", "--find-rate", "--sustain", "2", "--trials", "1", "--json"],
                         capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["all_services_ok"] and not out["failed_services"]
    assert out["converter_threads"] == 2 and out["mode"] == "flat-out"
    assert out["lost"] == 0 and out["chunks_recorded"] == out["chunks_sent"] > 0
    assert out["ratio_to_passthrough"] == pytest.approx(out["msamples_per_s"] / out["passthrough_msamples_per_s"],
                                                        abs=1e-3)
    stream, passthrough, relay = (out["per_process"][k] for k in ("stream", "passthrough", "relay"))
    assert set(stream) == set(passthrough) == set(relay) == {"recorder", "converter", "sink", "source", "relay"}
    assert all(0 <= p["cores"] <= os.cpu_count() + 0.1 for p in stream.values())
    assert stream["converter"]["cpu_s"] > 0 and passthrough["sink"]["cpu_s"] > 0
    assert stream["sink"]["msamples_per_cpu_s"] is None and passthrough["converter"]["msamples_per_cpu_s"] is None
    conv = stream["converter"]
    assert out["converter_msamples_per_core_s"] == conv["msamples_per_cpu_s"] == pytest.approx(
        out["msamples_per_s"] / conv["cores"], rel=0.02)
    assert out["recorder_msamples_per_cpu_s"] == stream["recorder"]["msamples_per_cpu_s"]
    assert out["ratio_per_core"] == pytest.approx(
        out["converter_msamples_per_core_s"] / out["passthrough_msamples_per_core_s"], rel=0.01, abs=1e-3)
    # The relay phase: every chunk relayed, at a rate per core of its own; idle in the other phases.
    assert out["relay_chunks"] > 0 and out["relay_msamples_per_s"] > 0
    assert out["relay_msamples_per_core_s"] == relay["relay"]["msamples_per_cpu_s"] > 0
    assert stream["relay"]["msamples_per_cpu_s"] is None and relay["converter"]["msamples_per_cpu_s"] is None
    assert out["converter_ratio_to_relay"] > 0 and out["converter_ratio_to_relay"] == pytest.approx(
        out["converter_msamples_per_core_s"] / out["relay_msamples_per_core_s"], rel=0.01, abs=1e-3)
    # Per chunk: the converter's CPU inside its kernel calls is part of its CPU (threads 2: summed over both), and
    # the overhead is its CPU outside them over the relay's, from the figures beside it.
    per_chunk = out["converter_cpu_us_per_chunk"]
    kernel = out["converter_kernel_us_per_chunk"]
    assert out["converter_kernel_cpu_s"] > 0 and 0 < kernel < per_chunk
    # The tiny array's steps are 2 modules: a kernel call takes at least a chunk, at most a batch (512 messages).
    assert 1 <= out["converter_chunks_per_kernel_call"] <= 512
    assert per_chunk == pytest.approx(conv["cpu_s"] / out["chunks_converted"] * 1e6, rel=0.01)
    assert out["relay_cpu_us_per_chunk"] == pytest.approx(relay["relay"]["cpu_s"] / out["relay_chunks"] * 1e6, rel=0.05)
    assert out["converter_overhead_per_relay"] == pytest.approx((per_chunk - kernel) / out["relay_cpu_us_per_chunk"],
                                                                rel=0.02, abs=2e-3)
    rt = out["real_time"]
    (trial,) = rt["trials"]
    assert trial["offered_msamples_per_s"] == pytest.approx(out["msamples_per_s"] * 1.05 / 2, rel=1e-3)
    # Real time: what was offered is what came through, and the verdict follows the criterion.
    assert trial["msamples_per_s"] == pytest.approx(trial["offered_msamples_per_s"], rel=0.05)
    ok = trial["lost"] == 0 and not trial["converter_shed"] and trial["latency_p99_ms"] < 100
    assert trial["passed"] == ok and (rt["msamples_per_s"] == trial["offered_msamples_per_s"]) == ok
    assert "find-rate: trial 1:" in res.stderr
