"""Simulated G3 runs (``simulate --format g3``) against their truth, and the whole chain round trip.

- MNTES power (exact inverse) from a simulated G3 run, with a bias step, a
  nuller-gain change and a drifting bath, matches the simulator's truth to
  the power of half a count (the counts travel as whole counts), through
  spt3g's housekeeping conversions and a parameter file keyed by bolometer name.
- G3 in -> g3-bridge -> zenoh -> converter -> recorder -> ``convert REC OUT.g3``
  -> spt3g's G3Reader: bolometer names intact, every sample of the run there.
"""

from __future__ import annotations

import threading
import time

import numpy as np
import pytest

pytest.importorskip("spt3g.core")

from mntes_stream.core.sim import SimConfig  # noqa: E402
from mntes_stream.g3 import spt3g  # noqa: E402

T0_NS = 1_750_000_000 * 10**9


def read_back(path) -> list:
    """Every frame of ``path`` through spt3g's own G3Reader in a G3Pipeline."""
    core, _ = spt3g()
    frames = []
    pipe = core.G3Pipeline()
    pipe.Add(core.G3Reader, filename=str(path))
    pipe.Add(frames.append)
    pipe.Run()
    return frames


def _power(path, key="MntesOpticalPower"):
    core, _ = spt3g()
    p, f = {}, {}
    for frame in read_back(path):
        if frame.type == core.G3FrameType.Scan and key in frame:
            for name, ts in frame[key].items():
                p.setdefault(name, []).append(np.asarray(ts))
                f.setdefault(name, []).append(np.asarray(frame["MntesFlags"][name]))
    return {k: np.concatenate(v) for k, v in p.items()}, {k: np.concatenate(v) for k, v in f.items()}


def test_mntes_power_from_a_simulated_g3_run_matches_truth(tmp_path):
    from mntes_stream.core.ids import parse_detector_id
    from mntes_stream.g3.files import g3_to_g3
    from mntes_stream.g3.sim import bolometer_name, write_g3
    from mntes_stream.service.simulator import TruthRecorder

    cfg = SimConfig.noise_free(modules=2, channels=4, t_bath_wander_k=0.2e-3, t_bath_wander_period_s=60.0,
                               bias_steps=((1.0, 0.01),))
    truth = TruthRecorder([], cfg)
    res = write_g3(cfg, tmp_path / "sim.g3", 3.0, layout="scans", exact_counts=True, truth=truth, t0_ns=T0_NS,
                   gain_steps=((2.0, 6),), params_out=tmp_path / "p.toml")
    assert res["samples"] == 458
    assert "[detectors.\"Sim0.1.003\"]" in (tmp_path / "p.toml").read_text()  # keyed by bolometer name
    out = g3_to_g3(tmp_path / "sim.g3", tmp_path / "out.g3", params=tmp_path / "p.toml", kind="exact")
    assert out["housekeeping_changes"] >= 2  # the bias step and the gain change
    p, f = _power(tmp_path / "out.g3")
    want = np.concatenate([b.truth_p_opt_w for b in truth._blocks], axis=1)
    from mntes_stream.core.sim import ArraySimulator

    for k, det in enumerate(ArraySimulator(cfg).detector_ids):
        name = bolometer_name(*parse_detector_id(det))
        assert not f[name].any()
        # The converter's wire carries whole counts (int32): the simulator's exact (fractional) counts are rounded
        # there, so the power is the truth to within the power of half a count (1.8e-17 W here), not 1e-19 W.
        # Conversion of the counts read is exact: tests/test_g3_one_path.py (the same as the MCAP path, bit for bit).
        assert np.max(np.abs(p[name] - want[k])) <= 3e-17


