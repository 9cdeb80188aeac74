"""Simulated calibration campaigns: known truth, realistic sweeps, noise.

Per detector the truth scatters around the paper's Table 1 detector, the
bias is tuned to ``R = 0.7 R_n`` at the nominal loading (as an operator
would), and the sweeps are placed the way a campaign places them: centred on
each detector's own transition and resonance, found beforehand by a coarse
scan. Imperfections that the fit has to model:

- measurement noise (complex Gaussian, known sigma per point);
- finite probe bias: R(T) and the network analyses carry the probe's Joule
  power (self-heating) and the optical load;
- readout parasitics: a frequency-dependent Thevenin impedance (series LC
  resonator, residual reactance at the bias frequency, ESR slope), a magnetic
  pickup in the readout, an arbitrary demodulation phase of the DAN gain.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mntes_stream.core.calib.forward import Design, Readout, predict_counts, theta_from_params
from mntes_stream.core.calib.measurements import CONDITIONS, SWEPT_AXIS, Campaign, DetectorCalibration, Sweep
from mntes_stream.core.ids import detector_id
from mntes_stream.core.model import power_of_resistance_w, tune_bias_v
from mntes_stream.core.params import DetectorParams, table1_params
from mntes_stream.errors import ConfigError

__all__ = ["SweepGrid", "SMALL_GRID", "FULL_GRID", "TruthSpread", "draw_truth", "design_sweeps", "simulate_campaign"]


@dataclass(frozen=True)
class SweepGrid:
    """Points per sweep and the campaign's fixed choices.

    ``iv_t_bath_k``: bath temperatures of the I-V curves; ``field_bias_ratios``:
    biases of the field sweeps (1 = operating point; a high bias drives the TES
    normal, where the field sweep sees the pickup alone).
    """

    n_optical: int = 40
    n_field: int = 25
    n_iv: int = 40
    n_rt: int = 60
    n_na_normal: int = 40
    n_na_super: int = 40
    iv_t_bath_k: tuple = (0.080, 0.100, 0.120, 0.140)
    field_bias_ratios: tuple = (1.0, 2.5)
    b_max_t: float = 100e-6
    probe_bias_ratio: float = 0.05
    t_bath_normal_k: float = 0.250
    iv_bias_ratio_max: float = 2.5
    r_frac_range: tuple = (0.25, 0.92)   # biased sweeps stay inside the transition
    rt_r_frac_range: tuple = (0.03, 0.97)


FULL_GRID = SweepGrid()
SMALL_GRID = SweepGrid(n_optical=12, n_field=8, n_iv=10, n_rt=16, n_na_normal=10, n_na_super=10,
                       iv_t_bath_k=(0.085, 0.115, 0.140))


@dataclass(frozen=True)
class TruthSpread:
    """Relative (``*_rel``) or absolute scatter of the truth around Table 1."""

    t_c_k: float = 2e-3
    iqr_rel: float = 0.10
    r_n_rel: float = 0.03
    n: float = 0.1
    p_sat_rel: float = 0.05
    z_re_ohm: float = 0.01
    z_im_ohm: float = 0.01
    l_series_h: float = 60e-6
    l_series_rel: float = 0.05
    r_slope_ohm: tuple = (0.3, 0.1)        # mean, sigma
    t_c_shift_k_per_t: tuple = (2.0, 0.5)
    t_c_shift_k_per_t2: tuple = (5e3, 2e3)
    pickup_a_per_t: float = 1e-4           # per component
    gain_abs_a_per_count: float = 1e-12
    gain_abs_rel: float = 0.02
    bias_freq_hz: tuple = (1.5e6, 4.5e6)   # carrier comb range


def draw_truth(n_det: int, rng: np.random.Generator, spread: TruthSpread = TruthSpread(),
               board: int = 0, module: int = 0) -> list[tuple[DetectorParams, Readout]]:
    """Random detectors around Table 1, biases tuned to R = 0.7 R_n at the nominal loading."""
    if n_det < 1:
        raise ConfigError("n_det must be >= 1")
    base = table1_params()
    t1 = base.transition
    out = []
    for ch in range(n_det):
        t_c = t1.t_c_k + spread.t_c_k * rng.standard_normal()
        n = base.n + spread.n * rng.standard_normal()
        p_sat = base.p_sat_w * (1.0 + spread.p_sat_rel * rng.standard_normal())
        k = p_sat / (t_c**n - base.t_bath_k**n)
        p = table1_params(
            detector_id(board, module, ch),
            t_c_k=t_c,
            iqr_k=t1.iqr_k * float(np.exp(spread.iqr_rel * rng.standard_normal())),
            r_n_ohm=t1.r_n_ohm * (1.0 + spread.r_n_rel * rng.standard_normal()),
            n=n,
            k_w_per_k_n=k,
            z_thev_ohm=complex(abs(0.05 + spread.z_re_ohm * rng.standard_normal()),
                               0.05 + spread.z_im_ohm * rng.standard_normal()),
            t_c_shift_k_per_t=spread.t_c_shift_k_per_t[0] + spread.t_c_shift_k_per_t[1] * rng.standard_normal(),
            t_c_shift_k_per_t2=spread.t_c_shift_k_per_t2[0] + spread.t_c_shift_k_per_t2[1] * rng.standard_normal(),
            pickup_a_per_t=complex(*(spread.pickup_a_per_t * rng.standard_normal(2))),
            gain_a_per_count=spread.gain_abs_a_per_count * (1.0 + spread.gain_abs_rel * rng.standard_normal())
            * np.exp(1j * rng.uniform(-np.pi, np.pi)),
        )
        p = p.replace(v_thev_v=float(tune_bias_v(p, 0.7)))
        readout = Readout(
            bias_freq_hz=float(rng.uniform(*spread.bias_freq_hz)),
            l_series_h=spread.l_series_h * (1.0 + spread.l_series_rel * rng.standard_normal()),
            r_slope_ohm=spread.r_slope_ohm[0] + spread.r_slope_ohm[1] * rng.standard_normal(),
        )
        out.append((p, readout))
    return out


def _t_bath_at(p: DetectorParams, r_frac: float, v: float, p_opt: float) -> float:
    """Bath temperature that puts the TES at ``r_frac R_n`` (explicit power balance)."""
    r = r_frac * p.r_normal_ohm
    # power_of_resistance_w is K T^n - K T_bath^n - J: solve for T_bath.
    excess = float(power_of_resistance_w(p, r, 0.0, 0.0, v)) - p_opt
    return (excess / p.k_w_per_k_n) ** (1.0 / p.n)


def _sweep(kind, det_id, swept, **fixed) -> Sweep:
    axis = SWEPT_AXIS[kind]
    fixed = {c: fixed[c] for c in CONDITIONS if c != axis}
    n = len(swept)
    return Sweep(kind, det_id, np.asarray(swept, float), fixed, np.zeros(n, complex), np.ones(n))


def design_sweeps(p: DetectorParams, readout: Readout, grid: SweepGrid = FULL_GRID) -> list[Sweep]:
    """Where a campaign puts the points for this detector (counts left at zero)."""
    det_id, f0 = p.detector_id, readout.bias_freq_hz
    p0, tb0, v0 = p.p_opt_w, p.t_bath_k, p.v_thev_v
    r_n = p.r_normal_ohm
    r_lo, r_hi = grid.r_frac_range
    common = dict(p_opt_w=p0, b_field_t=0.0, bias_ratio=1.0, t_bath_k=tb0, freq_hz=f0)
    sweeps = []
    # Optical response: loading that moves R across the transition at the operating bias.
    p_lo, p_hi = (float(power_of_resistance_w(p, x * r_n, tb0)) for x in (r_lo, r_hi))
    sweeps.append(_sweep("optical_response", det_id, np.linspace(max(p_lo, 0.0), p_hi, grid.n_optical), **common))
    for ratio in grid.field_bias_ratios:
        sweeps.append(_sweep("field_sensitivity", det_id, np.linspace(-grid.b_max_t, grid.b_max_t, grid.n_field),
                             **{**common, "bias_ratio": ratio}))
    for tb in grid.iv_t_bath_k:
        u_lo = float(tune_bias_v(p, r_lo, t_bath_k=tb)) / v0
        sweeps.append(_sweep("iv_curve", det_id, np.linspace(u_lo, grid.iv_bias_ratio_max, grid.n_iv),
                             **{**common, "t_bath_k": tb}))
    probe = grid.probe_bias_ratio
    # R(T): bath temperatures stepped so that R moves in equal steps (fine through the
    # steep part of the transition, where its shape matters most).
    fracs = np.linspace(*grid.rt_r_frac_range, grid.n_rt)
    t_baths = np.array([_t_bath_at(p, x, probe * v0, p0) for x in fracs])
    sweeps.append(_sweep("impedance_temperature", det_id, t_baths, **{**common, "bias_ratio": probe}))
    # Network analyses: +-4 half widths around the resonance, normal and superconducting.
    omega0 = 2 * np.pi * f0
    l_h = readout.l_series_h
    f_res = f0 * np.sqrt(1.0 - p.z_thev_ohm.imag / (omega0 * l_h))
    for kind, r_tot, tb in (("network_normal", r_n + p.z_thev_ohm.real, grid.t_bath_normal_k),
                            ("network_super", p.z_thev_ohm.real, tb0)):
        half_hz = r_tot / (4 * np.pi * l_h)
        n_pts = grid.n_na_normal if kind == "network_normal" else grid.n_na_super
        sweeps.append(_sweep(kind, det_id, f_res + np.linspace(-4, 4, n_pts) * half_hz,
                             **{**common, "bias_ratio": probe, "t_bath_k": tb}))
    return sweeps


def simulate_campaign(
    n_det: int,
    seed: int = 0,
    grid: SweepGrid = FULL_GRID,
    noise_a: float = 1e-10,
    spread: TruthSpread = TruthSpread(),
    board: int = 0,
    module: int = 0,
) -> tuple[Campaign, dict[str, tuple[DetectorParams, Readout]]]:
    """A campaign of ``n_det`` detectors and its truth.

    Parameters
    ----------
    noise_a : float
        Noise of each of I and Q of a point's mean, expressed in amperes
        (converted to counts with each detector's gain).

    Returns
    -------
    campaign : Campaign
    truth : dict of detector id to (DetectorParams, Readout)
    """
    if not noise_a > 0:
        raise ConfigError("noise_a must be > 0")
    rng = np.random.default_rng(seed)
    truth = draw_truth(n_det, rng, spread, board, module)
    dets = {}
    for p, readout in truth:
        abs_g = abs(p.gain_a_per_count)
        header = DetectorCalibration(p.detector_id, readout.bias_freq_hz, abs_g, p.p_opt_w, p.t_bath_k, 0.0)
        sweeps = design_sweeps(p, readout, grid)
        design = Design.from_detector(header, tuple(sweeps))
        mean = predict_counts(theta_from_params(p, readout), design)
        sigma = noise_a / abs_g
        noisy = mean + sigma * (rng.standard_normal(mean.shape) + 1j * rng.standard_normal(mean.shape))
        out, start = [], 0
        for s in sweeps:
            sl = slice(start, start + len(s))
            out.append(Sweep(s.kind, s.detector_id, s.swept, s.fixed, noisy[sl], np.full(len(s), sigma)))
            start += len(s)
        dets[p.detector_id] = header.replace_sweeps(out)
    meta = {"simulated": "true", "seed": str(seed), "n_detectors": str(n_det), "noise_a": repr(noise_a)}
    return Campaign(detectors=dets, metadata=meta), {p.detector_id: (p, r) for p, r in truth}
