"""One converter for G3: ``convert RUN.g3 OUT.g3`` (the OpticalPower module) goes through the same pipeline
stages as ``convert RUN.g3 OUT.mcap``: the same power and the same flags, HK_STALE included, bit for bit."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("spt3g.core")

from mntes_stream.core import flags as fl  # noqa: E402
from mntes_stream.core.sim import SimConfig  # noqa: E402

T0_NS = 1_750_000_000 * 10**9


def _g3_power(path):
    from mntes_stream.g3 import spt3g

    core, _ = spt3g()
    p, f = {}, {}
    for frame in core.G3File(str(path)):
        if frame.type == core.G3FrameType.Scan and "MntesOpticalPower" in frame:
            for k in frame["MntesOpticalPower"].keys():
                p.setdefault(k, []).append(np.asarray(frame["MntesOpticalPower"][k]))
                f.setdefault(k, []).append(np.asarray(frame["MntesFlags"][k]))
    return {k: np.concatenate(v) for k, v in p.items()}, {k: np.concatenate(v) for k, v in f.items()}


def _mcap_power(path, names):
    from mntes_stream.io.mcap import Session
    from mntes_stream.io.messages import PowerChunk

    p, f = {}, {}
    for m in Session(path).iter_messages():
        if "/power/" in m.topic:
            c = PowerChunk.from_bytes(m.payload)
            for d, row, fr in zip(c.detector_ids, c.p_opt_w, c.flags):
                p.setdefault(names[d], []).append(row)
                f.setdefault(names[d], []).append(fr)
    return {k: np.concatenate(v) for k, v in p.items()}, {k: np.concatenate(v) for k, v in f.items()}


@pytest.mark.parametrize("staleness_s", [60.0, 0.3])
def test_g3_to_g3_equals_g3_to_mcap_flags_and_all(tmp_path, staleness_s, monkeypatch):
    from mntes_stream.core.ids import parse_detector_id
    from mntes_stream.core.sim import ArraySimulator
    from mntes_stream.g3.files import g3_to_g3, g3_to_mcap
    from mntes_stream.g3.sim import bolometer_name, write_g3
    from mntes_stream.pipeline import PipelineConfig

    cfg = SimConfig.noise_free(modules=2, channels=4, t_bath_wander_k=0.2e-3, t_bath_wander_period_s=60.0,
                               bias_steps=((1.0, 0.01),), hk_t_bath_rate_hz=1.0)
    write_g3(cfg, tmp_path / "run.g3", 3.0, layout="scans", t0_ns=T0_NS, gain_steps=((2.0, 6),),
             params_out=tmp_path / "p.toml")
    pc = PipelineConfig(hk_staleness_s=staleness_s)
    monkeypatch.setenv("MNTES_STREAM_CACHE", str(tmp_path / "cache"))  # the default table cache, this test's own
    g3_to_g3(tmp_path / "run.g3", tmp_path / "out.g3", params=tmp_path / "p.toml",
             pipeline_config=pc)
    (bank,) = (tmp_path / "cache" / "tables").glob("table-*.npz")  # the G3 module's bank, kept in the table cache
    g3_to_mcap(tmp_path / "run.g3", tmp_path / "out.mcap", params=tmp_path / "p.toml", pipeline_config=pc)
    assert list((tmp_path / "cache" / "tables").glob("table-*.npz")) == [bank]  # ... which convert took from there
    names = {d: bolometer_name(*parse_detector_id(d)) for d in ArraySimulator(cfg).detector_ids}
    p_g3, f_g3 = _g3_power(tmp_path / "out.g3")
    p_mc, f_mc = _mcap_power(tmp_path / "out.mcap", names)
    assert set(p_g3) == set(p_mc) == set(names.values())
    stale = 0
    for name in p_g3:
        assert p_g3[name].size == 458
        np.testing.assert_array_equal(f_g3[name], f_mc[name])
        np.testing.assert_array_equal(p_g3[name], p_mc[name])  # NaN where flagged, in both
        stale += int(np.count_nonzero(f_g3[name] & fl.HK_STALE))
    # Readings a second apart: stale only with the short limit (and then flagged in both outputs alike).
    assert (stale > 0) == (staleness_s < 1.0)


def test_g3_housekeeping_histories_stay_bounded_in_a_long_run():
    from mntes_stream.g3.mapping import BathHistory, HkHistory, HkSnapshot
    from mntes_stream.g3.settings import G3InputConfig

    cfg = G3InputConfig(hk_retention_s=10.0)
    bath, hk = BathHistory(cfg), HkHistory(int(10e9))
    for k in range(10_000):  # a reading a second: 2.8 hours
        bath.add(k * 10**9, 0.1 + 1e-6 * k)
        hk.add(HkSnapshot(k * 10**9, np.full(4, 1.0 + k), np.full(4, 2.0)))
        hk.prune(k * 10**9)
    assert len(bath) <= 12 and len(hk) <= 12
    # What is kept still gives the values in force: the newest readings, interpolated; the snapshot in force.
    assert bath.at(np.array([9_998_500_000_000]))[0] == pytest.approx(0.1 + 1e-6 * 9998.5, abs=1e-15)
    amps, _ = hk.at(np.array([9_995 * 10**9 + 1]))
    assert amps[0, 0] == 1.0 + 9_995
