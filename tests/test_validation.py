"""The validation study: its analysis primitives on analytic signals, and the
quick study's numbers against independent computations from the physics core."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mntes_stream.cli import main
from mntes_stream.core import model
from mntes_stream.core.params import table1_params
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.core.validation import (
    CALIBRATION_ERRORS,
    JSON_KEYS,
    effective_nonlinearity,
    harmonic_amplitudes,
    perturb_params,
    source_distortion,
    template_gain,
    windowed_gain,
)
from mntes_stream.errors import ConfigError

FS = DFMUX_SAMPLE_RATE_HZ
T = np.arange(int(60 * FS)) / FS


@pytest.mark.parametrize("f0", [0.65, 0.77, 1.02])
def test_harmonic_amplitudes_recover_a_synthetic_signal(f0):
    rng = np.random.default_rng(1)
    amps = {h: complex(*rng.normal(size=2)) for h in (1, 2, 3, 4, 5, 6)}
    x = 3.0 + 0.01 * T + sum((a * np.exp(2j * np.pi * h * f0 * T)).real for h, a in amps.items())
    fit = harmonic_amplitudes(T, x, f0)
    for h, a in amps.items():
        assert abs(fit[h] - a) < 1e-9
    assert math.isclose(fit["offset"] + fit["trend"] * (0 - T.mean()), 3.0, abs_tol=1e-9)
    assert math.isclose(fit["trend"], 0.01, rel_tol=1e-9)
    with pytest.raises(ConfigError):
        harmonic_amplitudes(T, np.where(T > 3, np.nan, x), f0)


@pytest.mark.parametrize("eps_per_pw", [0.8, -0.3, 1e-4])
def test_effective_nonlinearity_of_an_analytic_response(eps_per_pw):
    eps = eps_per_pw * 1e12
    p0, amp = 0.5e-12, 20e-15
    p = p0 + amp * np.cos(2 * np.pi * 2 * 0.77 * T + 0.4)
    dp = p - p0
    rec = p0 + 0.7e-15 + dp + 0.5 * eps * dp**2   # f' = 1, f'' = eps
    nl = effective_nonlinearity(T, p, rec, 0.77)
    assert math.isclose(nl.eps_per_w, eps, rel_tol=1e-7)
    assert abs(nl.eps_quadrature_per_w) < 1e-7 * abs(eps)
    assert math.isclose(nl.leak_4f_w, abs(eps) * amp**2 / 4, rel_tol=1e-7)
    # A gain error scales f' and f'' alike: eps = f''/f' is unchanged.
    nl2 = effective_nonlinearity(T, p, p0 + 1.1 * (dp + 0.5 * eps * dp**2), 0.77)
    assert math.isclose(nl2.eps_per_w, eps, rel_tol=1e-7) and math.isclose(nl2.gain_2f, 1.1, rel_tol=1e-9)


def test_source_distortion_of_known_distortions():
    t = np.arange(int(20 * FS)) / FS
    s = 0.3e-12 * np.exp(-0.5 * ((t - 10) / 0.4) ** 2)
    base = np.abs(t - 10) > 4
    d = source_distortion(t, 0.5e-12 + s, 0.5e-12 + 1.02 * s, base)
    assert math.isclose(d["peak_frac_error"], 0.02, rel_tol=1e-9)
    assert abs(d["fwhm_frac_error"]) < 1e-9 and d["shape_rms_frac"] < 1e-12
    c = 0.5e12
    d = source_distortion(t, 0.5e-12 + s, 0.5e-12 + s - c * s**2, base)
    assert math.isclose(d["peak_frac_error"], -c * 0.3e-12, rel_tol=1e-5)
    assert d["fwhm_frac_error"] > 0 and d["shape_rms_frac"] > 1e-3


def test_template_and_windowed_gain():
    template = 6e-16 * np.cos(2 * np.pi * T / 20)
    nuisance = 1e-14 * np.cos(2 * np.pi * 2 * 0.77 * T) + 1e-17 * T
    assert math.isclose(template_gain(T, template, 0.5e-12 + 0.97 * template + nuisance, 0.77), 0.97, rel_tol=1e-8)
    env = 0.099 + 2e-3 * T / T[-1]
    p = 0.5e-12 + 1e-14 * np.cos(2 * np.pi * 2 * 0.77 * T)
    rec = 0.5e-12 + (p - 0.5e-12) * (1 + 3.0 * (env - 0.1)) + 5e-12 * (env - 0.1)
    wg = windowed_gain(T, p, rec, env, 0.77, 5.0)
    assert math.isclose(wg["gain_slope_per_unit"], 3.0, rel_tol=1e-3)
    assert math.isclose(wg["offset_slope_w_per_unit"], 5e-12, rel_tol=1e-3)


def test_perturb_params_changes_exactly_one_thing():
    p = table1_params(t_c_shift_k_per_t=2.0, t_c_shift_k_per_t2=1e4, pickup_a_per_t=2e-4j)
    for name, (_, sigma, _mode, _) in CALIBRATION_ERRORS.items():
        q = perturb_params(p, {name: sigma})
        diff = {k for k, v in q.to_dict().items() if v != p.to_dict()[k]}
        expected = {"z_re_ohm": {"z_thev_ohm"}, "z_im_ohm": {"z_thev_ohm"},
                    "gain_phase_rad": {"gain_a_per_count"}}.get(name, {name})
        assert diff == expected, name
    assert math.isclose(perturb_params(p, {"r_n_ohm": 0.01}).r_normal_ohm, 1.01)
    assert perturb_params(p, {"z_im_ohm": 0.01}).z_thev_ohm == pytest.approx(0.05 + 0.06j)
    assert math.isclose(abs(perturb_params(p, {"pickup_a_per_t": -0.5}).pickup_a_per_t), 1e-4)
    with pytest.raises(ConfigError):
        perturb_params(p, {"nope": 1.0})
    with pytest.raises(ConfigError):
        perturb_params(p, {"z_re_ohm": -1.0})  # Re z < 0 is not a passive network


# --- the quick study, run once through the CLI ----------------------------------------------------

@pytest.fixture(scope="module")
def study(tmp_path_factory):
    out = tmp_path_factory.mktemp("validation")
    import contextlib
    import io

    buf = io.StringIO()
    with contextlib.redirect_stdout(buf):
        assert main(["validate", "--quick", "--json", "--out", str(out)]) == 0
    return json.loads(buf.getvalue()), out


def _detector():
    p = table1_params(t_c_shift_k_per_t=2.0, t_c_shift_k_per_t2=1e4)
    return p.replace(v_thev_v=float(model.tune_bias_v(p, 0.7)))


def _linear_response(p):
    """The linear conversion as a function of optical power (forward model + P0 + Re(dI/S))."""
    op0 = model.solve_operating_point(p, p.p_opt_w)
    s = model.small_signal(p, op0.r_ohm).responsivity_a_per_w

    def f(power, t_bath=0.1):
        op = model.solve_operating_point(p, power, t_bath)
        return p.p_opt_w + np.real((op.i_a - op0.i_a) / s)

    return f


def test_study_json_and_report(study):
    res, out = study
    for key in JSON_KEYS:
        assert key in res and res[key] is not None, key
    text = (out / "report.md").read_text()
    assert "| HWP 2f -> 4f: effective nonlinearity | 1/pW |" in text
    assert "largest error meeting 0.014/pW" in text
    for name in ("timestreams.png", "spectra.png", "drift.png", "robustness.png", "jupiter_sweep.png", "overview.png"):
        data = (out / name).read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 10_000, name
    assert json.loads((out / "summary.json").read_text())["mntes_kind"] == "table"


def test_linear_conversion_shows_the_papers_nonlinearity(study):
    res, _ = study
    # About 0.8 / pW (paper sect. 3.3), and exactly the leading-order Re(I''/S) of this
    # detector (independent: small_signal's implicit derivatives), up to the 0.4%
    # third-order term at A = 20 fW.
    assert 0.7 < res["linear_nonlinearity_per_pw"] < 0.9
    p = _detector()
    op = model.solve_operating_point(p, p.p_opt_w)
    ss = model.small_signal(p, op.r_ohm)
    expected = abs((ss.d2i_dp2_a_per_w2 / ss.di_dp_a_per_w).real) * 1e-12
    assert math.isclose(res["linear_nonlinearity_per_pw"], expected, rel_tol=0.01)
    assert math.isclose(res["linear_4f_leak_w"], expected * 1e12 * (20e-15) ** 2 / 4, rel_tol=0.02)


def test_mntes_removes_the_nonlinearity(study):
    res, _ = study
    assert res["mntes_nonlinearity_per_pw"] < 1e-4
    assert res["converters"]["exact"]["nonlinearity_per_pw"] < 1e-4
    assert res["mntes_4f_leak_w"] < 1e-3 * res["linear_4f_leak_w"]
    assert abs(res["mntes_jupiter_peak_frac_error"]) < 1e-4 < abs(res["linear_jupiter_peak_frac_error"])
    assert abs(res["mntes_dipole_gain_bias"]) < 1e-5
    assert abs(res["mntes_drift_gain_per_mk"]) < 1e-6 and abs(res["mntes_drift_gain_per_ut"]) < 1e-7
    assert res["converters"]["table"]["flagged_samples"] == 0


def test_linear_baseline_numbers_against_the_forward_model(study):
    res, _ = study
    p = _detector()
    f = _linear_response(p)
    h = 1e-15
    # Dipole: its gain is the linear conversion's slope at the 10%-higher sky loading.
    p_sky = 1.1 * p.p_opt_w
    slope = (f(p_sky + h) - f(p_sky - h)) / (2 * h)
    assert math.isclose(res["linear_dipole_gain_bias"], slope - 1, rel_tol=0.02)
    # Bath drift: the slope's derivative in bath temperature, and the offset G_bath = n K T_b^(n-1).
    def slope_at(tb):
        return (f(p.p_opt_w + h, tb) - f(p.p_opt_w - h, tb)) / (2 * h)

    dg = (slope_at(0.1005) - slope_at(0.0995)) / 1e-3 * 1e-3
    assert math.isclose(res["linear_drift_gain_per_mk"], dg, rel_tol=0.05)
    g_bath = p.n * p.k_w_per_k_n * 0.1 ** (p.n - 1)
    assert math.isclose(res["linear_drift_offset_w_per_mk"], g_bath * 1e-3, rel_tol=0.05)
    # Jupiter: the peak through the forward model, at the true peak sample.
    expected_peak = (f(p.p_opt_w + 0.8e-12) - f(p.p_opt_w)) / 0.8e-12 - 1
    assert math.isclose(res["linear_jupiter_peak_frac_error"], expected_peak, rel_tol=1e-3)


def test_robustness_table_against_an_independent_inverse(study):
    res, _ = study
    rows = {r["parameter"]: r for r in res["robustness"]["one_at_a_time"]}
    assert set(rows) == set(CALIBRATION_ERRORS)
    # Recompute one entry with model.invert_current (not the converter) on the same signal.
    p = _detector().replace(pickup_a_per_t=2e-4)
    b = 50e-6
    q = perturb_params(p, {"r_n_ohm": rows["r_n_ohm"]["realistic_error"]})
    t = np.arange(int(20 * FS)) / FS
    power = p.p_opt_w + 20e-15 * np.cos(2 * np.pi * 2 * 0.77 * t)
    op = model.solve_operating_point(p, power, 0.1, b)
    counts = np.rint(model.readout_current_a(p, op.i_a, b) / p.gain_a_per_count)
    results = []
    for sign in (1, -1):
        q = perturb_params(p, {"r_n_ohm": sign * rows["r_n_ohm"]["realistic_error"]})
        inv = model.invert_current(q, q.gain_a_per_count * counts, 0.1, b)
        results.append(abs(effective_nonlinearity(t, power, inv.p_opt_w, 0.77).eps_per_w) * 1e-12)
    assert math.isclose(rows["r_n_ohm"]["nonlinearity_at_realistic_per_pw"], max(results), rel_tol=0.05)
    # Where a threshold was found, the error there just meets the requirement.
    for r in rows.values():
        assert r["largest_error_meeting_requirement"] > 0
        if r["bound"] == "exact":
            assert r["margin"] == pytest.approx(r["largest_error_meeting_requirement"] / r["realistic_error"])
    a = res["robustness"]["all_together"]
    assert 0 <= a["fraction_meeting_requirement"] <= 1 and a["median_per_pw"] <= a["p95_per_pw"]
    # Broken down by source (issue 26): shares from the one-at-a-time rows, largest first; removing
    # the largest source lowers the measured median; the linear budget predicts the median within 30 %.
    src = a["by_source"]
    assert {e["parameter"] for e in src} == set(CALIBRATION_ERRORS)
    assert sum(e["variance_share"] for e in src) == pytest.approx(1.0)
    shares = [e["variance_share"] for e in src]
    assert shares == sorted(shares, reverse=True)
    top = src[0]
    assert top["variance_share"] == pytest.approx(
        rows[top["parameter"]]["nonlinearity_at_realistic_per_pw"] ** 2
        / sum(r["nonlinearity_at_realistic_per_pw"] ** 2 for r in rows.values()))
    assert top["median_without_per_pw"] < a["median_per_pw"] and top["median_drop_frac"] > 0.1
    assert a["linear_prediction_median_per_pw"] == pytest.approx(a["median_per_pw"], rel=0.3)
