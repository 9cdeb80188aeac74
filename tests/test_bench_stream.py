"""``mntes-stream bench stream``: its per-process CPU accounting, and a run on a tiny array (real processes, loopback)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

from mntes_stream.bench.stream import _cpu_in, _cpu_s


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


def test_bench_stream_on_a_tiny_array():
    """Every chunk converted and recorded, and each process's cores and the ratios reported and consistent."""
    res = subprocess.run([sys.executable, "-m", "mntes_stream", "bench", "stream", "--modules", "2", "--channels", "8",
                          "--duration", "3", "--warmup", "0.5", "--passthrough-s", "1", "--threads", "2",
                          "--compression", "lz4", "--json"], capture_output=True, text=True, timeout=600)
    assert res.returncode == 0, res.stderr
    out = json.loads(res.stdout)
    assert out["all_services_ok"] and out["converter_threads"] == 2
    assert out["lost"] == 0 and out["chunks_recorded"] == out["chunks_sent"] > 0
    assert out["msamples_per_s"] == pytest.approx(2 * 8 * out["sample_rate_hz"] / 1e6, rel=0.05)
    assert out["ratio_to_passthrough"] == pytest.approx(out["msamples_per_s"] / out["passthrough_msamples_per_s"],
                                                        abs=1e-3)
    cores = out["cores_during_stream"]
    assert set(cores) == {"recorder", "converter", "sink", "source"}
    assert all(0 <= c <= os.cpu_count() + 0.1 for c in cores.values())
    assert cores["converter"] > 0 and out["cores_during_passthrough"]["sink"] > 0
    per_core = out["msamples_per_s"] / cores["converter"]
    assert out["converter_msamples_per_core_s"] == pytest.approx(per_core, rel=0.01, abs=1e-3)
    assert out["ratio_per_core"] == pytest.approx(
        out["converter_msamples_per_core_s"] / out["passthrough_msamples_per_core_s"], rel=0.01, abs=1e-3)
