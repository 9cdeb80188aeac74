"""Calibration measurement model against independent computations."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import brentq

from mntes_stream.core.calib.forward import PARAM_NAMES, Design, predict_counts, theta_from_params, z_of_omega
from mntes_stream.core.calib.measurements import DetectorCalibration, Sweep
from mntes_stream.core.calib.simulate import SMALL_GRID, design_sweeps, simulate_campaign
from mntes_stream.core.model import SQRT2, readout_current_a, solve_operating_point


@pytest.fixture(scope="module")
def one():
    campaign, truth = simulate_campaign(1, seed=5, grid=SMALL_GRID)
    det = next(iter(campaign.detectors.values()))
    return (*truth[det.detector_id], det)


def test_impedance_is_a_series_resonator():
    # Independent form: z = R0 + r1 (w - 1) + j (omega L - 1/(omega C)), C from the reactance at omega0.
    f0, l_h, z0, r1 = 2.1e6, 61e-6, 0.04 + 0.06j, 0.3
    omega0 = 2 * np.pi * f0
    c_f = 1.0 / (omega0 * (omega0 * l_h - z0.imag))
    f = f0 + np.linspace(-5e3, 5e3, 21)
    omega = 2 * np.pi * f
    expected = z0.real + r1 * (f / f0 - 1) + 1j * (omega * l_h - 1 / (omega * c_f))
    np.testing.assert_allclose(z_of_omega(z0, l_h, r1, f0, f), expected, rtol=1e-9, atol=1e-9)
    assert z_of_omega(z0, l_h, r1, f0, f0) == pytest.approx(z0, abs=1e-12)


def test_biased_points_match_the_core_forward_model(one):
    p, ro, det = one
    sweeps = tuple(s for s in det.sweeps if s.kind in ("optical_response", "iv_curve", "field_sensitivity"))
    design = Design.from_detector(det, sweeps)
    model = predict_counts(theta_from_params(p, ro), design)
    v = p.v_thev_v * design.bias_ratio
    op = solve_operating_point(p, design.p_opt_w, design.t_bath_k, design.b_field_t, v)
    expected = readout_current_a(p, op.i_a, design.b_field_t) / p.gain_a_per_count
    np.testing.assert_allclose(model, expected, rtol=1e-12)


def test_probe_points_solve_the_power_balance_with_self_heating(one):
    # Independent: brentq on the TES temperature with the arctan R(T) and Joule heating.
    p, ro, det = one
    sweeps = tuple(s for s in det.sweeps if s.kind in ("impedance_temperature", "network_normal", "network_super"))
    design = Design.from_detector(det, sweeps)
    model = predict_counts(theta_from_params(p, ro), design)
    tr = p.transition
    for j in range(0, len(design), 3):
        v = p.v_thev_v * design.bias_ratio[j]
        z = z_of_omega(p.z_thev_ohm, ro.l_series_h, ro.r_slope_ohm, ro.bias_freq_hz, design.freq_hz[j])

        def balance(t):
            r = tr.resistance_ohm(t)
            return p.k_w_per_k_n * (t**p.n - design.t_bath_k[j] ** p.n) - design.p_opt_w[j] - v**2 * r / abs(r + z) ** 2

        t = brentq(balance, design.t_bath_k[j], 1.0, xtol=1e-15, rtol=1e-15)
        r = tr.resistance_ohm(t)
        expected = SQRT2 * v / (r + z) / p.gain_a_per_count
        assert model[j] == pytest.approx(expected, rel=1e-9)
    # The probe heats the TES: without its Joule power the R(T) points would differ.
    rt = [s for s in sweeps if s.kind == "impedance_temperature"][0]
    cold = Design.from_detector(det, (Sweep(rt.kind, rt.detector_id, rt.swept, {**rt.fixed, "bias_ratio": 1e-6},
                                            rt.counts, rt.sigma_counts),))
    i_hot = predict_counts(theta_from_params(p, ro), Design.from_detector(det, (rt,))) / rt.fixed["bias_ratio"]
    i_cold = predict_counts(theta_from_params(p, ro), cold) / 1e-6
    assert np.max(np.abs(i_hot / i_cold - 1)) > 1e-3


def test_counts_have_the_documented_scale_symmetry(one):
    # (R, z, L, r1, V, g, m) -> (s R, s z, s L, s r1, sqrt(s) V, g / sqrt(s), m / sqrt(s)) leaves every count unchanged:
    # the reason |g| must come from the electronics.
    p, ro, det = one
    s = 1.37
    th = theta_from_params(p, ro)
    ix = {n: k for k, n in enumerate(PARAM_NAMES)}
    th2 = th.copy()
    for n in ("r_n_ohm", "z_re_ohm", "z_im_ohm", "l_series_h", "r_slope_ohm"):
        th2[ix[n]] *= s
    th2[ix["v_thev_v"]] *= np.sqrt(s)
    th2[ix["pickup_re_a_per_t"]] /= np.sqrt(s)
    th2[ix["pickup_im_a_per_t"]] /= np.sqrt(s)
    d1 = Design.from_detector(det)
    d2 = Design.from_detector(DetectorCalibration(det.detector_id, det.bias_freq_hz, det.gain_abs_a_per_count / np.sqrt(s),
                                                  det.p_opt_w, det.t_bath_k, det.b_field_t, det.sweeps))
    np.testing.assert_allclose(predict_counts(th2, d2), predict_counts(th, d1), rtol=1e-10)


def test_sweep_design_covers_the_transition(one):
    p, ro, _ = one
    sweeps = design_sweeps(p, ro, SMALL_GRID)
    kinds = [s.kind for s in sweeps]
    assert kinds.count("iv_curve") == len(SMALL_GRID.iv_t_bath_k)
    assert kinds.count("field_sensitivity") == len(SMALL_GRID.field_bias_ratios)
    opt = sweeps[kinds.index("optical_response")]
    op = solve_operating_point(p, opt.swept)
    assert np.all(op.state == 0)
    frac = op.r_ohm / p.r_normal_ohm
    assert frac.min() < 0.5 < frac.max()
