"""Calibration files (MCAP + msgpack, JSON Schemas), truth/params files and the ``calib`` CLI."""

from __future__ import annotations

import json
import math
import tomllib

import msgpack
import numpy as np
import pytest
import schema_check
from hypothesis import given, settings
from hypothesis import strategies as st

from mntes_stream.cli import main
from mntes_stream.core.calib.measurements import CONDITIONS, KINDS, SWEPT_AXIS, Sweep
from mntes_stream.core.calib.simulate import SMALL_GRID, simulate_campaign
from mntes_stream.core.convert import make_converter
from mntes_stream.core.transition import ArctanTransition, TabulatedTransition
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io.calib_file import (
    decode_message,
    encode_header,
    encode_sweep,
    read_campaign,
    read_covariance,
    read_truth,
    write_campaign,
    write_truth,
)
from mntes_stream.io.paramfile import dump_params, load_params


@pytest.fixture(scope="module")
def small():
    return simulate_campaign(3, seed=11, grid=SMALL_GRID)


def _same_sweep(a: Sweep, b: Sweep) -> None:
    assert (a.kind, a.detector_id, a.fixed) == (b.kind, b.detector_id, b.fixed)
    np.testing.assert_array_equal(a.swept, b.swept)
    np.testing.assert_array_equal(a.counts, b.counts)
    np.testing.assert_array_equal(a.sigma_counts, b.sigma_counts)


def test_campaign_file_round_trip_and_schemas(small, tmp_path):
    campaign, _ = small
    path = tmp_path / "c.mcap"
    n = write_campaign(path, campaign)
    assert n == sum(1 + len(d.sweeps) for d in campaign.detectors.values())
    back = read_campaign(path)
    assert list(back.detectors) == list(campaign.detectors)
    assert back.metadata["seed"] == "11" and not back.orphans
    for det_id, det in campaign.detectors.items():
        b = back.detectors[det_id]
        assert (b.bias_freq_hz, b.gain_abs_a_per_count, b.p_opt_w, b.t_bath_k) == (
            det.bias_freq_hz, det.gain_abs_a_per_count, det.p_opt_w, det.t_bath_k)
        for s, t in zip(det.sweeps, b.sweeps, strict=True):
            _same_sweep(s, t)
    # Every message validates against its JSON Schema, which the file carries.
    det = next(iter(campaign.detectors.values()))
    schema_check.validate_payload(encode_header(det))
    kinds = set()
    for s in det.sweeps:
        msg = schema_check.validate_payload(encode_sweep(s, 0, 1))
        kinds.add(s.kind)
        assert set(CONDITIONS) <= set(msg) and isinstance(msg[SWEPT_AXIS[s.kind]], dict)
    assert kinds == set(KINDS)
    with pytest.raises(ConfigError, match="exists"):
        write_campaign(path, campaign)


_finite = st.floats(-1e6, 1e6, allow_nan=False)


@settings(max_examples=60, deadline=None)
@given(kind=st.sampled_from(KINDS), n=st.integers(1, 20), data=st.data())
def test_sweep_message_round_trip(kind, n, data):
    axis = SWEPT_AXIS[kind]
    positive = st.floats(1e-3, 1e7)
    fixed = {c: data.draw(positive if c in ("bias_ratio", "t_bath_k", "freq_hz") else _finite)
             for c in CONDITIONS if c != axis}
    swept = np.array(data.draw(st.lists(st.floats(allow_nan=True, allow_infinity=False), min_size=n, max_size=n)))
    re = data.draw(st.lists(st.floats(allow_nan=True), min_size=n, max_size=n))
    counts = np.array(re) + 1j * np.array(data.draw(st.lists(_finite, min_size=n, max_size=n)))
    sigma = np.array(data.draw(st.lists(st.floats(1e-6, 1e6), min_size=n, max_size=n)))
    s = Sweep(kind, "b1m2c003", swept, fixed, counts, sigma)
    back = decode_message(encode_sweep(s, 4, 5))
    _same_sweep(s, back)


def test_malformed_messages_are_schema_errors(small):
    det = next(iter(small[0].detectors.values()))
    s = det.by_kind("iv_curve")[0]
    good = msgpack.unpackb(encode_sweep(s), raw=False)
    # (mutation, error text, whether the JSON Schema can see it: byte counts it cannot)
    for mutate, match, in_schema in (
        (lambda m: m.pop("t_bath_k"), "t_bath_k must be a number", True),
        (lambda m: m.__setitem__("bias_ratio", 1.0), "bias_ratio", True),
        (lambda m: m.__setitem__("counts", {**m["counts"], "dtype": "<f8"}), "dtype", True),
        (lambda m: m.__setitem__("sigma_counts", {**m["sigma_counts"], "data": b"\0" * 8}), "bytes do not match", False),
        (lambda m: m.__setitem__("detector_id", ""), "detector_id", True),
        (lambda m: m.__setitem__("freq_hz", -1.0), "not a valid fixed condition", True),
    ):
        bad = dict(good)
        mutate(bad)
        with pytest.raises(SchemaError, match=match):
            decode_message(msgpack.packb(bad, use_bin_type=True))
        assert bool(schema_check.errors(bad)) == in_schema, match
    with pytest.raises(SchemaError):
        decode_message(b"\xc1 not msgpack")


