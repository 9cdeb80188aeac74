"""core.leakage: the 2f -> 4f effective nonlinearity, against injected quadratics and the simulator's truth."""

from __future__ import annotations

import numpy as np
import pytest

from mntes_stream.core import validation
from mntes_stream.core.leakage import (
    STATUS_NO_2F,
    STATUS_OK,
    STATUS_TOO_SHORT,
    leakage_between,
    leakage_of,
    median_nl,
    refine_f_hwp,
)
from mntes_stream.core.sim import ArraySimulator, SimConfig

FS_HZ = 152.587890625
F_HWP_HZ = 0.77
P0_W = 0.5e-12
A_W = 10e-15


def _series(seconds=30.0, phase=0.7, seed=0):
    t = np.arange(int(seconds * FS_HZ)) / FS_HZ
    d = A_W * np.cos(4 * np.pi * F_HWP_HZ * t + phase)
    return t, d, np.random.default_rng(seed)


@pytest.mark.parametrize("gain, e2_per_w, phase", [(1.0, 0.4e12, 0.7), (1.03, -0.4e12, 2.9), (0.97, 7e9, -1.2)])
def test_an_injected_quadratic_gives_its_eps_at_any_phase_and_gain(gain, e2_per_w, phase):
    # f(P0 + dP) = P0 + g dP + e2 dP^2: f'' / f' = 2 e2 / g (validation's eps), by hand.
    t, d, rng = _series(phase=phase)
    noise = 2e-17 * rng.standard_normal(t.size)  # readout-like: the same in both conversions of the same counts
    p_ref = P0_W + d + noise
    p_x = P0_W + gain * d + e2_per_w * d**2 + noise
    r = leakage_between(t, p_x, p_ref, F_HWP_HZ)
    assert r.status == STATUS_OK
    assert r.nl_per_w == pytest.approx(2 * e2_per_w / gain, rel=2e-3)
    assert r.gain_2f == pytest.approx(gain, rel=1e-5)
    assert abs(r.nl_quadrature_per_w) < 1e-3 * abs(r.nl_per_w)
    assert r.resolved


def test_a_4f_line_of_the_sky_cancels_in_the_difference_but_biases_one_series():
    t, d, rng = _series()
    sky_4f = 3e-17 * np.cos(8 * np.pi * F_HWP_HZ * t + 0.3)
    p_ref = P0_W + d + sky_4f
    p_x = p_ref + 0.4e12 * d**2
    assert leakage_between(t, p_x, p_ref, F_HWP_HZ).nl_per_w == pytest.approx(0.8e12, rel=2e-3)
    alone = leakage_of(t, p_x, F_HWP_HZ)
    assert alone.status == STATUS_OK and abs(alone.nl_per_w - 0.8e12) > 0.5e12  # 4 * 3e-17 / A^2 = 1.2e12 off


def test_the_uncertainty_is_the_scatter_of_the_estimate():
    # White noise in the difference only: the pulls of 40 draws have unit width, centred on the truth.
    pulls = []
    for seed in range(40):
        t, d, rng = _series(seconds=15.0, seed=seed)
        p_ref = P0_W + d
        p_x = p_ref + 0.4e12 * d**2 + 3e-16 * rng.standard_normal(t.size)
        r = leakage_between(t, p_x, p_ref, F_HWP_HZ)
        pulls.append((r.nl_per_w - 0.8e12) / r.sigma_nl_per_w)
    pulls = np.array(pulls)
    assert 0.75 < np.std(pulls) < 1.3
    assert abs(np.mean(pulls)) < 0.5


def test_flagged_samples_are_left_out_not_propagated():
    t, d, _ = _series()
    p_ref = P0_W + d
    p_x = p_ref + 0.4e12 * d**2
    p_x[1000:1400] = np.nan
    p_ref[3000:3100] = np.nan
    r = leakage_between(t, p_x, p_ref, F_HWP_HZ)
    assert r.n_samples == t.size - 500
    assert r.nl_per_w == pytest.approx(0.8e12, rel=2e-3)


def test_no_2f_line_gives_a_status_not_a_number():
    t, _, rng = _series()
    p = P0_W + 1e-17 * rng.standard_normal(t.size)
    r = leakage_between(t, p + 1e-17 * rng.standard_normal(t.size), p, F_HWP_HZ)
    assert r.status == STATUS_NO_2F and r.nl_per_w is None and r.nl_per_pw is None and not r.resolved
    assert leakage_of(t, p, F_HWP_HZ).status == STATUS_NO_2F
    short = leakage_between(t[:500], p[:500], p[:500], F_HWP_HZ)  # 3.3 s: under 8 HWP periods
    assert short.status == STATUS_TOO_SHORT and short.nl_per_w is None


def test_refine_f_hwp_finds_the_line_from_a_guess_a_bin_off():
    t, _, rng = _series(seconds=25.0)
    f_true = 0.7713
    rows = [P0_W + A_W * np.cos(4 * np.pi * f_true * t + ph) + 1e-17 * rng.standard_normal(t.size)
            for ph in (0.1, 2.0, 4.0)]
    f = refine_f_hwp(t, np.array(rows), f_true + 1.0 / 25.0)
    assert abs(f - f_true) < 1e-4  # 4f phase slip over the window < 0.07 rad


