"""The monitor's live leakage, on a real pipeline over zenoh on 127.0.0.1.

``mntes-stream simulate`` (HWP on, then off) -> ``mntes-stream serve`` (MNTES,
kind table) -> the monitor's subscriber in this process, which subscribes to
the measured detectors' counts and converts them with its linear shadow. Its
aggregate state must give the linear conversion's effective nonlinearity
within 20 % of the simulator's (the model's ``I''/S``, computed independently
of any fit), and with the HWP off say there is no 2f line instead of a number.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import time

import numpy as np
import pytest

from mntes_stream.core import validation
from mntes_stream.core.sim import ArraySimulator, SimConfig
from mntes_stream.io.paramfile import dump_params
from mntes_stream.io.transport import free_tcp_port, loopback
from mntes_stream.monitor.aggregate import MonitorConfig
from mntes_stream.monitor.leakage_live import LiveLeakage
from mntes_stream.monitor.subscriber import MonitorSubscriber
from mntes_stream.monitor.text import render_text

SIM = SimConfig(modules=1, channels=8)  # what `simulate --modules 1 --channels 8` runs (default seed)


@contextlib.contextmanager
def _process(args, log_path):
    with open(log_path, "w") as log:
        proc = subprocess.Popen([sys.executable, "-m", "mntes_stream", *args], stdout=log, stderr=log)
        try:
            yield proc
        finally:
            if proc.poll() is None:
                proc.terminate()
                try:
                    proc.wait(20)
                except subprocess.TimeoutExpired:
                    proc.kill()
                    proc.wait(5)


def _run(tmp_path, name, extra, done, timeout_s=150):
    """Simulator + converter + the monitor's subscriber until ``done(leakage)``; the last tick and the text."""
    sim = ArraySimulator(SIM)
    dump_params(list(sim.truth_params), tmp_path / "params.toml")
    p_sim, p_conv = free_tcp_port(), free_tcp_port()
    (tmp_path / f"{name}.toml").write_text(
        '[converter]\nsetup = "lab"\nparams = "params.toml"\nkind = "table"\n[status]\ninterval_s = 1.0\n'
        f'[zenoh]\nmode = "peer"\nlisten = ["tcp/127.0.0.1:{p_conv}"]\nconnect = ["tcp/127.0.0.1:{p_sim}"]\n')
    cfg = MonitorConfig(leakage_detectors=4, leakage_window_s=30.0, leakage_every_s=2.0)
    with contextlib.ExitStack() as stack:
        stack.enter_context(_process(
            ["simulate", "--listen", f"tcp/127.0.0.1:{p_sim}", "--setup", "lab", "--modules", "1", "--channels", "8",
             "--duration", "200", "--speed", "2", "--no-truth", *extra], tmp_path / f"{name}-simulate.log"))
        stack.enter_context(_process(["serve", "--config", str(tmp_path / f"{name}.toml"), "--duration", "200"],
                                     tmp_path / f"{name}-converter.log"))
        sub = stack.enter_context(MonitorSubscriber("lab", loopback(None, [p_conv, p_sim]), cfg))
        deadline = time.monotonic() + timeout_s
        tick = None
        while time.monotonic() < deadline:
            time.sleep(1.0)
            with sub.lock:
                tick = sub.aggregator.tick(time.time_ns())
                text = render_text(sub.aggregator, tick)
            if done(tick["leakage"]):
                return sim, tick, text
    logs = {p.name: p.read_text()[-1500:] for p in tmp_path.glob(f"{name}-*.log")}
    pytest.fail(f"leakage never complete within {timeout_s} s; last: {tick and tick['leakage']}; logs {logs}")


