"""The lab's calibration in (issue 26): sotodlib det_cal results (written and read by sotodlib's own
metadata functions) checked against and seeding the MNTES parameters."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mntes_stream.core import model
from mntes_stream.core.calib import lab as L
from mntes_stream.core.sweep import range_detectors
from mntes_stream.errors import ConfigError

meta = pytest.importorskip("sotodlib.io.metadata", reason="sotodlib extra not installed")

DETS = range_detectors()


def _write(path, rows: list[dict], dataset="obs_1700000000_satp1_1111111"):
    keys = list(rows[0])
    rs = meta.ResultSet(keys=keys)
    for r in rows:
        rs.append(r)
    meta.write_dataset(rs, str(path), dataset, overwrite=True)
    return dataset


def _lab_row(q, readout_id):
    """What a lab measuring detector ``q`` would store (sotodlib's names; s_i negative as sodetlib's)."""
    pred = L.mntes_predictions(q)
    return {"readout_id": readout_id, "r_n": pred["r_n_ohm"], "p_sat": pred["p_sat_w"], "r_frac": pred["r_frac"],
            "loopgain": pred["loop_gain"], "s_i": -pred["s_i_per_v"], "p_bias": pred["p_bias_w"], "bg": 3}


def test_iv_p_sat_is_the_bias_power_at_0_9_r_n_of_a_dark_iv():
    for p in (DETS["arctan"], DETS["current-dependent"]):
        r = 0.9 * p.r_normal_ohm
        v = float(model.tune_bias_v(p, 0.9, p_opt_w=0.0))  # independent: a bracketed solve for the bias
        assert L.mntes_predictions(p)["p_sat_w"] == pytest.approx(float(model.joule_power_w(p, r, v)), rel=1e-9)


@pytest.mark.parametrize("name", ["arctan", "current-dependent"])
def test_det_cal_checks_and_seeds_the_model(tmp_path, name):
    from mntes_stream.io.sotodlib_cal import load_det_cal

    p = DETS[name]
    # The lab's detector differs from our parameters: R_n 2 % higher, K 3 % lower.
    truth = p.replace(r_n_ohm=1.02 * p.r_normal_ohm, k_w_per_k_n=0.97 * p.k_w_per_k_n)
    path = tmp_path / "det_cal.h5"
    rows = [_lab_row(truth, p.detector_id), {**_lab_row(truth, "b0m0c999"), "p_sat": math.nan}]
    ds = _write(path, rows)
    labs = load_det_cal(path, ds)
    assert set(labs) == {p.detector_id, "b0m0c999"}
    lab = labs[p.detector_id]
    assert lab.source.endswith(f"[{ds}]") and lab.s_i_per_v > 0
    assert "p_sat_w" not in labs["b0m0c999"].measured()  # a failed fit (NaN) is "not measured"
    cmp = L.compare(p, lab)
    assert set(cmp) == set(L.LAB_QUANTITIES)
    assert cmp["r_n_ohm"]["rel_diff"] == pytest.approx(1 / 1.02 - 1, rel=1e-9)
    assert cmp["p_sat_w"]["rel_diff"] > 0.005  # ours has the larger K
    # Seeded from the lab: R_n and P_sat are the lab's; the model's other predictions move toward it.
    s = L.seed(p, lab)
    after = L.compare(s, lab)
    assert abs(after["r_n_ohm"]["rel_diff"]) < 1e-12 and abs(after["p_sat_w"]["rel_diff"]) < 1e-9
    assert s.k_w_per_k_n == pytest.approx(truth.k_w_per_k_n, rel=1e-6)
    summary = L.table({p.detector_id: cmp})
    assert summary["r_n_ohm"]["n"] == 1 and summary["p_sat_w"]["max_abs_rel_diff"] == abs(cmp["p_sat_w"]["rel_diff"])


def test_det_cal_ids_and_bad_input(tmp_path):
    from mntes_stream.io.sotodlib_cal import load_det_cal

    p = DETS["arctan"]
    path = tmp_path / "det_cal.h5"
    ds = _write(path, [_lab_row(p, "ufm_mv5_12345_0001"), _lab_row(p, "ufm_mv5_12345_0002")])
    mapped = load_det_cal(path, ds, id_map={"ufm_mv5_12345_0001": p.detector_id})
    assert list(mapped) == [p.detector_id]
    np.testing.assert_allclose([v["rel_diff"] for v in L.compare(p, mapped[p.detector_id]).values()], 0, atol=1e-9)
    with pytest.raises(ConfigError, match="cannot read a det_cal dataset"):
        load_det_cal(path, "obs_missing")
    with pytest.raises(ConfigError, match="no such file"):
        load_det_cal(tmp_path / "nope.h5", ds)
    bad = _write(tmp_path / "bad.h5", [_lab_row(p, "../../x")])
    with pytest.raises(ConfigError, match="not a safe name"):
        load_det_cal(tmp_path / "bad.h5", bad)
    with pytest.raises(ConfigError, match="compared with parameters"):
        L.compare(p.replace(detector_id="other"), mapped[p.detector_id])
    with pytest.raises(ConfigError, match="arctan"):
        from mntes_stream.core.params import tabulated_example_params

        L.seed(tabulated_example_params("b0m0c000"), L.LabCalibration("b0m0c000", r_n_ohm=0.01))


def test_calib_lab_command(tmp_path, capsys):
    import json

    from mntes_stream.cli import main
    from mntes_stream.io.paramfile import dump_params, load_params

    p = DETS["arctan"]
    params = tmp_path / "p.toml"
    dump_params([p], params)
    truth = p.replace(r_n_ohm=1.02 * p.r_normal_ohm)
    ds = _write(tmp_path / "det_cal.h5", [_lab_row(truth, "ufm_1"), _lab_row(truth, "ufm_2")])
    idmap = tmp_path / "ids.json"
    idmap.write_text(json.dumps({"ufm_1": p.detector_id}))
    seeded = tmp_path / "seeded.toml"
    args = ["calib", "lab", str(tmp_path / "det_cal.h5"), "--dataset", ds, "--params", str(params),
            "--id-map", str(idmap), "--seed-out", str(seeded), "--json"]
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["detectors"] == 1 and out["lab_only"] == 0
    assert out["summary"]["r_n_ohm"]["median_rel_diff"] == pytest.approx(1 / 1.02 - 1, rel=1e-9)
    assert load_params(seeded)[p.detector_id].r_normal_ohm == pytest.approx(1.02 * p.r_normal_ohm)
    # Again without --overwrite: one line, rc 2; a dataset naming none of our detectors too.
    assert main(args) == 2
    assert main(["calib", "lab", str(tmp_path / "det_cal.h5"), "--dataset", ds, "--params", str(params)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 2 and "names none" in err and "Traceback" not in err
