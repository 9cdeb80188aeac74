"""Flags from physics (issue 17): thresholds checked against an independent Brent solve.

The truth of every sample here comes from ``scipy.optimize.brentq`` on the
power balance written out in this file (not the package's solver); the
converters see int32 counts of that truth.
"""

import numpy as np
import pytest
from scipy.optimize import brentq

from mntes_stream.bench.convert import tabulated_params
from mntes_stream.core import flags as fl
from mntes_stream.core import model
from mntes_stream.core.convert import BASELINE_TOLERANCE_W, EnvironmentBlock, make_converter
from mntes_stream.core.params import table1_params

KINDS = ("table", "grid", "exact", "linear", "electrical")


def _balance(p, r, p_opt, v, t_bath=0.1):
    """Independent power balance at resistance r: heat out minus heat in (W)."""
    i_abs = np.sqrt(2) * v / abs(r + p.z_thev_ohm)
    t = float(p.transition.temperature_k(r)) - p.current_shift_k_per_a * i_abs
    joule = v**2 * r / abs(r + p.z_thev_ohm) ** 2
    return p.k_w_per_k_n * (t**p.n - t_bath**p.n) - joule - p_opt


def _brent_r(p, p_opt, v, lo, hi):
    return brentq(lambda r: _balance(p, r, p_opt, v), lo, hi, xtol=1e-15, rtol=1e-15)


def _counts(p, r, v):
    c = np.sqrt(2) * v / (r + p.z_thev_ohm) / p.gain_a_per_count
    return np.array([[np.rint(c.real)]], np.int32), np.array([[np.rint(c.imag)]], np.int32)


def _convert(kind, p, ci, cq, v):
    conv = make_converter(kind, {p.detector_id: p})
    env = EnvironmentBlock(np.array([0.1]), np.array([0.0]), np.array([v]))
    return conv.convert([p.detector_id], ci, cq, env)


@pytest.fixture(scope="module", params=["arctan", "tabulated"])
def det(request):
    return table1_params("b0m0c001") if request.param == "arctan" else tabulated_params("b0m0c002")


@pytest.mark.parametrize("kind", KINDS)
def test_saturation_threshold_just_inside_and_outside(det, kind):
    """Brent puts a detector 20 sigma_R either side of its SATURATED threshold; only outside is flagged."""
    p = det
    th = model.flag_thresholds(p)
    v = p.v_thev_v
    sigma_r = th.sigma_i_a * abs(th.r_saturated_ohm + p.z_thev_ohm) ** 2 / (np.sqrt(2) * v)
    lo_r, hi_r = 0.3 * p.r_normal_ohm, float(model.branch_bounds_ohm(p)[1])
    for side, r_target in (("inside", th.r_saturated_ohm - 20 * sigma_r), ("outside", th.r_saturated_ohm + 20 * sigma_r)):
        if r_target >= hi_r:  # past the top of the model: the detector is normal at any higher power
            r_target = hi_r
        p_opt = _balance(p, r_target, 0.0, v)  # the power that puts it there
        r = _brent_r(p, p_opt, v, lo_r, hi_r) if r_target < hi_r else r_target
        out = _convert(kind, p, *_counts(p, r, v), v)
        f = int(out.flags[0, 0]) & ~fl.OUT_OF_TABLE & ~fl.ENV_OUT_OF_RANGE
        if side == "inside":
            assert not f & fl.SATURATED, (kind, side, f)
            if kind in ("table", "grid", "exact") and not out.flags[0, 0] & fl.OUT_OF_TABLE:
                assert abs(out.p_opt_w[0, 0] - p_opt) < 2e-16  # the counts' rounding at the top of the transition
        else:
            assert f & fl.SATURATED and np.isnan(out.p_opt_w[0, 0]), (kind, side, f)


@pytest.mark.parametrize("kind", KINDS)
def test_normal_detector_with_noisy_counts_is_always_saturated(kind):
    """The bug of issue 17: a tabulated detector driven normal, noisy int32 counts, never unflagged."""
    p = tabulated_params("b0m0c002")
    rng = np.random.default_rng(5)
    v = p.v_thev_v
    r = float(model.branch_bounds_ohm(p)[1])  # normal: R at the top of the measured curve
    c = np.sqrt(2) * v / (r + p.z_thev_ohm) / p.gain_a_per_count
    n = 20000
    sigma = model.DEFAULT_READOUT_NOISE_A / abs(p.gain_a_per_count)
    ci = np.rint(c.real + sigma * rng.standard_normal((1, n))).astype(np.int32)
    cq = np.rint(c.imag + sigma * rng.standard_normal((1, n))).astype(np.int32)
    conv = make_converter(kind, {p.detector_id: p})
    out = conv.convert([p.detector_id], ci, cq, EnvironmentBlock(np.full(n, 0.1), np.zeros(n)))
    assert np.all(out.flags & fl.SATURATED) and np.all(np.isnan(out.p_opt_w))