def test_refine_f_hwp_never_finds_the_mirror_line_at_a_negative_frequency():
    """A short window searches wide: around a low guess the search reached below 0 Hz, where a real series'
    2f power mirrors the positive side, and the monitor's live leakage then refused the negative f_HWP with a
    traceback (seen in the chaos-net run: -0.758 Hz after the link came back)."""
    rng = np.random.default_rng(5)
    t = np.arange(0.0, 2.0, 1 / 152.587890625)  # 2 s: the search spans +-0.75 Hz
    for f_true in (0.05, 0.1, 0.2):
        rows = [P0_W + A_W * np.cos(4 * np.pi * f_true * t + ph) + 1e-17 * rng.standard_normal(t.size)
                for ph in (0.3, 1.9)]
        for guess in (f_true, f_true * 1.5, 0.3):
            f = refine_f_hwp(t, np.array(rows), guess)
            assert f > 0, (f_true, guess, f)


@pytest.fixture(scope="module")
def simulated():
    """Six scattered detectors, 25 s, HWP 2f = 10 fW, every noise but readout's: truth, linear and MNTES power."""
    cfg = SimConfig(channels=6, saturated_per_module=0, latched_per_module=0, seed=3, nei_a_rthz=0.0)
    sim = ArraySimulator(cfg)
    n = int(25 * cfg.sample_rate_hz)
    blk = sim.next_block(n)
    params = {p.detector_id: p for p in sim.truth_params}
    conv = {k: validation._convert(validation.default_converter_factory(k, params), blk, sim.detector_ids)[0]
            for k in ("linear", "exact")}
    return cfg, sim, blk, np.arange(n) / cfg.sample_rate_hz, conv


def test_on_the_simulator_linear_against_mntes_is_the_true_nonlinearity(simulated):
    cfg, sim, blk, t, conv = simulated
    f = refine_f_hwp(t, conv["exact"], cfg.f_hwp_hz + 0.02)
    for i, p in enumerate(sim.truth_params):
        expected = validation.expected_linear_nonlinearity_per_w(p)  # the model's I''/S: independent of the fit
        truth_based = validation.effective_nonlinearity(t, blk.truth_p_opt_w[i], conv["linear"][i], cfg.f_hwp_hz)
        lin = leakage_between(t, conv["linear"][i], conv["exact"][i], f)
        assert lin.status == STATUS_OK and lin.resolved
        assert lin.nl_per_w == pytest.approx(expected, rel=0.2)
        assert lin.nl_per_w == pytest.approx(truth_based.eps_per_w, rel=0.01)
        mntes = leakage_between(t, conv["exact"][i], blk.truth_p_opt_w[i], f)
        assert abs(mntes.nl_per_pw) < validation.REQUIREMENT_PER_PW
        assert mntes.sigma_nl_per_pw < validation.REQUIREMENT_PER_PW / 10


def test_on_the_simulator_with_the_hwp_off_there_is_no_2f_line():
    cfg = SimConfig(channels=3, saturated_per_module=0, latched_per_module=0, seed=1, hwp_2f_w=0.0)
    sim = ArraySimulator(cfg)
    blk = sim.next_block(int(20 * cfg.sample_rate_hz))
    params = {p.detector_id: p for p in sim.truth_params}
    t = np.arange(blk.n_samples) / cfg.sample_rate_hz
    lin = validation._convert(validation.default_converter_factory("linear", params), blk, sim.detector_ids)[0]
    mn = validation._convert(validation.default_converter_factory("exact", params), blk, sim.detector_ids)[0]
    for i in range(3):
        assert leakage_between(t, lin[i], mn[i], cfg.f_hwp_hz).status == STATUS_NO_2F


def test_a_planet_crossing_with_flagged_samples_is_left_out_of_the_difference():
    # A 0.8 pW Gaussian crossing, its top flagged (NaN) in one conversion: edges the fit cannot absorb.
    t, d, _ = _series(seconds=40.0)
    planet = 0.8e-12 * np.exp(-0.5 * ((t - 20.0) / 0.42) ** 2)
    p_ref = P0_W + d + planet
    p_x = p_ref + 0.4e12 * (d + planet) ** 2
    p_x[np.abs(t - 20.0) < 0.3] = np.nan
    r = leakage_between(t, p_x, p_ref, F_HWP_HZ)
    assert r.n_masked > FS_HZ  # more than a second around the crossing
    assert r.nl_per_w == pytest.approx(0.8e12, rel=0.01)
    kept = leakage_between(t, p_x, p_ref, F_HWP_HZ, clip=np.inf)
    # Kept, the crossing's edges swamp both lines: no 2f line above their noise, or a far larger sigma.
    assert kept.n_masked == 0
    assert kept.status == STATUS_NO_2F or kept.sigma_nl_per_w > 10 * r.sigma_nl_per_w


def test_the_median_is_a_number_when_resolved_and_a_bound_when_not():
    t, d, rng = _series(seconds=15.0)
    resolved, noisy = [], []
    for k in range(9):
        p_ref = P0_W + d
        noise = 1e-17 * rng.standard_normal(t.size)
        resolved.append(leakage_between(t, p_ref + (0.3e12 + 0.05e12 * k) * d**2 + noise, p_ref, F_HWP_HZ))
        noisy.append(leakage_between(t, p_ref + 1e-15 * rng.standard_normal(t.size), p_ref, F_HWP_HZ))
    m = median_nl(resolved)
    assert m.resolved and m.value_per_pw == pytest.approx(2 * 0.5, rel=0.01) and m.n_resolved == 9
    n = median_nl(noisy)
    assert not n.resolved and n.value_per_pw is None and n.n_detectors == 9
    # The bound covers the truth (0) and is of the order of the per-detector noise, not far above it.
    assert 0 < n.bound_per_pw < 3 * n.detector_sigma_per_pw
    assert median_nl([]).n_detectors == 0 and median_nl([]).bound_per_pw is None
