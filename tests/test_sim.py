"""The array simulator against independent computations: the model's own forward
solve, the exact inverse, spectra of the noise, housekeeping alignment, the
Planck law, and its own reproducibility."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.signal import welch

from mntes_stream.core import model
from mntes_stream.core.align import align
from mntes_stream.core.params import ParamArray, table1_params
from mntes_stream.core.sim import (
    CHANNEL_LATCHED,
    CHANNEL_OK,
    CHANNEL_SATURATED,
    ArraySimulator,
    SimConfig,
    cmb_dpdt_w_per_k,
    solve_quasi_static,
)
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.errors import ConfigError

SMALL = SimConfig(channels=8, modules=2, jupiter_t_s=1.0, jupiter_period_s=3.0, bias_steps=((0.7, 0.02),))


def _model_truth(sim, blk):
    """Independent forward solve of a block with the physics core (Illinois bracket)."""
    pa = ParamArray.from_params(list(sim.truth_params))
    b = blk.truth_b_field_t[None, :]
    op = model.solve_operating_point(pa, blk.truth_p_opt_w, blk.truth_t_bath_k[None, :], b, blk.truth_v_thev_v,
                                     sequential=True)
    return pa, op, model.readout_current_a(pa, op.i_a, b)


def test_counts_are_the_quantised_forward_model():
    sim = ArraySimulator(SMALL.replace(nei_a_rthz=0.0))
    blk = sim.next_block(600)
    pa, op, i_meas = _model_truth(sim, blk)
    assert np.array_equal(op.state, blk.truth_state)
    counts = i_meas / pa.gain_a_per_count
    # Rounding may differ only where the two solvers straddle a half count.
    assert np.max(np.abs(counts.real - blk.counts_i)) <= 0.5 + 1e-6
    assert np.max(np.abs(counts.imag - blk.counts_q)) <= 0.5 + 1e-6
    assert blk.counts_i.dtype == np.int32 and blk.counts_q.dtype == np.int32


@settings(max_examples=25, deadline=None)
@given(
    p_frac=st.floats(0.0, 3.0),
    t_bath=st.floats(0.09, 0.11),
    b=st.floats(-1e-4, 1e-4),
    v_frac=st.floats(0.2, 1.2),
    gamma=st.sampled_from([0.0, 800.0]),
    guess=st.floats(0.01, 0.999),
)
def test_fast_solve_matches_model(p_frac, t_bath, b, v_frac, gamma, guess):
    base = table1_params(current_shift_k_per_a=gamma, t_c_shift_k_per_t=5.0, t_c_shift_k_per_t2=-2e3)
    ps = [base.replace(detector_id=f"d{k}", t_c_k=0.18 * (1 + 0.01 * k), z_thev_ohm=0.05 + 0.02j * k) for k in range(3)]
    pa = ParamArray.from_params(ps)
    p_opt = np.linspace(0.2, 1.0, 5)[None, :] * p_frac * base.p_sat_w
    v = v_frac * base.v_thev_v
    ref = model.solve_operating_point(pa, p_opt, t_bath, b, v, sequential=True)  # samples are a time stream
    got = solve_quasi_static(pa, p_opt, t_bath, b, v, r_guess_ohm=guess)
    assert np.array_equal(ref.state, got.state)
    assert np.allclose(got.r_ohm, ref.r_ohm, rtol=1e-12, atol=1e-14)
    assert np.allclose(got.i_a, ref.i_a, rtol=1e-12)


def test_stream_does_not_depend_on_block_size():
    a = ArraySimulator(SMALL)
    b = ArraySimulator(SMALL)
    whole = a.next_block(1000)
    parts = [b.next_block(n) for n in (7, 93, 400, 500)]
    for name in ("counts_i", "counts_q", "truth_p_opt_w", "truth_v_thev_v", "truth_state"):
        joined = np.concatenate([getattr(p, name) for p in parts], axis=1)
        assert np.array_equal(joined, getattr(whole, name)), name
    # Sample times agree to the nanosecond rounding of chunk-relative times.
    t_parts = np.concatenate([p.t_ns for p in parts])
    assert np.max(np.abs(t_parts - whole.t_ns)) <= 1
    for sensor in ("t_bath", "b_field", "bias"):
        def readings(blocks):
            hs = [h for blk in blocks for h in blk.hk if h.sensor == sensor and h.module in (None, 1)]
            return np.concatenate([h.t_ns for h in hs]), np.concatenate([h.value for h in hs])
        t1, v1 = readings([whole])
        t2, v2 = readings(parts)
        assert np.array_equal(t1, t2) and np.array_equal(v1, v2), sensor


def test_seed_makes_the_run():
    x = ArraySimulator(SMALL).next_block(200)
    y = ArraySimulator(SMALL).next_block(200)
    z = ArraySimulator(SMALL.replace(seed=1)).next_block(200)
    assert np.array_equal(x.counts_i, y.counts_i)
    assert not np.array_equal(x.counts_i, z.counts_i)
    assert ArraySimulator(SMALL).truth_params == ArraySimulator(SMALL).truth_params


def test_bias_tuning_and_channel_kinds():
    cfg = SimConfig.noise_free(channels=6, saturated_per_module=1, latched_per_module=1,
                               scatter_t_c_frac=0.01, scatter_r_n_frac=0.03, scatter_k_frac=0.05,
                               scatter_z_ohm=0.005, scatter_loading_frac=0.05)
    sim = ArraySimulator(cfg)
    kinds = [ch.kind for ch in sim.channels]
    assert kinds == [CHANNEL_OK] * 4 + [CHANNEL_SATURATED, CHANNEL_LATCHED]
    blk = sim.next_block(50)
    r_n = np.array([p.r_normal_ohm for p in sim.truth_params])
    pa, op, _ = _model_truth(sim, blk)
    r_frac = op.r_ohm[:, 0] / r_n
    assert np.allclose(r_frac[:4], 0.7, atol=1e-9)
    assert r_frac[4] > 0.995                       # driven far above T_c
    # Under-biased: not at R = 0 but on the stable part below |z| (loop gain between -1 and 0).
    assert np.all(blk.truth_state[5] == model.STATE_LATCHED)
    assert np.all((op.r_ohm[5] > 1e-3) & (op.r_ohm[5] < np.abs(pa.z_thev_ohm[5])))
    assert np.all(blk.truth_state[:5] == model.STATE_TRANSITION)
    # Each detector's nominal loading is where it was tuned.
    for p in sim.truth_params[:4]:
        assert math.isclose(float(model.solve_operating_point(p, p.p_opt_w).r_ohm), 0.7 * p.r_normal_ohm, rel_tol=1e-9)


def test_one_bias_per_module_is_the_median_of_its_tuned_biases():
    cfg = SimConfig(modules=3, channels=5, latched_per_module=0)
    own = np.array([p.v_thev_v for p in ArraySimulator(cfg).truth_params]).reshape(3, 5)
    shared = ArraySimulator(cfg.replace(bias_per_module=True))
    v = np.array([p.v_thev_v for p in shared.truth_params]).reshape(3, 5)
    assert np.all(v == np.median(own, axis=1)[:, None]) and np.ptp(own[0]) > 0
    blk = shared.next_block(20)
    assert np.all(blk.truth_v_thev_v == np.repeat(v[:, 0], 5)[:, None] * shared.bias_factor(blk.t_ns)[None, :])
    # the detectors themselves are the same: only their bias differs
    assert [p.replace(v_thev_v=0.0) for p in shared.truth_params] == \
        [p.replace(v_thev_v=0.0) for p in ArraySimulator(cfg).truth_params]


def test_exact_inverse_recovers_truth_within_quantisation():
    cfg = SimConfig.noise_free(channels=3, hwp_2f_w=50e-15, jupiter_peak_w=0.6e-12, jupiter_t_s=2.0,
                               b_field_amp_t=30e-6, b_field_period_s=4.0, t_bath_wander_k=0.5e-3,
                               t_bath_wander_period_s=5.0, bias_steps=((3.0, -0.02),),
                               t_c_shift_k_per_t=2.0, pickup_a_per_t=2e-4, scatter_b_coeff_frac=0.2)
    sim = ArraySimulator(cfg)
    blk = sim.next_block(int(6 * cfg.sample_rate_hz))
    pa = ParamArray.from_params(list(sim.truth_params))
    i = pa.gain_a_per_count * (blk.counts_i + 1j * blk.counts_q)
    inv = model.invert_current(pa, i, blk.truth_t_bath_k[None, :], blk.truth_b_field_t[None, :], blk.truth_v_thev_v)
    # Half a count on each quadrature, through the local responsivity.
    ss = model.small_signal(pa, inv.r_ohm, blk.truth_t_bath_k[None, :], blk.truth_b_field_t[None, :], blk.truth_v_thev_v)
    bound = 0.5 * math.sqrt(2) * np.abs(pa.gain_a_per_count) / np.abs(ss.di_dp_a_per_w)
    err = np.abs(inv.p_opt_w - blk.truth_p_opt_w)
    assert np.all(err <= 1.05 * bound)
    # Near the loading a count is ~5e-19 W; at Jupiter's peak the responsivity is much lower.
    t = np.arange(blk.n_samples) / cfg.sample_rate_hz
    assert np.max(err[:, np.abs(t - 2.0) > 2.0]) < 1e-18
    assert np.ptp(blk.truth_v_thev_v) > 0  # the bias step happened


def test_photon_and_readout_noise_levels():
    fs = DFMUX_SAMPLE_RATE_HZ
    cfg = SimConfig.noise_free(channels=16, nep_w_rthz=2e-17, f_knee_hz=1.0)
    sim = ArraySimulator(cfg)
    blk = sim.next_block(int(200 * fs))
    x = blk.truth_p_opt_w - blk.truth_p_opt_w.mean(axis=1, keepdims=True)
    f, psd = welch(x, fs=fs, nperseg=8192, axis=1)
    psd = psd.mean(axis=0)
    nep2 = 2e-17**2
    for f0 in (0.1, 0.3, 30.0, 60.0):
        k = np.argmin(np.abs(f - f0))
        expected = nep2 * (1 + 1.0 / f[k])
        assert abs(psd[k] / expected - 1) < 0.3, (f0, psd[k] / expected)
    # Readout noise: counts scatter around a constant current.
    cfg = SimConfig.noise_free(channels=16, nei_a_rthz=10e-12)
    sim = ArraySimulator(cfg)
    blk = sim.next_block(4000)
    sigma = 10e-12 * math.sqrt(fs / 2) / np.abs(np.array([p.gain_a_per_count for p in sim.truth_params]))
    measured = blk.counts_i.std(axis=1)
    assert np.allclose(measured, np.sqrt(sigma**2 + 1 / 12), rtol=0.06)


def test_housekeeping_cadence_and_alignment():
    cfg = SimConfig.noise_free(channels=4, modules=2, t_bath_wander_k=0.3e-3, t_bath_wander_period_s=20.0,
                               b_field_amp_t=20e-6, b_field_period_s=10.0, bias_steps=((1.234, 0.03), (3.0, -0.01)),
                               hk_t_bath_rate_hz=5.0, hk_b_field_rate_hz=10.0, hk_bias_rate_hz=1.0)
    sim = ArraySimulator(cfg, t0_ns=1_700_000_000 * 10**9)
    blocks = list(sim.blocks(61, int(5 * cfg.sample_rate_hz)))
    t = np.concatenate([b.t_ns for b in blocks])
    hk = {}
    for blk in blocks:
        for h in blk.hk:
            key = (h.sensor, h.board, h.module)
            hk.setdefault(key, []).append(h)
            assert h.t_ns.size and h.value.shape[0] == h.t_ns.size
            assert np.all((h.t_ns >= blk.t_ns[0]) & (h.t_ns < blk.t_ns[-1] + 1e9 / cfg.sample_rate_hz))
    assert set(hk) == {("t_bath", None, None), ("b_field", None, None), ("bias", 0, 0), ("bias", 0, 1)}
    cat = {k: (np.concatenate([h.t_ns for h in v]), np.concatenate([h.value for h in v])) for k, v in hk.items()}
    tb_t, tb_v = cat[("t_bath", None, None)]
    assert np.all(np.diff(tb_t) > 0)
    assert np.allclose(np.diff(tb_t), 0.2e9, atol=1)          # own cadence
    assert (tb_t[0] - sim.t0_ns) % int(0.2e9) != 0             # own timestamps, not on the sample grid
    assert np.allclose(tb_v, sim.t_bath_k((tb_t - sim.t0_ns) * 1e-9), rtol=0, atol=1e-15)
    # Bias readings interpolated to sample times reproduce the truth exactly, steps included.
    truth_v = np.concatenate([b.truth_v_thev_v for b in blocks], axis=1)
    for m in (0, 1):
        bt, bv = cat[("bias", 0, m)]
        assert np.all(np.diff(bt) > 0)
        aligned = align(t, bt, bv, staleness_ns=2 * 10**9)
        rows = sim.module_rows(0, m)
        assert np.array_equal(aligned.value.T, truth_v[rows])
    assert len(np.unique(truth_v[0])) == 3


def test_signal_components():
    fs = DFMUX_SAMPLE_RATE_HZ
    jup = ArraySimulator(SimConfig.noise_free(jupiter_peak_w=0.3e-12, jupiter_t_s=20.0, jupiter_period_s=0.0,
                                              jupiter_fwhm_s=1.0))
    p = jup.next_block(int(40 * fs)).truth_p_opt_w[0] - 0.5e-12
    t = np.arange(p.size) / fs
    k = np.argmax(p)
    assert abs(t[k] - 20.0) < 1 / fs and math.isclose(p[k], 0.3e-12, rel_tol=1e-3)
    above = t[p > 0.15e-12]
    assert math.isclose(above[-1] - above[0], 1.0, abs_tol=2 / fs)  # FWHM
    cfg = SimConfig.noise_free(channels=1, hwp_2f_w=20e-15, hwp_1f_w=3e-15, hwp_4f_w=1e-15, f_hwp_hz=1.02,
                               dipole_k=3.36e-3, dipole_period_s=40.0)
    sim = ArraySimulator(cfg)
    p = sim.next_block(int(40 * fs)).truth_p_opt_w[0] - cfg.loading_w
    w = 2 * np.pi * 1.02 * t
    design = np.column_stack([np.ones(t.size)] + [f(h * w) for h in (1, 2, 4) for f in (np.cos, np.sin)]
                             + [np.cos(2 * np.pi * t / 40.0)])
    coef, *_ = np.linalg.lstsq(design, p, rcond=None)
    assert np.allclose([coef[1], coef[3], coef[5]], [3e-15, 20e-15, 1e-15], rtol=1e-6)
    assert math.isclose(coef[7], sim.dpdt_cmb_w_per_k * 3.36e-3, rel_tol=1e-6)


def test_dipole_conversion_against_planck_law():
    kb, h = 1.380649e-23, 6.62607015e-34
    # Rayleigh-Jeans limit: dP/dT = eta k_B bandwidth.
    assert math.isclose(cmb_dpdt_w_per_k(1e9, 0.1, 0.5), 0.5 * kb * 1e8, rel_tol=1e-3)
    # Independent: finite-difference derivative of the single-mode Planck power.
    nu = np.linspace(140e9 * 0.85, 140e9 * 1.15, 20001)

    def power(t):
        return np.trapezoid(h * nu / np.expm1(h * nu / (kb * t)), nu)

    ref = 0.5 * (power(2.7255 + 1e-4) - power(2.7255 - 1e-4)) / 2e-4
    assert math.isclose(cmb_dpdt_w_per_k(140e9, 0.30, 0.5), ref, rel_tol=1e-6)


def test_bad_configs_are_rejected():
    with pytest.raises(ConfigError, match="unknown"):
        SimConfig.from_dict({"chanels": 64})
    with pytest.raises(ConfigError):
        SimConfig(channels=2, saturated_per_module=2, latched_per_module=1)
    with pytest.raises(ConfigError):
        SimConfig(bias_steps=((1.0, -1.5),))
    with pytest.raises(ConfigError):
        SimConfig(sample_rate_hz=0.0)
    with pytest.raises(ConfigError):
        ArraySimulator(SimConfig()).next_block(0)
    cfg = SimConfig.from_dict(SimConfig(channels=128, bias_steps=((5.0, 0.01),)).to_dict())
    assert cfg.channels == 128 and cfg.bias_steps == ((5.0, 0.01),)


def test_bistable_channel_latches_until_its_power_passes_the_reentry_point():
    """Starts on its low branch; a Jupiter crossing lifts it above P(R1); it stays on the branch after."""
    from mntes_stream.core.sim import CHANNEL_BISTABLE

    cfg = SimConfig.noise_free(channels=3, latched_per_module=1, bistable_per_module=1, jupiter_peak_w=0.3e-12,
                               jupiter_t_s=5.0, sample_rate_hz=20.0)
    sim = ArraySimulator(cfg)
    assert [ch.kind for ch in sim.channels] == [CHANNEL_OK, CHANNEL_BISTABLE, CHANNEL_LATCHED]
    whole = sim.next_block(300)
    st = whole.truth_state[1]
    k = np.flatnonzero(np.diff(st))
    assert k.size == 1 and st[0] == model.STATE_LATCHED and st[-1] == model.STATE_TRANSITION
    p = sim.truth_params[1]
    # Same loading before and after the crossing: two stable states, the history picks.
    assert whole.truth_p_opt_w[1, 0] == whole.truth_p_opt_w[1, -1]
    r0, r1, r2 = (float(x) for x in model.stability_bounds_ohm(p, p.v_thev_v))
    p_r1, p_r2 = (float(model.power_of_resistance_w(p, r, p.t_bath_k, 0.0, p.v_thev_v)) for r in (r1, r2))
    assert p_r2 < whole.truth_p_opt_w[1, 0] < p_r1
    assert whole.truth_p_opt_w[1, k[0] + 1] > p_r1 >= whole.truth_p_opt_w[1, k[0]]
    # The latch carries across blocks.
    again = ArraySimulator(cfg)
    parts = np.concatenate([again.next_block(n).truth_state for n in (50, 37, 213)], axis=1)
    assert np.array_equal(parts, whole.truth_state)