@pytest.mark.parametrize("kind", KINDS)
def test_latched_threshold_just_inside_and_outside(det, kind):
    """Either side of the LATCHED threshold (|z| plus the noise margin), from Brent on the balance."""
    p = det
    th = model.flag_thresholds(p)
    out_r = _latched_r(p, th)
    for r, expect in ((th.r_latched_ohm * 1.02, 0), (out_r, fl.LATCHED | fl.SUPERCONDUCTING)):
        f = int(_convert(kind, p, *_counts(p, r, p.v_thev_v), p.v_thev_v).flags[0, 0])
        f &= fl.LATCHED | fl.SUPERCONDUCTING | fl.SATURATED
        assert f == expect, (kind, r, f)


def _latched_r(p, th):
    return 0.98 * th.r_latched_ohm


def test_latched_state_from_brent_is_stable_and_flagged():
    """An under-biased arctan detector: Brent finds its state below |z|; dP/dR > 0 there; flagged LATCHED."""
    p = table1_params()
    v = 0.25 * p.v_thev_v
    r = _brent_r(p, p.p_opt_w, v, 0.0015, abs(p.z_thev_ohm))
    op = model.solve_operating_point(p, p.p_opt_w, v_thev_v=v)
    assert int(op.state) == model.STATE_LATCHED and abs(float(op.r_ohm) - r) < 1e-12
    assert float(model.balance_slope_w_per_ohm(p, r, v)) > 0
    out = _convert("table", p, *_counts(p, r, v), v)
    assert int(out.flags[0, 0]) & fl.LATCHED and np.isnan(out.p_opt_w[0, 0])


def test_bistable_detector_keeps_its_history():
    """Half bias: two stable states for P between P(R2) and P(R1); the way in decides."""
    p = table1_params()
    v = 0.5 * p.v_thev_v
    r0, r1, r2 = (float(x) for x in model.stability_bounds_ohm(p, v))
    assert r0 < r1 < r2 < abs(p.z_thev_ohm)
    p_r1 = float(model.power_of_resistance_w(p, r1, p.t_bath_k, 0.0, v))
    p_r2 = float(model.power_of_resistance_w(p, r2, p.t_bath_k, 0.0, v))
    assert p_r2 < p_r1
    mid = 0.5 * (p_r1 + p_r2)
    # Independent: both roots by Brent, each on a branch of positive slope.
    r_low = _brent_r(p, mid, v, r0 * 1.000001, r1)
    r_high = _brent_r(p, mid, v, r2, 0.999 * p.r_normal_ohm)
    # Down from high power, down into the window, below P(R2) (drops), back into the window (stays),
    # above P(R1) (re-enters).
    p_seq = np.array([0.6e-12, mid, 0.5 * p_r2, mid, 1.05 * p_r1, mid])
    op = model.solve_operating_point(p, p_seq, v_thev_v=v, sequential=True)
    assert op.dropped.tolist() == [False, False, True, True, False, False]
    assert abs(op.r_ohm[1] - r_high) < 1e-12 and abs(op.r_ohm[3] - r_low) < 1e-12
    # Elementwise, the history is given.
    both = model.solve_operating_point(p, np.array([mid, mid]), v_thev_v=v, dropped=np.array([False, True]))
    assert abs(both.r_ohm[0] - r_high) < 1e-12 and abs(both.r_ohm[1] - r_low) < 1e-12


@pytest.mark.parametrize("kind", KINDS)
def test_phase_residual_set_on_unexplained_quadrature_not_on_clean_noisy_data(kind):
    p = table1_params("b0m0c001", gain_a_per_count=1e-12 * np.exp(0.7j))
    rng = np.random.default_rng(9)
    n = 20000
    v = p.v_thev_v
    p_opt = np.linspace(0.2e-12, 0.8e-12, n)
    op = model.solve_operating_point(p, p_opt)
    sigma = model.DEFAULT_READOUT_NOISE_A
    i = op.i_a + sigma * (rng.standard_normal(n) + 1j * rng.standard_normal(n))
    conv = make_converter(kind, {p.detector_id: p})
    env = EnvironmentBlock(np.full(n, 0.1), np.zeros(n))

    def run(i_meas):
        c = i_meas / p.gain_a_per_count
        return conv.convert([p.detector_id], np.rint(c.real)[None].astype(np.int32),
                            np.rint(c.imag)[None].astype(np.int32), env)

    clean = run(i)
    assert not np.any(clean.flags & fl.PHASE_RESIDUAL)
    # A signal orthogonal to the model's current (as a wrong demodulation phase or pickup gives).
    ortho = 1j * op.i_a / np.abs(op.i_a) * 1.5e-9 * np.sin(np.linspace(0, 20, n))
    dirty = run(i + ortho)
    hit = (dirty.flags[0] & fl.PHASE_RESIDUAL) != 0
    big = np.abs(1.5e-9 * np.sin(np.linspace(0, 20, n))) > 13 * np.hypot(sigma, 1e-12 / np.sqrt(12))
    assert np.all(hit[big]) and hit.mean() > 0.2
    assert np.isfinite(dirty.p_opt_w[0, hit]).all()  # a warning: the value is kept
    del v


