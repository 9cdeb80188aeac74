"""Physics core against independent computations: brentq, finite differences,
exact round trips and the paper's numbers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st
from scipy.optimize import brentq

from mntes_stream.core import model as m
from mntes_stream.core.params import ParamArray, table1_params
from mntes_stream.core.transition import ArctanTransition, TabulatedTransition

SQRT2 = np.sqrt(2.0)


def brentq_forward(p, p_opt, t_bath, b=0.0, v=None):
    """Independent forward solve: brentq in T, an inner brentq for R(T, I)."""
    v = p.v_thev_v if v is None else v
    tr = p.transition
    shift = p.t_c_shift_k_per_t * b + p.t_c_shift_k_per_t2 * b * b
    gamma = p.current_shift_k_per_a

    def r_of_t(t):
        # R = R_shape(T - shift + gamma |I(R)|), solved for R.
        def g(r):
            i_abs = SQRT2 * v / abs(r + p.z_thev_ohm)
            return float(tr.resistance_ohm(t - shift + gamma * i_abs)) - r

        return brentq(g, 0.0, tr.r_n_ohm, xtol=1e-300, rtol=1e-15)

    def f(t):
        r = r_of_t(t)
        return p_opt + v**2 * r / abs(r + p.z_thev_ohm) ** 2 - p.k_w_per_k_n * (t**p.n - t_bath**p.n)

    # Bracket on the stable branch: from where R = |z| up to far above T_c.
    t_lo = float(tr.temperature_k(abs(p.z_thev_ohm) * 1.0001)) + shift
    t_hi = 2 * tr.t_c_k
    t = brentq(f, t_lo - gamma * 1e-5, t_hi, xtol=1e-300, rtol=1e-15, maxiter=500)
    return r_of_t(t), t


@pytest.mark.parametrize(
    "overrides",
    [
        {},
        {"z_thev_ohm": 0.02 + 0.1j},
        {"current_shift_k_per_a": 800.0},
        {"t_c_shift_k_per_t": 5.0, "t_c_shift_k_per_t2": -2e3},
    ],
)
def test_forward_matches_brentq(overrides):
    p = table1_params(**overrides)
    for p_opt in (0.05e-12, 0.3e-12, 0.5e-12, 0.8e-12):
        for b in (0.0, 80e-6):
            op = m.solve_operating_point(p, p_opt, 0.1, b)
            assert int(op.state) == m.STATE_TRANSITION
            r_ref, t_ref = brentq_forward(p, p_opt, 0.1, b)
            assert float(op.r_ohm) == pytest.approx(r_ref, rel=1e-11)
            assert float(op.t_k) == pytest.approx(t_ref, rel=1e-12)


def test_forward_vectorised_equals_pointwise():
    p = table1_params(current_shift_k_per_a=500.0, z_thev_ohm=0.05 + 0.08j)
    p_opt = np.linspace(0.05e-12, 1.0e-12, 7)[:, None]
    t_bath = np.array([0.095, 0.1, 0.105])[None, :]
    op = m.solve_operating_point(p, p_opt, t_bath, 50e-6)
    for i in range(7):
        for j in range(3):
            one = m.solve_operating_point(p, float(p_opt[i, 0]), float(t_bath[0, j]), 50e-6)
            assert op.r_ohm[i, j] == pytest.approx(float(one.r_ohm), rel=1e-13)


def test_round_trip_exact_table1():
    p = table1_params(pickup_a_per_t=2e-3 - 1e-3j, t_c_shift_k_per_t=3.0)
    p_opt = np.linspace(0.05e-12, 1.0e-12, 200)
    t_bath = np.linspace(0.095, 0.105, 200)
    b = np.linspace(-100e-6, 100e-6, 200)
    v = p.v_thev_v * np.linspace(0.95, 1.05, 200)
    op = m.solve_operating_point(p, p_opt, t_bath, b, v)
    assert np.all(op.state == m.STATE_TRANSITION)
    inv = m.invert_current(p, m.readout_current_a(p, op.i_a, b), t_bath, b, v)
    np.testing.assert_allclose(inv.p_opt_w, p_opt, rtol=1e-12, atol=0)
    np.testing.assert_allclose(inv.x_residual_ohm, 0, atol=1e-12)


@settings(max_examples=60, deadline=None)
@given(
    t_c=st.floats(0.12, 0.3),
    iqr=st.floats(0.3e-3, 10e-3),
    r_n=st.floats(0.3, 3.0),
    z_re=st.floats(0.0, 0.08),
    z_im=st.floats(-0.1, 0.1),
    n=st.floats(2.5, 4.5),
    gamma=st.floats(0.0, 2000.0),
    r_frac=st.floats(0.3, 0.9),
    load_frac=st.floats(0.05, 0.8),
)
def test_round_trip_property(t_c, iqr, r_n, z_re, z_im, n, gamma, r_frac, load_frac):
    t_bath = 0.6 * t_c
    k = 1.25e-12 / (t_c**n - t_bath**n)
    p = table1_params(
        t_c_k=t_c, iqr_k=iqr, r_n_ohm=r_n, z_thev_ohm=complex(z_re * r_n, z_im * r_n),
        n=n, k_w_per_k_n=k, t_bath_k=t_bath, current_shift_k_per_a=gamma,
        p_opt_w=load_frac * 1.25e-12,
    )
    assume(r_frac * r_n > abs(p.z_thev_ohm) * 1.5)
    v = float(m.tune_bias_v(p, r_frac))
    op = m.solve_operating_point(p, p.p_opt_w, t_bath, 0.0, v)
    assert int(op.state) == m.STATE_TRANSITION
    assert float(op.r_ohm) == pytest.approx(r_frac * r_n, rel=1e-9)
    p_grid = p.p_opt_w * np.array([0.5, 0.9, 1.0, 1.1, 1.3])
    op = m.solve_operating_point(p, p_grid, t_bath, 0.0, v)
    ok = op.state == m.STATE_TRANSITION
    inv = m.invert_current(p, op.i_a, t_bath, 0.0, v)
    np.testing.assert_allclose(inv.p_opt_w[ok], p_grid[ok], rtol=1e-12, atol=1e-27)


@pytest.mark.parametrize(
    "overrides",
    [{}, {"z_thev_ohm": 0.03 + 0.12j}, {"current_shift_k_per_a": 1500.0}, {"z_thev_ohm": 0.08 - 0.04j, "current_shift_k_per_a": 600.0}],
)
def test_small_signal_against_finite_differences(overrides):
    p = table1_params(**overrides)
    p0 = p.p_opt_w
    r0 = m.solve_operating_point(p, p0).r_ohm
    ss = m.small_signal(p, r0)
    h = 2e-15
    i = [m.solve_operating_point(p, p0 + k * h).i_a for k in (-2, -1, 0, 1, 2)]
    d1 = (i[0] - 8 * i[1] + 8 * i[3] - i[4]) / (12 * h)
    d2 = (-i[0] + 16 * i[1] - 30 * i[2] + 16 * i[3] - i[4]) / (12 * h * h)
    # Paper eq. 3 (closed form, with the loop gain of eq. 2) and the implicit derivative.
    np.testing.assert_allclose(ss.responsivity_a_per_w, d1, rtol=1e-6)
    np.testing.assert_allclose(ss.di_dp_a_per_w, d1, rtol=1e-6)
    np.testing.assert_allclose(ss.d2i_dp2_a_per_w2, d2, rtol=1e-3)
    if overrides.get("current_shift_k_per_a"):
        assert float(ss.beta) > 0.1


def test_alpha_beta_definitions_by_finite_difference():
    p = table1_params(current_shift_k_per_a=1000.0)
    op = m.solve_operating_point(p, p.p_opt_w)
    ss = m.small_signal(p, op.r_ohm)
    t, i_abs = float(op.t_k), float(np.abs(op.i_a))

    def r_at(t_k, i_a):
        return float(p.transition.resistance_ohm(t_k + p.current_shift_k_per_a * i_a))

    r = r_at(t, i_abs)
    assert r == pytest.approx(float(op.r_ohm), rel=1e-12)
    h = 1e-7
    alpha = t / r * (r_at(t + h, i_abs) - r_at(t - h, i_abs)) / (2 * h)
    hi = 1e-10
    beta = i_abs / r * (r_at(t, i_abs + hi) - r_at(t, i_abs - hi)) / (2 * hi)
    assert float(ss.alpha) == pytest.approx(alpha, rel=1e-5)
    assert float(ss.beta) == pytest.approx(beta, rel=1e-5)


def test_fiducial_matches_paper_table1():
    p = table1_params()
    d = m.describe(p)  # V = 0.8 uV as in Table 1
    assert d["abs_responsivity_a_per_w"] == pytest.approx(1.8e6, rel=0.05)
    assert d["loop_gain"] == pytest.approx(10, rel=0.05)
    assert d["alpha"] == pytest.approx(77, rel=0.02)
    assert d["g_bar_w_per_k"] == pytest.approx(15e-12, rel=0.05)
    assert d["tau0_s"] == pytest.approx(33e-3, rel=0.02)
    assert d["r_frac"] == pytest.approx(0.7, abs=0.035)
    tuned = m.describe(p, v_thev_v=float(m.tune_bias_v(p, 0.7)))
    assert tuned["r_frac"] == pytest.approx(0.7, rel=1e-12)
    # Paper: 1.9e18 A/W^2 and 0.8 / pW (the latter at the R_frac = 0.7 tuned point).
    assert tuned["nonlinearity_per_pw"] == pytest.approx(0.8, rel=0.05)
    assert d["d2i_dp2_a_per_w2"] == pytest.approx(1.9e18, rel=0.1)


def test_states_off_the_branch():
    p = table1_params()
    # The arctan transition only approaches R_n: a large load drives R there.
    op = m.solve_operating_point(p, np.array([0.0, 5e-12]), v_thev_v=0.8e-6)
    assert op.r_ohm[1] > 0.995 * p.r_normal_ohm
    tab = p.replace(transition=_tabulated_from_arctan(p))
    assert int(m.solve_operating_point(tab, 5e-12).state) == m.STATE_NORMAL
    # Far under-biased, the arctan TES is not at R = 0 but on the stable part below |z|
    # (loop gain between -1 and 0): latched, with R from the power balance.
    op_lat = m.solve_operating_point(p, 0.0, v_thev_v=0.05e-6)
    assert int(op_lat.state) == m.STATE_LATCHED
    assert 1e-3 < float(op_lat.r_ohm) < abs(p.z_thev_ohm)
    assert abs(float(m.power_of_resistance_w(p, op_lat.r_ohm, p.t_bath_k, 0.0, 0.05e-6))) < 1e-22
    assert float(m.balance_slope_w_per_ohm(p, op_lat.r_ohm, 0.05e-6)) > 0  # a stable state
    tab0 = p.replace(transition=TabulatedTransition(t_k=(0.17, 0.1795, 0.18, 0.1805, 0.19), r_ohm=(0.0, 0.1, 0.5, 0.9, 1.0)))
    assert int(m.solve_operating_point(tab0, 0.0, v_thev_v=0.05e-6).state) == m.STATE_SUPERCONDUCTING
    inv = m.invert_current(p, np.array([m.SQRT2 * 0.8e-6 / (0.01 + p.z_thev_ohm), m.SQRT2 * 0.8e-6 / (1.2 + p.z_thev_ohm)]))
    assert list(inv.state) == [m.STATE_LATCHED, m.STATE_NORMAL]
    assert np.all(np.isnan(inv.p_opt_w))


def test_param_array_broadcasts_like_single_detectors():
    dets = [table1_params(f"d{k}", t_c_k=0.178 + 0.002 * k, iqr_k=1e-3 + 2e-4 * k) for k in range(4)]
    arr = ParamArray.from_params(dets)
    p_opt = np.linspace(0.2e-12, 0.7e-12, 5)[None, :]
    op = m.solve_operating_point(arr, p_opt)
    assert op.r_ohm.shape == (4, 5)
    for k, d in enumerate(dets):
        one = m.solve_operating_point(d, p_opt[0])
        np.testing.assert_allclose(op.r_ohm[k], one.r_ohm, rtol=1e-13)
    inv = m.invert_current(arr, op.i_a)
    np.testing.assert_allclose(inv.p_opt_w, np.broadcast_to(p_opt, (4, 5)), rtol=1e-12)


def _tabulated_from_arctan(p, n_points=80):
    r = np.linspace(0.005, 0.995, n_points) * p.r_normal_ohm
    t = p.transition.temperature_k(r)
    return TabulatedTransition(t_k=tuple(t), r_ohm=tuple(r))


def test_tabulated_transition_round_trip_and_consistency():
    p = table1_params()
    tab = p.replace(transition=_tabulated_from_arctan(p))
    p_opt = np.linspace(0.05e-12, 0.9e-12, 50)
    op = m.solve_operating_point(tab, p_opt)
    assert np.all(op.state == m.STATE_TRANSITION)
    inv = m.invert_current(tab, op.i_a)
    np.testing.assert_allclose(inv.p_opt_w, p_opt, rtol=1e-12)
    # Forward R(T) is the exact inverse of T(R).
    t = tab.transition.temperature_k(op.r_ohm)
    np.testing.assert_allclose(tab.transition.resistance_ohm(t), op.r_ohm, rtol=1e-12)
    # A fine table reproduces the analytic transition closely.
    op_a = m.solve_operating_point(p, p_opt)
    np.testing.assert_allclose(op.r_ohm, op_a.r_ohm, rtol=1e-3)
    ss = m.small_signal(tab, op.r_ohm[10])
    h = 2e-15
    i1 = m.solve_operating_point(tab, p_opt[10] + h).i_a
    i0 = m.solve_operating_point(tab, p_opt[10] - h).i_a
    np.testing.assert_allclose(ss.di_dp_a_per_w, (i1 - i0) / (2 * h), rtol=1e-5)


def test_tune_bias_with_current_dependence():
    p = table1_params(current_shift_k_per_a=1200.0)
    for r_frac in (0.4, 0.7, 0.85):
        v = float(m.tune_bias_v(p, r_frac))
        op = m.solve_operating_point(p, p.p_opt_w, v_thev_v=v)
        assert float(op.r_ohm) == pytest.approx(r_frac, rel=1e-9)


def test_bracketed_root_agrees_with_brentq():
    from mntes_stream.core.solve import bracketed_root

    c = np.linspace(-5, 30, 50)
    x = bracketed_root(lambda x: x + 0.9 * np.sin(x) - c, np.full(50, -10.0), np.full(50, 40.0))
    for ci, xi in zip(c, x):
        ref = brentq(lambda y: y + 0.9 * np.sin(y) - ci, -10.0, 40.0, xtol=1e-300, rtol=1e-15)
        assert xi == pytest.approx(ref, rel=1e-13, abs=1e-14)


def test_arctan_derivatives_by_finite_difference():
    tr = ArctanTransition(t_c_k=0.18, iqr_k=1.1e-3, r_n_ohm=1.0)
    r = np.linspace(0.1, 0.9, 9)
    h = 1e-6
    d1, d2 = tr.dtemperature_dr(r)
    np.testing.assert_allclose(d1, (tr.temperature_k(r + h) - tr.temperature_k(r - h)) / (2 * h), rtol=1e-7)
    h = 1e-4
    np.testing.assert_allclose(
        d2, (tr.temperature_k(r + h) - 2 * tr.temperature_k(r) + tr.temperature_k(r - h)) / h**2, rtol=1e-3
    )
    np.testing.assert_allclose(tr.resistance_ohm(tr.temperature_k(r)), r, rtol=1e-13)