def _running(service):
    import contextlib

    @contextlib.contextmanager
    def run():
        stop, ready, errors = threading.Event(), threading.Event(), []

        def main():
            try:
                service.start(stop, ready)
            except BaseException as exc:  # noqa: BLE001 - reported by the test
                errors.append(exc)
                ready.set()

        t = threading.Thread(target=main, daemon=True)
        t.start()
        try:
            assert ready.wait(60) and not errors, errors
            yield service
        finally:
            stop.set()
            t.join(30)
        assert not t.is_alive() and not errors, errors

    return run()


def test_round_trip_g3_bridge_converter_recorder_back_to_g3(tmp_path):
    from mntes_stream.cli import main
    from mntes_stream.g3.bridge import BridgeSettings, G3BridgeConfig, G3BridgeService
    from mntes_stream.g3.files import converter_params, g3_to_g3
    from mntes_stream.g3.mapping import Wiring
    from mntes_stream.g3.settings import G3InputConfig
    from mntes_stream.g3.sim import write_g3
    from mntes_stream.io.paramfile import dump_params
    from mntes_stream.io.transport import free_tcp_port, loopback
    from mntes_stream.service.converter import ConverterConfig, ConverterService
    from mntes_stream.service.recorder import RecorderConfig, RecorderService

    core, _ = spt3g()
    cfg = SimConfig.noise_free(modules=1, channels=4)
    run = tmp_path / "run.g3"
    write_g3(cfg, run, 2.0, layout="timepoints", t0_ns=T0_NS, params_out=tmp_path / "names.toml")
    pdict = converter_params(run, tmp_path / "names.toml")  # bolometer names -> detector ids, DfMux gain
    dump_params(list(pdict.values()), tmp_path / "ids.toml")
    conv_port, rec_port = free_tcp_port(), free_tcp_port()
    conv = ConverterService(ConverterConfig(params=str(tmp_path / "ids.toml"), kind="exact",
                                            zenoh=loopback(conv_port), provenance_interval_s=0.0))
    rec = RecorderService(RecorderConfig(directory=str(tmp_path / "rec"), flush_interval_s=0.2,
                                         zenoh=loopback(rec_port, [conv_port])))
    bridge = G3BridgeService(G3BridgeConfig(
        bridge=BridgeSettings(source=str(run), wait_subscribers_s=10.0), g3=G3InputConfig(),
        zenoh=loopback(None, [conv_port, rec_port])))
    with _running(conv), _running(rec):
        result = bridge.start()
        assert result["samples"] == 4 * 305 and result["gap_samples"] == 0
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and conv.status().get("samples_converted", 0) < 4 * 305:
            time.sleep(0.1)
        time.sleep(1.0)  # the recorder's flush cadence
    assert main(["convert", str(tmp_path / "rec"), str(tmp_path / "back.g3"), "--wiring", str(run), "--json"]) == 0
    names = set(Wiring.from_frame(next(iter(core.G3File(str(run))))).names)
    got, times = {}, []
    for frame in read_back(tmp_path / "back.g3"):
        if frame.type == core.G3FrameType.Scan:
            assert set(frame["MntesOpticalPower"].keys()) == names
            assert frame["MntesOpticalPower"].units == core.G3TimestreamUnits.Power
            times += [t.time * 10 for t in frame["DetectorSampleTimes"]]
            for k, ts in frame["MntesOpticalPower"].items():
                got.setdefault(k, []).append(np.asarray(ts))
    assert set(got) == names
    # The same power as the offline G3 path (OpticalPower on the file) gives, sample for sample.
    g3_to_g3(run, tmp_path / "offline.g3", params=tmp_path / "names.toml", kind="exact")
    offline, _ = _power(tmp_path / "offline.g3")
    for name in names:
        live = np.concatenate(got[name])
        assert np.isfinite(live).mean() > 0.9
        np.testing.assert_allclose(live, offline[name], rtol=0, atol=1e-21)
    assert sorted(times) == [T0_NS + round(k * 1e9 / cfg.sample_rate_hz) for k in range(305)]


