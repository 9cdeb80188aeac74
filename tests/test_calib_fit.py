"""Per-detector calibration fits: accuracy, honest uncertainties, end to end, bad input."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from mntes_stream.core.calib.campaign import pulls
from mntes_stream.core.calib.endtoend import REQUIREMENT_PER_PW, calibration_nonlinearity
from mntes_stream.core.calib.fit import FitOptions, fit_detector, tabulated_transition
from mntes_stream.core.calib.forward import PARAM_NAMES
from mntes_stream.core.calib.measurements import (
    KINDS,
    Campaign,
    DetectorCalibration,
    Sweep,
    assemble_campaign,
)
from mntes_stream.core.calib.simulate import SMALL_GRID, simulate_campaign
from mntes_stream.core.convert import EnvironmentBlock, make_converter
from mntes_stream.core.transition import TabulatedTransition
from mntes_stream.core.validation import expected_linear_nonlinearity_per_w
from mntes_stream.errors import ConfigError
from mntes_stream.reports.calib_run import fit_campaign

N_DET = 100


@pytest.fixture(scope="module")
def fitted():
    campaign, truth = simulate_campaign(N_DET, seed=20240621, grid=SMALL_GRID)
    fits = fit_campaign(campaign, workers=2)
    return campaign, truth, fits


def test_every_detector_fits_with_a_sensible_chi2(fitted):
    _, _, fits = fitted
    assert [f.status for f in fits.values()] == ["ok"] * N_DET
    chi = np.array([f.chi2 / f.ndf for f in fits.values()])
    assert 0.9 < np.median(chi) < 1.1
    assert all(f.cov.shape == (len(PARAM_NAMES),) * 2 and np.all(np.isfinite(f.sigma)) for f in fits.values())


def test_parameters_within_3_sigma_and_pulls_have_unit_width(fitted):
    _, truth, fits = fitted
    ids, p = pulls(fits, truth)
    assert len(ids) == N_DET
    within = np.abs(p) < 3
    # Every parameter within 3 sigma of the truth for >= 95% of detectors ...
    assert within.mean(axis=0).min() >= 0.95, dict(zip(PARAM_NAMES, within.mean(axis=0)))
    # ... and all 15 at once for >= 90% (0.9973^15 = 0.96 if independent).
    assert np.all(within, axis=1).mean() >= 0.90
    # Honest uncertainties: unit width (the standard deviation of a 100-sample std is ~0.07).
    std = p.std(axis=0, ddof=1)
    assert np.all((std > 0.8) & (std < 1.2)), dict(zip(PARAM_NAMES, std.round(3)))
    assert np.all(np.abs(p.mean(axis=0)) < 0.35), dict(zip(PARAM_NAMES, p.mean(axis=0).round(3)))


def test_end_to_end_nonlinearity_below_requirement(fitted):
    _, truth, fits = fitted
    truth_p = {d: truth[d][0] for d in fits}
    arctan = {d: f.params for d, f in fits.items()}
    eps = np.array([r.eps_per_w for r in calibration_nonlinearity(truth_p, arctan, "exact").values()]) * 1e-12
    assert np.max(np.abs(eps)) < REQUIREMENT_PER_PW / 10
    tab = {d: f.params.replace(transition=tabulated_transition(f)) for d, f in fits.items()}
    assert all(isinstance(p.transition, TabulatedTransition) for p in tab.values())
    eps_tab = np.array([r.eps_per_w for r in calibration_nonlinearity(truth_p, tab, "exact").values()]) * 1e-12
    assert np.max(np.abs(eps_tab)) < REQUIREMENT_PER_PW
    # Through the response tables, on a subset (the same numbers as the exact inverse).
    sub = list(fits)[:8]
    eps_table = np.array([r.eps_per_w for r in calibration_nonlinearity(
        {d: truth_p[d] for d in sub}, {d: arctan[d] for d in sub}, "table").values()]) * 1e-12
    np.testing.assert_allclose(eps_table, eps[:8], atol=1e-6)
    # The metric sees what the fit removes: the linear conversion of the same counts.
    lin = calibration_nonlinearity({d: truth_p[d] for d in sub}, {d: truth_p[d] for d in sub}, "linear", amplitude_w=2e-15)
    expected = np.array([expected_linear_nonlinearity_per_w(truth_p[d]) for d in sub])
    np.testing.assert_allclose([lin[d].eps_per_w for d in sub], expected, rtol=0.02)
    assert np.all(np.abs(expected) * 1e-12 > 0.5)


def test_conversion_does_not_depend_on_the_gain_gauge(fitted):
    campaign, truth, fits = fitted
    det = next(iter(campaign.detectors.values()))
    scaled = DetectorCalibration(det.detector_id, det.bias_freq_hz, 1.1 * det.gain_abs_a_per_count,
                                 det.p_opt_w, det.t_bath_k, det.b_field_t, det.sweeps)
    f1, f2 = fits[det.detector_id], fit_detector(scaled)
    assert f2.ok
    # The impedance scale follows the assumed |g|: R -> R / 1.21 ...
    assert f2.value("r_n_ohm") / f1.value("r_n_ohm") == pytest.approx(1 / 1.21, rel=1e-4)
    # ... the power from counts does not.
    true_p = truth[det.detector_id][0]
    counts = np.linspace(0.9, 1.1, 7)[None, :] * (1.5e-6 / abs(true_p.gain_a_per_count)) * np.exp(-1j * np.angle(true_p.gain_a_per_count))
    env = EnvironmentBlock(t_bath_k=np.full(7, 0.1), b_field_t=np.full(7, 3e-5))
    out = [make_converter("exact", {det.detector_id: f.params}).convert(
        [det.detector_id], counts.real.copy(), counts.imag.copy(), env).p_opt_w for f in (f1, f2)]
    assert np.all(np.isfinite(out[0]))
    np.testing.assert_allclose(out[1], out[0], rtol=1e-6)


# --------------------------------------------------------------------------- bad input


@pytest.fixture(scope="module")
def few():
    campaign, truth = simulate_campaign(2, seed=3, grid=SMALL_GRID)
    return campaign, truth


def _replace(det: DetectorCalibration, kind: str, fn) -> DetectorCalibration:
    out, done = [], False
    for s in det.sweeps:
        if s.kind == kind and not done:
            done = True
            s = fn(s)
            if s is None:
                continue
        out.append(s)
    return det.replace_sweeps(out)


def test_missing_measurement_fails_with_the_reason(few):
    det = next(iter(few[0].detectors.values()))
    f = fit_detector(_replace(det, "network_super", lambda s: None))
    assert f.status == "failed" and f.params is None
    assert f.reasons == ("missing measurement(s): network_super",)


def test_too_few_points_drop_the_sweep_and_say_so(few):
    det = next(iter(few[0].detectors.values()))
    f = fit_detector(_replace(det, "optical_response", lambda s: s.select(np.arange(len(s)) < 3)))
    assert f.status == "failed"
    assert "missing measurement(s): optical_response" in f.reasons
    assert any("too few usable points (3 < 5)" in n for n in f.notes)
    # A second I-V curve too short is only noted: the others still constrain the fit.
    f = fit_detector(_replace(det, "iv_curve", lambda s: s.select(np.arange(len(s)) < 4)))
    assert f.ok and any("iv_curve sweep" in n and "not used" in n for n in f.notes)


def test_nan_points_are_dropped_and_noted(few):
    det = next(iter(few[0].detectors.values()))

    def poison(s):
        c = s.counts.copy()
        c[[1, 4]] = np.nan
        return Sweep(s.kind, s.detector_id, s.swept, s.fixed, c, s.sigma_counts)

    f = fit_detector(_replace(det, "iv_curve", poison))
    assert f.ok
    assert any("dropped 2 of" in n and "iv_curve" in n for n in f.notes)
    assert sum(n for k, n, _ in f.sweep_chi2 if k == "iv_curve") == sum(len(s) for s in det.by_kind("iv_curve")) - 2


def test_wrong_noise_is_flagged_not_written(few):
    campaign, _ = few
    det = next(iter(campaign.detectors.values()))
    rng = np.random.default_rng(1)

    def noisier(s):  # actual noise 4x the declared sigma
        extra = 3 * s.sigma_counts * (rng.standard_normal(len(s)) + 1j * rng.standard_normal(len(s)))
        return Sweep(s.kind, s.detector_id, s.swept, s.fixed, s.counts + extra, s.sigma_counts)

    f = fit_detector(_replace(det, "iv_curve", noisier))
    assert f.status == "flagged"
    assert any(r.startswith("poor fit") for r in f.reasons)
    assert any("iv_curve" in r for r in f.reasons)


def test_mismatched_detector_ids(few):
    campaign, truth = few
    a, b = campaign.detectors.values()
    with pytest.raises(ConfigError, match="mismatched detector id"):
        a.replace_sweeps(a.sweeps + (b.sweeps[0],))
    headers = [DetectorCalibration(a.detector_id, a.bias_freq_hz, a.gain_abs_a_per_count, a.p_opt_w, a.t_bath_k)]
    c = assemble_campaign(headers, list(a.sweeps) + list(b.sweeps))
    assert list(c.detectors) == [a.detector_id]
    assert b.detector_id in c.orphans and "no detector header" in c.orphans[b.detector_id]
    fits = fit_campaign(Campaign({a.detector_id: c.detectors[a.detector_id]}, c.orphans))
    assert fits[a.detector_id].ok and fits[b.detector_id].status == "failed"
    with pytest.raises(ConfigError, match="no truth"):
        pulls(fits, {b.detector_id: truth[b.detector_id]})
    with pytest.raises(ConfigError, match="two calibration headers"):
        assemble_campaign(headers * 2, [])


def test_sweep_validation():
    ok = dict(kind="iv_curve", detector_id="b0m0c000", swept=[0.5, 1.0], counts=[1 + 1j, 2 + 2j], sigma_counts=1.0,
              fixed={"p_opt_w": 5e-13, "b_field_t": 0.0, "t_bath_k": 0.1, "freq_hz": 2e6})
    assert len(Sweep(**ok)) == 2
    for change, match in (
        ({"kind": "noise"}, "unknown calibration measurement kind"),
        ({"fixed": {**ok["fixed"], "bias_ratio": 1.0}}, "fixed conditions must be exactly"),
        ({"sigma_counts": -1.0}, "sigma_counts must be > 0"),
        ({"counts": [1j]}, "equal length"),
        ({"fixed": {**ok["fixed"], "t_bath_k": -0.1}}, "not a valid fixed condition"),
    ):
        with pytest.raises(ConfigError, match=match):
            Sweep(**{**ok, **change})


def test_fit_options_required_kinds_are_respected(few):
    det = next(iter(few[0].detectors.values()))
    f = fit_detector(det, FitOptions(required=KINDS, min_points=100))
    assert f.status == "failed" and "missing measurement(s)" in f.reasons[0]
    assert dataclasses.replace(FitOptions(), max_nfev=1).max_nfev == 1
    assert fit_detector(det, FitOptions(max_nfev=1)).status == "flagged"
