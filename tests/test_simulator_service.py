"""The simulator at the edges: messages valid against the schemas, an MCAP file that
reproduces the core simulation, live publication over loopback zenoh, and the
recorded session converted by the real pipeline back to the truth."""

from __future__ import annotations

import contextlib
import io
import json
import time

import numpy as np
import pytest
from schema_check import validate_payload

from mntes_stream.cli import main
from mntes_stream.core.sim import ArraySimulator, SimConfig
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.errors import ConfigError
from mntes_stream.io import keys
from mntes_stream.io.mcap import Session, read_metadata
from mntes_stream.io.messages import CountsChunk, HousekeepingChunk, PowerChunk, decode, detector_ids_for
from mntes_stream.io.paramfile import load_params
from mntes_stream.io.transport import QueueSubscriber, free_tcp_port, loopback, open_session
from mntes_stream.service.simulator import (
    SimulatorService,
    SimulatorServiceConfig,
    SimulatorSource,
    TruthRecorder,
    load_truth,
    run_simulator,
    write_mcap,
)

CFG = SimConfig(channels=8, modules=2, bias_steps=((1.3, 0.02),), jupiter_t_s=1.0, jupiter_period_s=0.0,
                jupiter_peak_w=0.3e-12)
T0 = 1_700_000_000 * 10**9


def test_batches_are_valid_messages_from_the_core_simulation():
    src = SimulatorSource(CFG, setup="lab", chunk_s=0.1)
    blocks = []
    batches = list(src.batches(T0, 2.0, blocks=blocks))
    ref = ArraySimulator(CFG, t0_ns=T0)
    hk_keys = set()
    last_pub = 0
    for (t_pub, batch), blk in zip(batches, blocks):
        assert t_pub > last_pub and t_pub > blk.t_ns[-1]
        last_pub = t_pub
        want = ref.next_block(blk.n_samples)
        kinds = [decode(p).SCHEMA for _, p in batch]
        # Housekeeping first, then one counts chunk per module.
        assert kinds == sorted(kinds, key=lambda s: s != "mntes.hk")
        for key, payload in batch:
            validate_payload(payload)
            msg = decode(payload)
            if isinstance(msg, CountsChunk):
                assert key == f"mntes/lab/counts/{msg.board}/{msg.module}"
                rows = ref.module_rows(msg.board, msg.module)
                assert np.array_equal(msg.counts_i, want.counts_i[rows])
                assert np.array_equal(msg.counts_q, want.counts_q[rows])
                assert np.array_equal(msg.times_ns(), want.t_ns)
                assert msg.t_pub_ns == t_pub
            else:
                assert isinstance(msg, HousekeepingChunk) and np.all(msg.t_ns < t_pub)
                hk_keys.add(key)
    assert hk_keys == {"mntes/lab/hk/t_bath", "mntes/lab/hk/b_field", "mntes/lab/hk/bias/0/0", "mntes/lab/hk/bias/0/1"}
    assert len(batches) == src.n_chunks(2.0) == 21  # ceil(2 s * 152.588 Hz / 15 samples)
    seqs = [decode(p).seq for t, b in batches for k, p in b if k.endswith("counts/0/1")]
    assert seqs == list(range(21))


