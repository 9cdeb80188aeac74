"""Validation study: MNTES against the linear conversion, on simulated data (pure).

Every effect of the paper's section 2 is measured on a simulated Table-1
detector (bias tuned to R = 0.7 R_n at 0.5 pW, assumed magnetic coefficients)
by converting its quantised counts with each converter and comparing with the
simulator's truth. The converters see the true environment at every sample
(perfect housekeeping: alignment is the service's job, tested there).

Effective nonlinearity (the quantity compared with the 0.014 pW^-1 requirement)
-------------------------------------------------------------------------------
Write the reconstructed power as a function of the true power,
``P_rec = f(P)``, and expand about the loading P0::

    f(P0 + dP) = f(P0) + f' dP + f''/2 dP^2 + O(dP^3)

and define ``eps = f'' / f'``: the reconstructed-power analogue of the paper's
leading-order nonlinearity ``(d2I/dP2) / (dI/dP)``. For the linear conversion
``f(P) = P0 + Re((I(P) - I0) / S)`` with ``S = dI/dP``, so ``f' = 1`` and
``eps = Re(I'' / S)``, the paper's number wherever ``I''/S`` is real. A pure
HWP signal ``dP = A cos(2 w t + phi)`` gives
``f''/2 dP^2 = f'' A^2 / 4 (1 + cos(4 w t + 2 phi))``: a 4f line of amplitude
``a4 = f'' A^2 / 4`` and a 2f line of amplitude ``f' A``, hence::

    eps_eff = 4 a4 / (f' A^2)

measured by least squares on ``P_rec - P`` (a4 projected on the phase 2 phi;
the quadrature part is reported as a check). Third-order terms change it by a
relative ``O((A / P_s)^2)`` with ``P_s`` ~ 0.3 pW for the Table-1 detector:
0.4% at the study's A = 20 fW (2.6% at 50 fW).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from mntes_stream.core import model
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.sim import HWP_FREQUENCIES_HZ, ArraySimulator, SimBlock, SimConfig
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.errors import ConfigError

__all__ = [
    "REQUIREMENT_PER_PW",
    "CALIBRATION_ERRORS",
    "StudyConfig",
    "StudyResult",
    "harmonic_amplitudes",
    "effective_nonlinearity",
    "source_distortion",
    "template_gain",
    "windowed_gain",
    "perturb_params",
    "expected_linear_nonlinearity_per_w",
    "default_converter_factory",
    "run_study",
    "JSON_KEYS",
]

REQUIREMENT_PER_PW = 0.014  # LiteBIRD, Micheli et al. (paper sect. 2.1)

# Assumed 1-sigma ground-calibration uncertainties (stated in the README).
# name -> (label, realistic error, "abs" or "frac", unit of an absolute error)
CALIBRATION_ERRORS: dict[str, tuple[str, float, str, str]] = {
    "t_c_k": ("T_c", 1e-4, "abs", "K"),
    "k_w_per_k_n": ("K", 0.01, "frac", ""),
    "n": ("n", 0.05, "abs", ""),
    "z_re_ohm": ("Re z", 5e-3, "abs", "Ohm"),
    "z_im_ohm": ("Im z", 5e-3, "abs", "Ohm"),
    "v_thev_v": ("V_Thev", 0.005, "frac", ""),
    "r_n_ohm": ("R_n", 0.01, "frac", ""),
    "iqr_k": ("IQR", 0.05, "frac", ""),
    "t_c_shift_k_per_t": ("c1 (T_c shift per B)", 0.1, "frac", ""),
    "t_c_shift_k_per_t2": ("c2 (T_c shift per B^2)", 0.1, "frac", ""),
    "pickup_a_per_t": ("m (readout pickup)", 0.1, "frac", ""),
    "gain_a_per_count": ("gain magnitude (counts to current)", 0.005, "frac", ""),
    "gain_phase_rad": ("gain phase (demodulation)", 1e-3, "abs", "rad"),
}

# Keys of the study's JSON that downstream tools rely on.
JSON_KEYS = (
    "linear_nonlinearity_per_pw", "mntes_nonlinearity_per_pw", "linear_4f_leak_w", "mntes_4f_leak_w",
    "linear_jupiter_peak_frac_error", "mntes_jupiter_peak_frac_error", "linear_dipole_gain_bias",
    "mntes_dipole_gain_bias", "linear_drift_gain_per_mk", "mntes_drift_gain_per_mk",
    "linear_drift_gain_per_ut", "mntes_drift_gain_per_ut",
)


# --- analysis primitives -------------------------------------------------------------------

_BASIS_CACHE: dict = {}


def _harmonic_basis(t: np.ndarray, f0_hz: float, harmonics: tuple) -> tuple[np.ndarray, float]:
    """Design matrix ``[1, trend, cos, sin, ...]`` (n, k) and the trend scale."""
    span = max(float(np.ptp(t)), 1e-30)
    cols = [np.ones_like(t), (t - t.mean()) / span]
    for h in harmonics:
        w = 2 * np.pi * h * f0_hz * t
        cols += [np.cos(w), np.sin(w)]
    return np.column_stack(cols), span


def _solver(t: np.ndarray, f0_hz: float, harmonics: tuple):
    """Least-squares solver (pseudo-inverse) for one time grid, cached: studies refit the same grid."""
    key = (t.size, float(t[0]), float(t[-1]), float(f0_hz), harmonics)
    if key not in _BASIS_CACHE:
        if len(_BASIS_CACHE) > 32:
            _BASIS_CACHE.clear()
        design, span = _harmonic_basis(t, f0_hz, harmonics)
        _BASIS_CACHE[key] = (np.linalg.pinv(design), span)
    return _BASIS_CACHE[key]


def harmonic_amplitudes(t_s, x, f0_hz: float, harmonics=(1, 2, 3, 4, 5, 6), extra=None) -> dict:
    """Least-squares complex amplitudes of harmonics of ``f0_hz`` in ``x``.

    Fits ``x = c0 + c1 t + sum_h Re(a_h exp(i 2 pi h f0 t)) + extra @ b``.

    Parameters
    ----------
    t_s, x : ndarray, shape (n,)
    extra : ndarray, shape (n, k), optional
        Further regressors (their coefficients are returned under ``"extra"``).

    Returns
    -------
    dict
        ``{h: complex a_h}`` plus ``"offset"``, ``"trend"`` (per second), ``"extra"``.
    """
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(x, dtype=float)
    harmonics = tuple(harmonics)
    if not np.all(np.isfinite(x)):
        raise ConfigError("harmonic_amplitudes: the series has non-finite samples (flagged power)")
    if extra is None:
        pinv, span = _solver(t, f0_hz, harmonics)
        coef = pinv @ x
        extra_coef = np.zeros(0)
    else:
        design, span = _harmonic_basis(t, f0_hz, harmonics)
        e = np.asarray(extra, dtype=float).reshape(t.size, -1)
        # Unit-rms columns: a tiny template (W) would otherwise fall below lstsq's rank cut.
        scale = np.sqrt(np.mean(e * e, axis=0))
        scale = np.where(scale > 0, scale, 1.0)
        coef, *_ = np.linalg.lstsq(np.column_stack([design, e / scale]), x, rcond=None)
        extra_coef = coef[design.shape[1]:] / scale
    out: dict[Any, Any] = {"offset": coef[0], "trend": coef[1] / span, "extra": extra_coef}
    for k, h in enumerate(harmonics):
        a, b = coef[2 + 2 * k], coef[3 + 2 * k]
        out[h] = complex(a, -b)  # a cos + b sin = Re((a - i b) e^{i w t})
    return out


@dataclass(frozen=True)
class Nonlinearity:
    """Result of :func:`effective_nonlinearity` (SI: eps in 1/W)."""

    eps_per_w: float            # signed eps = f''/f' from the in-phase 4f line
    eps_quadrature_per_w: float  # the same from the quadrature part (0 for a memoryless f)
    leak_4f_w: float            # |4f amplitude| of P_rec - P
    gain_2f: float              # f' from the 2f line
    a2_true_w: float            # |2f amplitude| of the truth


def effective_nonlinearity(t_s, p_true_w, p_rec_w, f_hwp_hz: float) -> Nonlinearity:
    """``eps_eff = 4 a4 / (f' A^2)`` from a 2f_HWP signal (module docstring)."""
    truth = harmonic_amplitudes(t_s, p_true_w, f_hwp_hz)
    res = harmonic_amplitudes(t_s, np.asarray(p_rec_w) - np.asarray(p_true_w), f_hwp_hz)
    c2 = truth[2]
    amp = abs(c2)
    if amp == 0:
        raise ConfigError("effective_nonlinearity: the truth has no 2f signal")
    rot = np.conj(c2 / amp)  # e^{-i phi}
    gain = 1.0 + (res[2] * rot).real / amp
    c4 = res[4] * rot * rot
    return Nonlinearity(
        eps_per_w=4.0 * c4.real / (gain * amp * amp),
        eps_quadrature_per_w=4.0 * c4.imag / (gain * amp * amp),
        leak_4f_w=abs(res[4]),
        gain_2f=gain,
        a2_true_w=amp,
    )


def expected_linear_nonlinearity_per_w(p: DetectorParams) -> float:
    """``Re(I''/S)`` at the nominal operating point: what eps_eff of the linear conversion must be."""
    op = model.solve_operating_point(p, p.p_opt_w, p.t_bath_k, 0.0, p.v_thev_v)
    ss = model.small_signal(p, op.r_ohm)
    return float((ss.d2i_dp2_a_per_w2 / ss.di_dp_a_per_w).real)


def _fwhm(t, s):
    k = int(np.argmax(s))
    half = 0.5 * s[k]
    left = np.nonzero(s[:k] < half)[0]
    right = np.nonzero(s[k:] < half)[0]
    if not left.size or not right.size:
        return float("nan")
    i, j = left[-1], k + right[0]
    t_l = t[i] + (half - s[i]) * (t[i + 1] - t[i]) / (s[i + 1] - s[i])
    t_r = t[j - 1] + (half - s[j - 1]) * (t[j] - t[j - 1]) / (s[j] - s[j - 1])
    return float(t_r - t_l)


def source_distortion(t_s, p_true_w, p_rec_w, baseline) -> dict:
    """Peak and shape error of a compact-source crossing.

    Both curves are referred to their median over ``baseline`` (bool mask of
    samples away from the source). ``peak_frac_error`` compares the excess at
    the true peak; ``fwhm_frac_error`` the widths at half maximum;
    ``shape_rms_frac`` is the rms (within +-2 FWHM) of what is left after the
    best-fit rescaling of the true profile, relative to the peak.
    """
    t = np.asarray(t_s, dtype=float)
    s_true = np.asarray(p_true_w) - np.median(np.asarray(p_true_w)[baseline])
    s_rec = np.asarray(p_rec_w) - np.median(np.asarray(p_rec_w)[baseline])
    k = int(np.argmax(s_true))
    fw_true, fw_rec = _fwhm(t, s_true), _fwhm(t, s_rec)
    near = np.abs(t - t[k]) <= 2 * fw_true
    scale = float(s_rec[near] @ s_true[near] / (s_true[near] @ s_true[near]))
    return {
        "peak_w": float(s_true[k]),
        "peak_frac_error": float(s_rec[k] / s_true[k] - 1.0),
        "fwhm_frac_error": float(fw_rec / fw_true - 1.0),
        "shape_rms_frac": float(np.sqrt(np.mean((s_rec[near] - scale * s_true[near]) ** 2)) / s_true[k]),
    }


def template_gain(t_s, template_w, p_rec_w, f_hwp_hz: float) -> float:
    """Calibration gain: coefficient of ``template_w`` in ``p_rec_w``.

    Nuisances fitted alongside: offset, linear trend, harmonics 1-6 of f_HWP.
    """
    fit = harmonic_amplitudes(t_s, p_rec_w, f_hwp_hz, extra=np.asarray(template_w)[:, None])
    return float(fit["extra"][0])


def windowed_gain(t_s, p_true_w, p_rec_w, env, f_hwp_hz: float, window_s: float) -> dict:
    """Small-signal gain and offset per window against a slowly varying environment.

    In each window the 2f line of the reconstruction is compared with the
    truth's (``gain = Re(a2_rec / a2_true)``) and the mean of ``P_rec - P``
    is the offset. Slopes are least-squares lines against the window means
    of ``env``.

    Returns
    -------
    dict with arrays ``env``, ``gain``, ``offset_w`` and scalars
    ``gain_slope_per_unit``, ``offset_slope_w_per_unit``.
    """
    t = np.asarray(t_s, dtype=float)
    n_win = int((t[-1] - t[0]) // window_s)
    if n_win < 3:
        raise ConfigError("windowed_gain: need at least 3 windows")
    envs, gains, offsets = [], [], []
    for w in range(n_win):
        sel = (t >= t[0] + w * window_s) & (t < t[0] + (w + 1) * window_s)
        tr = harmonic_amplitudes(t[sel], np.asarray(p_true_w)[sel], f_hwp_hz, harmonics=(2, 4))
        rc = harmonic_amplitudes(t[sel], np.asarray(p_rec_w)[sel], f_hwp_hz, harmonics=(2, 4))
        envs.append(float(np.mean(np.asarray(env)[sel])))
        gains.append((rc[2] / tr[2]).real)
        offsets.append(float(np.mean(np.asarray(p_rec_w)[sel] - np.asarray(p_true_w)[sel])))
    envs, gains, offsets = np.array(envs), np.array(gains), np.array(offsets)
    return {
        "env": envs, "gain": gains, "offset_w": offsets,
        "gain_slope_per_unit": float(np.polyfit(envs, gains, 1)[0]),
        "offset_slope_w_per_unit": float(np.polyfit(envs, offsets, 1)[0]),
    }


def perturb_params(p: DetectorParams, errors: Mapping[str, float]) -> DetectorParams:
    """A copy of ``p`` with calibration errors applied (keys of :data:`CALIBRATION_ERRORS`).

    Absolute errors add, fractional ones scale (``x (1 + e)``); ``z_re_ohm`` /
    ``z_im_ohm`` shift the real / imaginary part of z, ``pickup_a_per_t`` and
    ``gain_a_per_count`` scale their magnitude, ``gain_phase_rad`` rotates the
    gain. A bias error changes ``v_thev_v``; where the bias comes from
    housekeeping, scale that too (:func:`run_study` does).

    Raises
    ------
    ConfigError
        Unknown key, or parameters that are no longer valid.
    """
    changes: dict[str, Any] = {}
    z = p.z_thev_ohm
    tr = p.transition
    for name, e in errors.items():
        if name not in CALIBRATION_ERRORS:
            raise ConfigError(f"unknown calibration error {name!r} (known: {sorted(CALIBRATION_ERRORS)})")
        e = float(e)
        if name == "t_c_k":
            changes["t_c_k"] = float(tr.t_c_k) + e
        elif name in ("r_n_ohm", "iqr_k"):
            changes[name] = float(getattr(tr, name)) * (1 + e)
        elif name == "z_re_ohm":
            z = complex(z.real + e, z.imag)
        elif name == "z_im_ohm":
            z = complex(z.real, z.imag + e)
        elif name == "n":
            changes["n"] = p.n + e
        elif name == "gain_phase_rad":
            changes["gain_a_per_count"] = changes.get("gain_a_per_count", p.gain_a_per_count) * complex(
                math.cos(e), math.sin(e))
        elif name == "gain_a_per_count":
            changes[name] = changes.get(name, p.gain_a_per_count) * (1 + e)
        else:
            changes[name] = getattr(p, name) * (1 + e)
    if z != p.z_thev_ohm:
        changes["z_thev_ohm"] = z
    return p.replace(**changes)


# --- converters ----------------------------------------------------------------------------

def default_converter_factory(kind: str, params: Mapping[str, DetectorParams]):
    """``core.convert.make_converter``; table kinds get a domain that holds Jupiter."""
    from mntes_stream.core.convert import make_converter

    if kind in ("table", "grid"):
        from mntes_stream.core.tables import TableDomain

        return make_converter(kind, params, domain=TableDomain(p_opt_w=(0.0, 1.6e-12)))
    return make_converter(kind, params)


def _convert(converter, block: SimBlock, ids, v_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Convert a block with the true environment (the bias reading scaled by ``v_scale``)."""
    from mntes_stream.core.convert import EnvironmentBlock

    env = EnvironmentBlock(t_bath_k=block.truth_t_bath_k, b_field_t=block.truth_b_field_t,
                           v_thev_v=block.truth_v_thev_v * v_scale)
    out = converter.convert(list(ids), block.counts_i, block.counts_q, env)
    return out.p_opt_w, out.flags


# --- the study -----------------------------------------------------------------------------

@dataclass(frozen=True)
class StudyConfig:
    """Scenario settings (SI). ``quick`` shortens runs and Monte-Carlo draws.

    The study detector is the paper's Table 1 TES, bias tuned to R = 0.7 R_n at
    0.5 pW, with the simulator's assumed magnetic coefficients
    (c1 = 2 K/T, c2 = 1e4 K/T^2, |m| = 0.2 nA/uT).
    """

    quick: bool = False
    sample_rate_hz: float = DFMUX_SAMPLE_RATE_HZ
    f_hwp_hz: float = HWP_FREQUENCIES_HZ["LFT"]
    # 2f amplitude for the nonlinearity measurement: small enough that higher orders
    # move the linear conversion's eps by only 0.4%, large enough to beat quantisation.
    hwp_2f_w: float = 20e-15
    nonlinearity_s: float = 120.0
    noisy_s: float = 600.0              # noisy run behind the spectra figure
    jupiter_peak_w: float = 0.8e-12
    jupiter_fwhm_s: float = 1.0
    jupiter_sweep_w: tuple = (0.05e-12, 0.1e-12, 0.2e-12, 0.4e-12, 0.6e-12, 0.8e-12)
    dipole_loading_offset_frac: float = 0.10  # sky loading vs the calibration point
    dipole_period_s: float = 60.0       # quasi-static: the time scale does not matter
    dipole_periods: int = 4
    dipole_hwp_2f_w: float = 10e-15
    drift_t_bath_span_k: float = 2e-3   # ramp 99 -> 101 mK
    drift_b_span_t: float = 100e-6      # ramp -50 -> +50 uT
    drift_s: float = 120.0
    drift_window_s: float = 10.0
    robustness_s: float = 20.0
    robustness_b_field_t: float = 50e-6  # static field, so B-coefficient errors matter
    robustness_draws: int = 200
    robustness_span: float = 1e3        # search errors from realistic/span to realistic*span
    mntes_kinds: tuple = ("table", "exact")
    baseline_kinds: tuple = ("linear", "electrical")
    seed: int = 0

    @classmethod
    def quick_config(cls, **changes: Any) -> StudyConfig:
        base = dict(quick=True, nonlinearity_s=60.0, noisy_s=120.0, dipole_periods=3, dipole_period_s=30.0,
                    drift_s=60.0, drift_window_s=5.0, robustness_draws=40,
                    jupiter_sweep_w=(0.1e-12, 0.4e-12, 0.8e-12))
        base.update(changes)
        return cls(**base)

    def sim_config(self, **changes: Any) -> SimConfig:
        """A noise-free single Table-1 detector with this study's settings."""
        base = dict(sample_rate_hz=self.sample_rate_hz, f_hwp_hz=self.f_hwp_hz, seed=self.seed,
                    t_c_shift_k_per_t=2.0, t_c_shift_k_per_t2=1.0e4, pickup_a_per_t=2.0e-4)
        base.update(changes)
        return SimConfig.noise_free(**base)


@dataclass
class StudyResult:
    """What :func:`run_study` measured: JSON-ready ``summary`` plus arrays for figures."""

    summary: dict
    figures: dict = field(default_factory=dict)


def _run(cfg: SimConfig, seconds: float) -> tuple[ArraySimulator, SimBlock, np.ndarray]:
    sim = ArraySimulator(cfg)
    n = int(round(seconds * cfg.sample_rate_hz))
    blk = sim.next_block(n)
    return sim, blk, np.arange(n) / cfg.sample_rate_hz


def _all_kinds(cfg: StudyConfig) -> tuple:
    return tuple(cfg.baseline_kinds) + tuple(cfg.mntes_kinds)


def run_study(cfg: StudyConfig | None = None, converter_factory: Callable | None = None,
              progress: Callable[[str], None] | None = None) -> StudyResult:
    """Simulate, convert with every kind, measure every effect (see module docstring).

    Parameters
    ----------
    cfg : StudyConfig
    converter_factory : callable(kind, params mapping) -> converter, optional
        Default :func:`default_converter_factory`.
    progress : callable(str), optional
        Called with the name of each step as it starts.
    """
    cfg = cfg or StudyConfig()
    factory = converter_factory or default_converter_factory
    note = progress or (lambda step: None)
    t_start = time.perf_counter()
    kinds = _all_kinds(cfg)
    mntes = cfg.mntes_kinds[0]
    per_kind: dict[str, dict] = {k: {} for k in kinds}
    figures: dict[str, Any] = {}
    converters: dict[tuple, Any] = {}

    def conv(kind, sim):
        key = (kind, sim.truth_params)
        if key not in converters:
            converters[key] = factory(kind, {p.detector_id: p for p in sim.truth_params})
        return converters[key]

    def reconstruct(sim, blk):
        out = {}
        for kind in kinds:
            p, flags = _convert(conv(kind, sim), blk, sim.detector_ids)
            out[kind] = (p[0], flags[0])
        return out

    # 1. HWP 2f -> 4f: effective nonlinearity (noise-free).
    note("hwp")
    sim, blk, t = _run(cfg.sim_config(hwp_2f_w=cfg.hwp_2f_w), cfg.nonlinearity_s)
    truth = blk.truth_p_opt_w[0]
    det = sim.truth_params[0]
    rec = reconstruct(sim, blk)
    for kind, (p, flags) in rec.items():
        nl = effective_nonlinearity(t, truth, p, cfg.f_hwp_hz)
        per_kind[kind].update(
            nonlinearity_per_pw=abs(nl.eps_per_w) * 1e-12, nonlinearity_signed_per_pw=nl.eps_per_w * 1e-12,
            nonlinearity_quadrature_per_pw=nl.eps_quadrature_per_w * 1e-12, leak_4f_w=nl.leak_4f_w,
            hwp_gain_error=nl.gain_2f - 1.0, flagged_samples=int(np.count_nonzero(flags)))
    span = t < 5.0
    figures["hwp"] = {"t_s": t[span], "truth_w": truth[span],
                      "residual_w": {k: rec[k][0][span] - truth[span] for k in kinds}}

    # Noisy version for spectra (photon white + 1/f, readout noise).
    note("spectra")
    sim_n, blk_n, t_n = _run(cfg.sim_config(hwp_2f_w=cfg.hwp_2f_w, nep_w_rthz=1e-17, f_knee_hz=0.02,
                                            nei_a_rthz=10e-12), cfg.noisy_s)
    rec_n = reconstruct(sim_n, blk_n)
    figures["spectra"] = {"fs_hz": cfg.sample_rate_hz, "f_hwp_hz": cfg.f_hwp_hz,
                          "truth_w": blk_n.truth_p_opt_w[0],
                          "rec_w": {k: rec_n[k][0] for k in kinds}}
    for kind in kinds:
        nl = effective_nonlinearity(t_n, blk_n.truth_p_opt_w[0], rec_n[kind][0], cfg.f_hwp_hz)
        per_kind[kind]["noisy_leak_4f_w"] = nl.leak_4f_w

    # 2. Jupiter crossing: peak and shape.
    note("jupiter")
    fwhm = cfg.jupiter_fwhm_s
    jup_cfg = dict(jupiter_fwhm_s=fwhm, jupiter_t_s=10.0 * fwhm, jupiter_period_s=0.0)
    sweep = {k: [] for k in kinds}
    for peak in sorted(set(cfg.jupiter_sweep_w) | {cfg.jupiter_peak_w}):
        sim_j, blk_j, t_j = _run(cfg.sim_config(jupiter_peak_w=peak, **jup_cfg), 20.0 * fwhm)
        rec_j = reconstruct(sim_j, blk_j)
        base = np.abs(t_j - 10.0 * fwhm) > 4.0 * fwhm
        for kind in kinds:
            d = source_distortion(t_j, blk_j.truth_p_opt_w[0], rec_j[kind][0], base)
            sweep[kind].append(d["peak_frac_error"])
            if peak == cfg.jupiter_peak_w:
                per_kind[kind].update(jupiter_peak_frac_error=d["peak_frac_error"],
                                      jupiter_fwhm_frac_error=d["fwhm_frac_error"],
                                      jupiter_shape_rms_frac=d["shape_rms_frac"],
                                      jupiter_flagged_samples=int(np.count_nonzero(rec_j[kind][1])))
                figures["jupiter"] = {"t_s": t_j, "truth_w": blk_j.truth_p_opt_w[0] - det.p_opt_w,
                                      "rec_w": {k: rec_j[k][0] - det.p_opt_w for k in kinds}}
    figures["jupiter_sweep"] = {"peak_w": sorted(set(cfg.jupiter_sweep_w) | {cfg.jupiter_peak_w}),
                                "peak_frac_error": sweep}

    # 3. Dipole calibration gain with the sky loading off the calibration point.
    note("dipole")
    sim_d, blk_d, t_d = _run(cfg.sim_config(dipole_k=3.36e-3, dipole_period_s=cfg.dipole_period_s,
                                            loading_offset_frac=cfg.dipole_loading_offset_frac,
                                            hwp_2f_w=cfg.dipole_hwp_2f_w, hwp_random_phase=False),
                             cfg.dipole_periods * cfg.dipole_period_s)
    template = sim_d.optical_components_w(t_d)["dipole"][0]
    rec_d = reconstruct(sim_d, blk_d)
    for kind in kinds:
        per_kind[kind]["dipole_gain_bias"] = template_gain(t_d, template, rec_d[kind][0], cfg.f_hwp_hz) - 1.0
    dipole_w = sim_d.dpdt_cmb_w_per_k * 3.36e-3

    # 4. Gain drift with bath temperature and magnetic field (2f signal as the probe).
    note("drift")
    drifts = {}
    for name, changes, env_of in (
        ("t_bath", dict(t_bath_offset_k=-cfg.drift_t_bath_span_k / 2,
                        t_bath_ramp_k_per_s=cfg.drift_t_bath_span_k / cfg.drift_s), "truth_t_bath_k"),
        ("b_field", dict(b_field_offset_t=-cfg.drift_b_span_t / 2,
                         b_field_ramp_t_per_s=cfg.drift_b_span_t / cfg.drift_s), "truth_b_field_t"),
    ):
        # Tuned at 100 mK and B = 0, then ramped through them: a drift, not a re-tune.
        sim_x, blk_x, t_x = _run(cfg.sim_config(hwp_2f_w=cfg.hwp_2f_w, **changes), cfg.drift_s)
        rec_x = reconstruct(sim_x, blk_x)
        drifts[name] = {}
        for kind in kinds:
            wg = windowed_gain(t_x, blk_x.truth_p_opt_w[0], rec_x[kind][0], getattr(blk_x, env_of),
                               cfg.f_hwp_hz, cfg.drift_window_s)
            drifts[name][kind] = wg
            if name == "t_bath":
                per_kind[kind].update(drift_gain_per_mk=wg["gain_slope_per_unit"] * 1e-3,
                                      drift_offset_w_per_mk=wg["offset_slope_w_per_unit"] * 1e-3)
            else:
                per_kind[kind].update(drift_gain_per_ut=wg["gain_slope_per_unit"] * 1e-6,
                                      drift_offset_w_per_ut=wg["offset_slope_w_per_unit"] * 1e-6)
    figures["drift"] = drifts

    # 5. Robustness to calibration errors (exact MNTES inverse with perturbed parameters).
    note("robustness")
    robustness, rob_fig = _robustness(cfg, factory)
    figures["robustness"] = rob_fig

    summary: dict[str, Any] = {
        "requirement_per_pw": REQUIREMENT_PER_PW,
        "mntes_kind": mntes,
        "expected_linear_nonlinearity_per_pw": abs(expected_linear_nonlinearity_per_w(det)) * 1e-12,
    }
    flat_names = {"leak_4f_w": "4f_leak_w"}
    for metric in ("nonlinearity_per_pw", "leak_4f_w", "jupiter_peak_frac_error", "dipole_gain_bias",
                   "drift_gain_per_mk", "drift_gain_per_ut", "drift_offset_w_per_mk", "drift_offset_w_per_ut",
                   "jupiter_fwhm_frac_error", "jupiter_shape_rms_frac", "hwp_gain_error"):
        name = flat_names.get(metric, metric)
        summary[f"linear_{name}"] = per_kind["linear"][metric] if "linear" in per_kind else None
        summary[f"mntes_{name}"] = per_kind[mntes][metric]
    summary["converters"] = per_kind
    summary["robustness"] = robustness
    summary["assumptions"] = {
        "detector": "paper Table 1, bias tuned to R = 0.7 R_n at 0.5 pW, T_bath = 100 mK, B = 0",
        "t_c_shift_k_per_t": 2.0, "t_c_shift_k_per_t2": 1.0e4, "pickup_abs_a_per_t": 2.0e-4,
        "gain_a_per_count": 1e-12,
        "environment_to_converters": "true environment at every sample (perfect housekeeping)",
        "hwp_2f_w": cfg.hwp_2f_w, "f_hwp_hz": cfg.f_hwp_hz, "sample_rate_hz": cfg.sample_rate_hz,
        "jupiter_peak_w": cfg.jupiter_peak_w, "jupiter_fwhm_s": cfg.jupiter_fwhm_s,
        "dipole": {"amplitude_k_cmb": 3.36e-3, "band_center_hz": 140e9, "fractional_bandwidth": 0.30,
                   "optical_efficiency": 0.5, "single_mode_single_polarisation": True,
                   "dpdt_w_per_k": sim_d.dpdt_cmb_w_per_k, "amplitude_w": dipole_w,
                   "sky_loading_offset_frac": cfg.dipole_loading_offset_frac,
                   "hwp_2f_w": cfg.dipole_hwp_2f_w},
        "drift": {"t_bath_k": [0.1 - cfg.drift_t_bath_span_k / 2, 0.1 + cfg.drift_t_bath_span_k / 2],
                  "b_field_t": [-cfg.drift_b_span_t / 2, cfg.drift_b_span_t / 2]},
        "noisy_run": {"nep_w_rthz": 1e-17, "f_knee_hz": 0.02, "nei_a_rthz": 10e-12, "seconds": cfg.noisy_s},
        "quick": cfg.quick,
    }
    summary["elapsed_s"] = time.perf_counter() - t_start
    return StudyResult(summary=summary, figures=figures)


# Median of |x| for x ~ N(0, 1).
_MEDIAN_ABS_NORMAL = 0.6744897501960817


def _by_source(rows: list, draws: np.ndarray, sigmas: np.ndarray, eps_of, median_all: float) -> list:
    """The all-together median broken down by calibration error source.

    ``variance_share``: for small errors the nonlinearity is about linear in
    them, ``eps ~ |sum_k a_k e_k|``, so source k carries ``a_k^2 / sum a^2`` of
    its variance (``a_k``: the one-at-a-time nonlinearity at the realistic
    error). ``median_without_per_pw``: the same draws with source k's error
    set to zero (measured, no linearity assumed); ``median_drop_frac`` what
    removing that source alone buys.
    """
    a2 = np.array([r["nonlinearity_at_realistic_per_pw"] ** 2 for r in rows])
    total = float(a2.sum()) or 1.0
    out = []
    for k, r in enumerate(rows):
        keep = np.ones(len(sigmas))
        keep[k] = 0.0
        eps = np.array([eps_of(dict(zip(CALIBRATION_ERRORS, keep * sigmas * d)))[0] for d in draws])
        med = float(np.median(np.where(np.isfinite(eps), eps, np.inf)))
        out.append({"parameter": r["parameter"], "label": r["label"], "variance_share": float(a2[k] / total),
                    "median_without_per_pw": med,
                    "median_drop_frac": 1.0 - med / median_all if median_all > 0 else 0.0})
    return sorted(out, key=lambda e: -e["variance_share"])


def _robustness(cfg: StudyConfig, factory) -> tuple[dict, dict]:
    sim, blk, t = _run(cfg.sim_config(hwp_2f_w=cfg.hwp_2f_w, b_field_offset_t=cfg.robustness_b_field_t),
                       cfg.robustness_s)
    truth = blk.truth_p_opt_w[0]
    det = sim.truth_params[0]

    def eps_of(errors: Mapping[str, float]) -> tuple[float, float]:
        try:
            q = perturb_params(det, errors)
            # The converter takes the bias from housekeeping: its calibration error is there.
            p, _ = _convert(factory("exact", {q.detector_id: q}), blk, sim.detector_ids,
                            v_scale=q.v_thev_v / det.v_thev_v)
            nl = effective_nonlinearity(t, truth, p[0], cfg.f_hwp_hz)
        except ConfigError:
            return math.inf, math.nan
        return abs(nl.eps_per_w) * 1e-12, nl.gain_2f - 1.0

    rows = []
    curves = {}
    grid_mult = np.geomspace(1.0 / cfg.robustness_span, cfg.robustness_span, 13)
    for name, (label, sigma, mode, unit) in CALIBRATION_ERRORS.items():
        def worst(e):
            return max(eps_of({name: e})[0], eps_of({name: -e})[0])

        eps_real = worst(sigma)
        curve = np.array([worst(m * sigma) for m in grid_mult])
        curves[name] = curve
        ok = curve <= REQUIREMENT_PER_PW
        if ok.all():
            largest, bound = float(grid_mult[-1] * sigma), "above"
        elif not ok[0]:
            largest, bound = float(grid_mult[0] * sigma), "below"
        else:
            first_bad = int(np.argmin(ok))
            lo, hi = math.log(grid_mult[first_bad - 1] * sigma), math.log(grid_mult[first_bad] * sigma)
            for _ in range(10):
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if worst(math.exp(mid)) <= REQUIREMENT_PER_PW else (lo, mid)
            largest, bound = math.exp(lo), "exact"
        rows.append({"parameter": name, "label": label, "mode": mode, "unit": unit, "realistic_error": sigma,
                     "nonlinearity_at_realistic_per_pw": eps_real,
                     "gain_error_at_realistic": max(abs(eps_of({name: sigma})[1]), abs(eps_of({name: -sigma})[1])),
                     "largest_error_meeting_requirement": largest, "bound": bound,
                     "margin": largest / sigma})
    rng = np.random.default_rng([cfg.seed, 7])
    draws = rng.standard_normal((cfg.robustness_draws, len(CALIBRATION_ERRORS)))
    sigmas = np.array([v[1] for v in CALIBRATION_ERRORS.values()])

    def together(scale):
        return np.array([eps_of(dict(zip(CALIBRATION_ERRORS, scale * sigmas * d)))[0] for d in draws])

    eps_all = together(1.0)
    finite = np.where(np.isfinite(eps_all), eps_all, np.inf)
    # Largest common scale of all realistic errors at which 95% of draws meet the
    # requirement: secant steps in log-log (eps grows about linearly with the errors).
    p95 = lambda s: float(np.percentile(together(s), 95))  # noqa: E731
    s0, e0 = 1.0, float(np.percentile(finite, 95))
    s1 = s0 * REQUIREMENT_PER_PW / e0
    e1 = p95(s1)
    for _ in range(4):
        if abs(e1 / REQUIREMENT_PER_PW - 1) < 0.02 or not np.isfinite(e1) or e1 == e0:
            break
        slope = math.log(e1 / e0) / math.log(s1 / s0)
        s0, e0 = s1, e1
        s1 = s1 * (REQUIREMENT_PER_PW / e1) ** (1.0 / max(slope, 0.2))
        e1 = p95(s1)
    scale95 = s1
    by_source = _by_source(rows, draws, sigmas, eps_of, float(np.median(finite)))
    all_together = {
        "draws": int(cfg.robustness_draws),
        "median_per_pw": float(np.median(finite)),
        "p95_per_pw": float(np.percentile(finite, 95)),
        "max_per_pw": float(np.max(finite)),
        "fraction_meeting_requirement": float(np.mean(finite <= REQUIREMENT_PER_PW)),
        "largest_scale_p95_meeting_requirement": scale95,
        # Which measurement to improve first (largest share first).
        "by_source": by_source,
        "linear_prediction_median_per_pw": _MEDIAN_ABS_NORMAL * math.sqrt(
            sum(r["nonlinearity_at_realistic_per_pw"] ** 2 for r in rows)),
    }
    return ({"one_at_a_time": rows, "all_together": all_together,
             "b_field_t": cfg.robustness_b_field_t, "hwp_2f_w": cfg.hwp_2f_w},
            {"multiples": grid_mult, "curves": curves, "all_together": finite})