def test_truth_file_is_marked_and_checked(small, tmp_path):
    _, truth = small
    write_truth(tmp_path / "t.toml", truth)
    doc = tomllib.loads((tmp_path / "t.toml").read_text())
    assert doc["metadata"]["truth"] is True and "TRUTH" in doc["metadata"]["note"]
    back = read_truth(tmp_path / "t.toml")
    for d, (p, r) in truth.items():
        assert back[d][0].to_dict() == p.to_dict() and back[d][1] == r
    dump_params([p for p, _ in truth.values()], tmp_path / "plain.toml")
    with pytest.raises(ConfigError, match="not a truth file"):
        read_truth(tmp_path / "plain.toml")


def test_cli_simulate_fit_report(tmp_path, capsys):
    c, t, out, rep = tmp_path / "c.mcap", tmp_path / "t.toml", tmp_path / "p.toml", tmp_path / "rep"
    assert main(["calib", "simulate", "--detectors", "4", "--seed", "2", "--grid", "small",
                 "--out", str(c), "--truth", str(t)]) == 0
    assert main(["calib", "info", str(c), "--json"]) == 0
    info = json.loads(capsys.readouterr().out.split("\n", 1)[1])
    assert info["detectors"] == 4 and info["sweeps"]["iv_curve"]["sweeps"] == 4 * len(SMALL_GRID.iv_t_bath_k)
    assert main(["calib", "fit", str(c), "--out", str(out), "--truth", str(t), "--report", str(rep),
                 "--workers", "1", "--converter", "exact", "--json", "--quiet"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert summary["ok"] == 4 and not summary["flagged"] and not summary["failed"]
    assert summary["eps_eff_max_per_pw"] < 0.014 and summary["margin_factor"] > 1
    params = load_params(out)
    assert list(params) == ["b0m0c000", "b0m0c001", "b0m0c002", "b0m0c003"]
    assert all(isinstance(p.transition, ArctanTransition) for p in params.values())
    meta = tomllib.loads(out.read_text())["metadata"]["calibration"]
    assert meta["n_ok"] == 4 and meta["fit"]["b0m0c001"]["sigma"]["t_c_k"] > 0
    names, cov = read_covariance(out.with_suffix(".cov.json"))
    assert names[0] == "t_c_k" and cov["b0m0c000"][1].shape == (15, 15)
    assert math.sqrt(cov["b0m0c001"][1][0, 0]) == pytest.approx(meta["fit"]["b0m0c001"]["sigma"]["t_c_k"])
    text = (rep / "summary.md").read_text()
    assert "End to end" in text and "below 0.014 /pW by" in text
    for kind in KINDS:
        assert (rep / f"fit_{kind}.png").stat().st_size > 10_000
    assert (rep / "pulls.png").exists() and (rep / "nonlinearity.png").exists()
    # The tabulated outcome: a parameter file the table builder reads directly.
    tab = tmp_path / "tab.toml"
    assert main(["calib", "fit", str(c), "--out", str(tab), "--transition", "tabulated", "--workers", "2", "--quiet"]) == 0
    tparams = load_params(tab)
    assert all(isinstance(p.transition, TabulatedTransition) for p in tparams.values())
    assert make_converter("exact", tparams).detector_ids == tuple(tparams)
    capsys.readouterr()


def test_cli_flags_bad_detectors_and_rejects_mismatched_truth(tmp_path, capsys):
    campaign, truth = simulate_campaign(3, seed=4, grid=SMALL_GRID)
    dets = list(campaign.detectors.values())
    dets[1] = dets[1].replace_sweeps([s for s in dets[1].sweeps if s.kind != "network_normal"])
    campaign.detectors[dets[1].detector_id] = dets[1]
    c = tmp_path / "c.mcap"
    write_campaign(c, campaign)
    out = tmp_path / "p.toml"
    assert main(["calib", "fit", str(c), "--out", str(out), "--workers", "1", "--quiet"]) == 0
    printed = capsys.readouterr().out
    assert "2 ok, 0 flagged, 1 failed" in printed and "missing measurement(s): network_normal" in printed
    assert dets[1].detector_id not in load_params(out)
    meta = tomllib.loads(out.read_text())["metadata"]["calibration"]
    assert meta["failed"] == [dets[1].detector_id]
    assert meta["fit"][dets[1].detector_id]["reasons"] == ["missing measurement(s): network_normal"]
    other = tmp_path / "t.toml"
    write_truth(other, {d: truth[d] for d in list(truth)[:2]})
    assert main(["calib", "fit", str(c), "--out", str(tmp_path / "q.toml"), "--truth", str(other), "--quiet"]) == 2
    assert "mismatched ids" in capsys.readouterr().err