def test_mcap_truth_and_params_files(tmp_path):
    out = tmp_path / "run.mcap"
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["simulate", "--out", str(out), "--duration", "2", "--channels", "8", "--modules", "2",
                     "--set", "jupiter_peak_w=0", "--perturbed-params-out", str(tmp_path / "wrong.toml"),
                     "--json"]) == 0
    res = json.loads(buf.getvalue())
    assert res["chunks"] == 21 and res["detectors"] == 16
    src = SimulatorSource(SimConfig(channels=8, modules=2, jupiter_peak_w=0.0))
    truth_params = load_params(tmp_path / "run.params.toml")
    assert list(truth_params.values()) == src.params
    wrong = load_params(tmp_path / "wrong.toml")
    assert wrong.keys() == truth_params.keys()
    assert all(wrong[k] != truth_params[k] for k in wrong)
    session = Session(out)
    # The default setup is every service's: the converter's default config converts it as it stands.
    assert {t.split("/")[1] for t in session.message_counts()} == {keys.DEFAULT_SETUP}
    counts = [decode(m.payload) for m in session.iter_messages(topics=f"mntes/{keys.DEFAULT_SETUP}/counts/**")]
    assert len(counts) == 2 * 21
    meta = {m.name: m.data for m in read_metadata(out)}
    assert "truth_params_toml" in meta["mntes.simulation"]
    assert json.loads(meta["mntes.simulation"]["sim_config"])["channels"] == 8
    truth = load_truth(tmp_path / "run.truth.npz")
    assert truth["truth_p_opt_w"].shape == (16, 21 * 15)
    t_counts = np.concatenate([c.times_ns() for c in counts if (c.board, c.module) == (0, 0)])
    assert np.array_equal(t_counts, truth["t_ns"])
    assert main(["simulate", "--duration", "1"]) == 2  # neither --out nor zenoh endpoints: a clear error


def test_recorded_session_converts_back_to_the_truth(tmp_path):
    """Simulator -> MCAP -> the converter pipeline (own-cadence housekeeping, a bias step) -> truth."""
    cfg = CFG.replace(jupiter_peak_w=0.0)
    src = SimulatorSource(cfg, setup="sim")
    truth = TruthRecorder(src.detector_ids, cfg)
    write_mcap(src, tmp_path / "in.mcap", 3.0, t_start_ns=T0, truth=truth)
    truth.save(tmp_path / "truth.npz")
    from mntes_stream.io.paramfile import dump_params

    dump_params(src.params, tmp_path / "params.toml")
    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["convert", str(tmp_path / "in.mcap"), str(tmp_path / "out.mcap"), "--params",
                     str(tmp_path / "params.toml"), "--json", "-q"]) == 0
    t = load_truth(tmp_path / "truth.npz")
    ids = list(t["detector_ids"])
    kinds = {ch.detector_id: ch.kind for ch in ArraySimulator(cfg).channels}
    # Readout noise alone: NEI sqrt(fs/2) per quadrature, through |dI/dP| ~ 1.9e6 A/W.
    sigma_w = 10e-12 * np.sqrt(DFMUX_SAMPLE_RATE_HZ / 2) / 1.7e6
    n_power = 0
    for m in Session(tmp_path / "out.mcap").iter_messages(topics="mntes/sim/power/**"):
        msg = decode(m.payload)
        assert isinstance(msg, PowerChunk)
        k = np.searchsorted(t["t_ns"], msg.times_ns())
        assert np.array_equal(t["t_ns"][k], msg.times_ns())
        for r, det in enumerate(detector_ids_for(msg.board, msg.module, msg.channels)):
            p, f = msg.p_opt_w[r], msg.flags[r]
            if kinds[det] == "latched":
                assert np.all(f & 2) and np.all(np.isnan(p))       # SUPERCONDUCTING
            elif kinds[det] == "ok":
                assert not np.any(f)
                err = p - t["truth_p_opt_w"][ids.index(det), k]
                assert np.max(np.abs(err)) < 6 * sigma_w
        n_power += 1
    assert n_power == 2 * 31


def _receive(sub, n: int, timeout_s: float = 10.0) -> list:
    """What ``sub`` holds, waiting up to ``timeout_s`` for ``n`` samples."""
    got, deadline = [], time.monotonic() + timeout_s
    while len(got) < n and time.monotonic() < deadline:
        item = sub.get(0.2)
        if item is not None:
            got.append(item)
    return got