@pytest.mark.slow
def test_live_linear_leakage_is_the_simulators_and_says_no_2f_with_the_hwp_off(tmp_path):
    def full(leak):
        rows = leak.get("detectors", [])
        return bool(rows) and all(r["status"] == "ok" and r["window_s"] > 25 for r in rows)

    sim, tick, text = _run(tmp_path, "on", [], full)
    leak = tick["leakage"]
    params = {p.detector_id: p for p in sim.truth_params}
    kinds = {ch.detector_id: ch.kind for ch in sim.channels}
    assert [r["id"] for r in leak["detectors"]] == [d for d in sorted(kinds) if kinds[d] == "ok"][:4]
    assert leak["f_hwp_hz"] == pytest.approx(SIM.f_hwp_hz, abs=2e-3)
    for r in leak["detectors"]:
        expected = validation.expected_linear_nonlinearity_per_w(params[r["id"]]) * 1e-12
        print(f"{r['id']}: live {r['nl_per_pw']:.4g} +- {r['sigma_per_pw']:.2g}, model {expected:.4g} pW^-1, "
              f"window {r['window_s']} s")
        assert r["resolved"] and r["nl_per_pw"] == pytest.approx(expected, rel=0.2), r
        assert r["sigma_per_pw"] < 0.05 * abs(expected)
    assert leak["median"]["value_per_pw"] == pytest.approx(
        np.median([abs(r["nl_per_pw"]) for r in leak["detectors"]]), rel=1e-3)
    assert "not measurable live" in leak["mntes"]
    # The focal plane's colouring holds the same numbers, on the measured detectors' cells only.
    focal = tick["focal"]["linear_nl_per_pw"]
    assert sorted(v for v in focal if v is not None) == pytest.approx(
        sorted(abs(r["nl_per_pw"]) for r in leak["detectors"]))
    assert "linear conversion leakage" in text and "pW^-1" in text and "requirement 0.014" in text
    print("\n" + "\n".join(line for line in text.splitlines() if "leakage" in line or line.startswith("  ")))

    _, tick, text = _run(tmp_path, "off", ["--set", "simulator.hwp_2f_w=0.0"],
                         lambda leak: len(leak.get("detectors", [])) == 4
                         and all(r["status"] == "no_2f_line" and (r.get("window_s") or 0) > 25
                                 for r in leak["detectors"]))
    leak = tick["leakage"]
    assert all("nl_per_pw" not in r for r in leak["detectors"])
    assert leak["median"]["value_per_pw"] is None and leak["median"]["n_measured"] == 0
    assert all(v is None for v in tick["focal"]["linear_nl_per_pw"])
    assert "no 2f line" in text


def test_live_leakage_of_an_injected_quadratic_and_its_bounds():
    """The pure part alone: two series through the rings, the estimator's eps back, a bound where unresolved."""
    fs_hz, f_hwp = 152.587890625, 0.77
    leak = LiveLeakage(3, window_s=20.0, every_s=5.0, max_rate_hz=200.0)
    assert leak.choose(["b0m0c000", "b0m0c001", "b0m1c000", "b0m1c001"]) and leak.chosen[-1] == "b0m1c000"
    assert leak.modules() == [(0, 0), (0, 1)]
    rng = np.random.default_rng(0)
    t_ns = np.int64(1_700_000_000_000_000_000) + np.round(np.arange(int(30 * fs_hz)) / fs_hz * 1e9).astype(np.int64)
    t = (t_ns - t_ns[0]) * 1e-9
    d = 10e-15 * np.cos(4 * np.pi * f_hwp * t + 0.4)
    noise = 2e-17 * rng.standard_normal((3, t.size))
    mntes = 0.5e-12 + d + noise
    linear = mntes + np.array([[0.4e12], [0.0], [0.3e12]]) * d**2 + np.array([[0], [1e-15], [0]]) * rng.standard_normal(
        (3, t.size))
    ids = leak.chosen
    for k in range(0, t.size, 15):  # chunk by chunk, as they arrive; the linear ones one chunk behind
        leak.add("mntes", ids, t_ns[k:k + 15], mntes[:, k:k + 15])
        if k >= 15:
            leak.add("linear", ids, t_ns[k - 15:k], linear[:, k - 15:k])
    leak.no_baseline = {"b0m1c000"}
    res = leak.evaluate(int(t_ns[-1]), f_hwp)
    r0, r1, r2 = res["detectors"]
    assert r0["status"] == "ok" and r0["nl_per_pw"] == pytest.approx(0.8, rel=0.01) and r0["resolved"]
    assert r0["window_s"] == pytest.approx(20.0, abs=0.5)
    assert r1["status"] == "ok" and not r1["resolved"] and r1["bound_per_pw"] >= 3 * r1["sigma_per_pw"]
    assert r2 == {"id": "b0m1c000", "status": "no_linear_baseline"}
    assert res["median"]["n_measured"] == 2
    assert leak.focal() == {"b0m0c000": pytest.approx(0.8, rel=0.01), "b0m0c001": r1["bound_per_pw"]}
    assert not leak.due(int(t_ns[-1]) + 1) and leak.due(int(t_ns[-1]) + 5_000_000_000)