def test_gain_change_applies_through_the_live_converter_pipeline(tmp_path):
    """convert RUN.g3 OUT.mcap (the messages the bridge publishes, the live converter's pipeline) on a run
    whose nuller gain changes at 1.5 s: the counts follow the converter's reference gain, so the power
    stays on the truth across the change (to DfMux count resolution, ~1e-17 W); with the old gain it
    would be off by the gain ratio."""
    from mntes_stream.core.ids import parse_detector_id
    from mntes_stream.core.sim import ArraySimulator
    from mntes_stream.g3.files import g3_to_mcap
    from mntes_stream.g3.sim import bolometer_name, write_g3
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import PowerChunk
    from mntes_stream.service.simulator import TruthRecorder

    cfg = SimConfig.noise_free(modules=1, channels=4)
    truth = TruthRecorder([], cfg)
    t_step = 1.5
    write_g3(cfg, tmp_path / "run.g3", 3.0, layout="timepoints", t0_ns=T0_NS, truth=truth, nuller_gain=2,
             gain_steps=((t_step, 9),), params_out=tmp_path / "names.toml")
    stats = g3_to_mcap(tmp_path / "run.g3", tmp_path / "out.mcap", params=tmp_path / "names.toml")
    assert stats.samples_converted == 4 * 458
    want_t = np.concatenate([b.t_ns for b in truth._blocks])
    want = np.concatenate([b.truth_p_opt_w for b in truth._blocks], axis=1)
    got: dict = {}
    for msg in Session(tmp_path / "out.mcap").iter_messages():
        if "/power/" in msg.topic:
            c = PowerChunk.from_bytes(msg.payload)
            for row, det in enumerate(c.detector_ids):
                got.setdefault(det, {}).update(zip(c.times_ns().tolist(), c.p_opt_w[row]))
    t_change = T0_NS + int(t_step * 1e9)
    for k, det in enumerate(ArraySimulator(cfg).detector_ids):
        assert bolometer_name(*parse_detector_id(det))  # the truth parameters were keyed by name
        p = np.array([got[det][t] for t in want_t.tolist()])
        after = want_t >= t_change
        assert np.isfinite(p[after]).mean() > 0.9 and np.isfinite(p[~after]).mean() > 0.9
        err = np.abs(p - want[k])
        assert np.nanmax(err[after]) < 1e-16 and np.nanmax(err[~after]) < 1e-16


def test_simulate_format_g3_cli_writes_run_truth_and_named_parameters(tmp_path, capsys):
    import json

    from mntes_stream.cli import main
    from mntes_stream.g3.mapping import Wiring
    from mntes_stream.io.paramfile import load_params
    from mntes_stream.service.simulator import load_truth

    core, _ = spt3g()
    for layout in ("timepoints", "scans"):
        out = tmp_path / f"{layout}.g3"
        assert main(["simulate", "--format", "g3", "--out", str(out), "--layout", layout, "--duration", "1",
                     "--modules", "2", "--channels", "4", "--gain-step", "0.5:5", "--json"]) == 0
        res = json.loads(capsys.readouterr().out)
        frames = read_back(out)
        kinds = {str(f.type) for f in frames}
        assert {"Wiring", "Housekeeping", "GcpSlow"} <= kinds
        assert ("Timepoint" in kinds) == (layout == "timepoints")
        wiring = Wiring.from_frame(frames[0])
        names = set(wiring.names)
        # The converter's file (detector ids, the run's gain) and the truth keyed by bolometer name.
        assert len(names) == 8 and set(load_params(res["bolometer_params"])) == names
        assert set(load_params(res["params"])) == set(wiring.detector_ids)
        truth = load_truth(res["truth"])
        assert set(truth["detector_ids"].tolist()) == names and truth["truth_p_opt_w"].shape == (8, 153)
        assert sum(str(f.type) == "Housekeeping" for f in frames) >= 2  # start + the gain step
    assert main(["simulate", "--format", "g3", "--out", str(tmp_path / "x.g3"), "--duration", "1",
                 "--gain-step", "soon"]) == 2