def test_live_publication_over_loopback_zenoh():
    port = free_tcp_port()
    cfg = CFG.replace(jupiter_peak_w=0.0)
    src = SimulatorSource(cfg, setup="live", chunk_s=0.1)
    with open_session(loopback(port)) as z:
        sub = QueueSubscriber(z, ["mntes/live/**"])
        try:
            result = run_simulator(SimulatorServiceConfig(sim=cfg, setup="live", speed=0.0, duration_s=1.0,
                                                          zenoh=loopback(connect_ports=[port])), source=src)
            got = _receive(sub, result["messages"])
        finally:
            sub.close()
    assert result["batches"] == 11 and len(got) == result["messages"]
    assert result["counts_published"] == {"0/0": 11, "0/1": 11}  # the service's own summary (base.Service)
    counts = [decode(p) for k, p, _ in got if "/counts/" in k]
    assert len(counts) == 22
    by_module = {}
    for c in counts:
        by_module.setdefault((c.board, c.module), []).append(c)
    ref = ArraySimulator(cfg, t0_ns=counts[0].t0_ns)
    for _ in range(11):
        blk = ref.next_block(src.chunk_samples)
        for (b, m), chunks in by_module.items():
            c = next(x for x in chunks if x.t0_ns == int(blk.t_ns[0]))
            assert np.array_equal(c.counts_i, blk.counts_i[ref.module_rows(b, m)])


def test_live_simulate_command_runs_the_simulator_service(tmp_path):
    """``simulate`` with zenoh endpoints runs ``SimulatorService`` (base.Service's lifecycle): the same summary
    keys as ever, every message it counts received, truth and parameter files written beside."""
    port = free_tcp_port()
    buf = io.StringIO()
    with open_session(loopback(port)) as z:
        sub = QueueSubscriber(z, ["mntes/live/**"])
        try:
            with contextlib.redirect_stdout(buf):
                assert main(["simulate", "--connect", f"tcp/127.0.0.1:{port}", "--setup", "live", "--duration", "1",
                             "--speed", "0", "--channels", "8", "--modules", "2", "--set", "simulator.linger_s=0.5",
                             "--params-out", str(tmp_path / "p.toml"), "--truth", str(tmp_path / "t.npz"),
                             "--json", "-q"]) == 0
            res = json.loads(buf.getvalue())
            got = _receive(sub, res["messages"])
        finally:
            sub.close()
    assert set(res) == {"batches", "messages", "bytes", "behind_max_ms", "matched", "detectors", "params", "truth",
                        "perturbed_params"}
    assert res["batches"] == 11 and res["matched"] is True and res["detectors"] == 16 and len(got) == res["messages"]
    assert len([k for k, _, _ in got if "/counts/" in k]) == 22
    assert load_truth(tmp_path / "t.npz")["truth_p_opt_w"].shape[0] == 16 and len(load_params(tmp_path / "p.toml")) == 16


def test_service_config_tables():
    import dataclasses

    from mntes_stream.pipeline import PipelineConfig
    from mntes_stream.service.source import SourceConfig

    svc = SimulatorService.config_from_document({"simulator": {"channels": 128, "setup": "x1", "speed": 0, "duration_s": 5,
                                                                "linger_s": 0.5},
                                                  "zenoh": {"connect": ["tcp/127.0.0.1:7447"], "gossip": True}})
    assert svc.sim.channels == 128 and svc.setup == "x1" and svc.speed == 0 and svc.duration_s == 5
    assert svc.linger_s == 0.5 and svc.zenoh.gossip and isinstance(svc.speed, float)
    with pytest.raises(dataclasses.FrozenInstanceError):
        svc.speed = 2.0
    # One default setup: the simulator publishes where the converter (and source, monitor) listen.
    default = SimulatorService.config_from_document({})
    assert default.setup == SimulatorSource(CFG).setup == PipelineConfig().setup == SourceConfig().setup == "lab"
    for bad in ({"simulator": {"chanels": 128}}, {"simulatr": {}}, {"simulator": {"chunk_s": 0}},
                {"simulator": {"speed": -1}}, {"simulator": {"speed": "fast"}}, {"simulator": {"setup": "a/b"}},
                {"simulator": {"duration_s": float("nan")}}, {"simulator": {"setup": 7}}):
        with pytest.raises(ConfigError):
            SimulatorService.config_from_document(bad)