def test_range_sweep_meets_the_acceptance_for_every_kind(tmp_path):
    """validate --range in small: every transition model, every kind (baselines via NONLINEAR), every region."""
    from mntes_stream.cli import main
    from mntes_stream.core.sweep import REGIONS, range_sweep

    res = range_sweep(n_samples=6000, seed=3)
    assert set(res.stats) == {"arctan", "tabulated", "current-dependent"}
    seen = set()
    for model_name, kinds in res.stats.items():
        for kind in ("table", "grid", "exact"):
            per = kinds[kind]
            for region in REGIONS:
                assert per[region]["worst_unflagged_error_w"] <= 1e-17, (model_name, kind, region)
                if per[region]["n"]:
                    seen.add(region)
            assert per["transition"]["n_in_domain"] > 500
            assert per["transition"]["flagged_frac_in_domain"] <= 1e-3, (model_name, kind)
            for region in ("saturated", "latched", "superconducting"):
                assert per[region]["unusable_frac"] == 1.0 or per[region]["n"] == 0, (model_name, kind, region)
        # The baselines meet it through NONLINEAR (their tolerance, 1e-17 W); in this sweep's
        # environment (bath 90-110 mK, field +-200 uT) that flags most of their transition samples.
        for kind in ("linear", "electrical"):
            per = kinds[kind]
            for region in REGIONS:
                assert per[region]["worst_unflagged_error_w"] <= BASELINE_TOLERANCE_W, (model_name, kind, region)
    assert {"transition", "saturated", "latched", "superconducting"} <= seen
    out = tmp_path / "range"
    assert main(["validate", "--range", "--samples", "3000", "--out", str(out), "--json"]) == 0
    assert (out / "range_errors.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert "arctan" in (out / "range_summary.json").read_text()


@pytest.mark.parametrize("kind", KINDS)
def test_superconducting_bottom_inside_and_outside(kind):
    """A tabulated transition with a zero-resistance bottom: R = 0 reads SUPERCONDUCTING alone;
    20 sigma_R above the bottom threshold (from Brent, under-biased) it reads SUPERCONDUCTING | LATCHED."""
    p = tabulated_params("b0m0c002")
    th = model.flag_thresholds(p)
    v = 0.2 * p.v_thev_v
    r_min = float(p.transition.r_domain_ohm()[0])
    assert r_min == 0.0
    # Independent: below P(R = 0+) the balance has no root in the transition; the TES is superconducting.
    p0 = _balance(p, 1e-12, 0.0, v)
    assert p0 > 0 and int(model.solve_operating_point(p, 0.5 * p0, v_thev_v=v).state) == model.STATE_SUPERCONDUCTING
    sigma_r0 = th.k_bottom_ohm_v / (model.K_SIGMA * v)
    r_up = th.at_bias(v)[0] + 20 * sigma_r0
    p_up = _balance(p, r_up, 0.0, v)
    r = _brent_r(p, p_up, v, 1e-12, 0.9 * abs(p.z_thev_ohm))
    assert abs(r - r_up) < 1e-12
    mask = fl.SUPERCONDUCTING | fl.LATCHED | fl.SATURATED
    env_v = v
    for r_at, expect in ((0.0, fl.SUPERCONDUCTING), (r, fl.SUPERCONDUCTING | fl.LATCHED)):
        f = int(_convert(kind, p, *_counts(p, r_at, env_v), env_v).flags[0, 0]) & mask
        assert f == expect, (kind, r_at, f)


def test_a_converter_pickled_with_the_old_kernel_layout_rebuilds_its_thresholds():
    """Restart snapshots pickle converters; one from before the 21-column layout must not be read past its end."""
    import pickle

    p = table1_params("b0m0c001")
    conv = make_converter("exact", {p.detector_id: p})
    old = pickle.loads(pickle.dumps(conv))
    old.__dict__["_phys"] = conv._phys[:, :15].copy()  # the 15 columns of the old layout
    del old.__dict__["readout_noise_a"]
    back = pickle.loads(pickle.dumps(old))
    assert np.array_equal(back._phys, conv._phys)
