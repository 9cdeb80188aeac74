"""Per-detector fit of the MNTES parameters to the six calibration measurements.

Strategy: closed-form starting values, one stage per measurement (each stage
uses what the earlier ones fixed), then ONE joint weighted least-squares fit
of all parameters to all points (``scipy.optimize.least_squares``), so that
every parameter gets its information from every measurement that constrains
it and the covariance carries the correlations.

Which measurement constrains what (the staged start makes this explicit):

==========================  ==============================================================
superconducting network     gain phase; z0 and the resonator (L, ESR slope), in units of V0
normal network              R_n (in units of V0)
R(T) at probe bias          transition shape (T_c0, IQR) given K, n; self-heating included
optical response            V0: absolute watts vs the Joule power seen in counts (the
                            overall normalisation); curvature of the response
I-V curves at several T_b   K, n, T_c0 (saturation power against bath temperature)
field sweeps                c1, c2 (at the operating bias); pickup m (at a high bias,
                            where the TES is normal and barely responds to B)
==========================  ==============================================================

The magnitude of the gain ``|g|`` is the one number the six measurements in
counts cannot fix (an exact scale symmetry, see ``DetectorCalibration``); it is
taken from the campaign header, and conversion to watts does not depend on it.

Uncertainties: residuals are weighted by the known noise, so the covariance is
``(J^T J)^-1`` without rescaling by chi2/ndf; a chi2 far from ndf is flagged
instead (it means the noise or the model is wrong, and rescaling would hide it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.interpolate import make_smoothing_spline
from scipy.optimize import least_squares

from mntes_stream.core.calib.forward import (
    N_PARAMS,
    PARAM_NAMES,
    Design,
    Readout,
    params_from_theta,
    predict_counts,
    z_of_omega,
)
from mntes_stream.core.calib.measurements import KINDS, DetectorCalibration, Sweep
from mntes_stream.core.model import SQRT2
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.transition import TabulatedTransition
from mntes_stream.errors import ConfigError, MntesError

__all__ = ["FitOptions", "DetectorFit", "fit_detector", "initial_guess", "tabulated_transition", "prepare"]

_IX = {name: k for k, name in enumerate(PARAM_NAMES)}


@dataclass(frozen=True)
class FitOptions:
    """Fit and quality-check settings.

    Attributes
    ----------
    min_points : int
        A sweep with fewer usable points is left out (and noted).
    required : tuple of str
        Measurement kinds without which a detector is not fitted.
    chi2_z_max : float
        Flag when ``(chi2 - ndf) / sqrt(2 ndf)`` exceeds this (overall, or per sweep).
    cond_max : float
        Flag when the Jacobian's condition number exceeds this (degenerate parameters).
    max_nfev : int
    """

    min_points: int = 5
    required: tuple = KINDS
    chi2_z_max: float = 5.0
    cond_max: float = 1e12
    max_nfev: int = 200


@dataclass(frozen=True, eq=False)
class DetectorFit:
    """Outcome of one detector's fit.

    ``status`` is ``"ok"`` (params usable), ``"flagged"`` (fit ran, quality
    checks failed: ``reasons`` say which) or ``"failed"`` (no parameters).
    ``theta``/``cov`` follow :data:`PARAM_NAMES`; ``sweep_chi2`` holds
    ``(kind, n_points, chi2)`` per sweep used (chi2 over 2 n_points residuals).
    """

    detector_id: str
    status: str
    reasons: tuple = ()
    notes: tuple = ()
    theta: np.ndarray | None = None
    cov: np.ndarray | None = None
    chi2: float = math.nan
    ndf: int = 0
    nfev: int = 0
    sweep_chi2: tuple = ()
    params: DetectorParams | None = None
    readout: Readout | None = None
    used_sweeps: tuple = field(default=())

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    @property
    def sigma(self) -> np.ndarray | None:
        return None if self.cov is None else np.sqrt(np.maximum(np.diag(self.cov), 0.0))

    def value(self, name: str) -> float:
        return float(self.theta[_IX[name]])

    def error(self, name: str) -> float:
        return float(self.sigma[_IX[name]])


# --------------------------------------------------------------------------- input cleaning


def prepare(det: DetectorCalibration, options: FitOptions = FitOptions()) -> tuple[tuple[Sweep, ...], list[str], list[str]]:
    """Usable sweeps, notes (dropped points/sweeps) and blocking problems."""
    notes, problems, usable = [], [], []
    for k, s in enumerate(det.sweeps):
        ok = s.finite_mask()
        if not np.all(ok):
            notes.append(f"{s.kind} sweep {k}: dropped {int((~ok).sum())} of {len(s)} non-finite/invalid points")
            s = s.select(ok)
        if len(s) < options.min_points:
            notes.append(f"{s.kind} sweep {k}: too few usable points ({len(s)} < {options.min_points}), not used")
            continue
        usable.append(s)
    kinds = {s.kind for s in usable}
    missing = [k for k in options.required if k not in kinds]
    if missing:
        problems.append("missing measurement(s): " + ", ".join(missing))
    return tuple(usable), notes, problems


# --------------------------------------------------------------------------- starting values


def _cat(sweeps, fn):
    return np.concatenate([fn(s) for s in sweeps]) if sweeps else np.array([])


def initial_guess(det: DetectorCalibration, sweeps: tuple[Sweep, ...]) -> np.ndarray:
    """Starting parameter vector from closed-form stages (see module docstring).

    Raises ConfigError when the data cannot give a start (e.g. no transition seen).
    """
    by = {k: [s for s in sweeps if s.kind == k] for k in KINDS}
    g_abs, f0 = det.gain_abs_a_per_count, det.bias_freq_hz
    omega0 = 2 * np.pi * f0
    # 1. Superconducting network: sqrt(2) bias_ratio / (|g| counts) = exp(1j phi) z(omega) / V0.
    #    Over the narrow band z is linear in delta = w - 1: z0 + (r1 + 1j (2 L omega0 - Im z0)) delta.
    zeta = _cat(by["network_super"], lambda s: _zeta_rot(s, g_abs, 0.0, 0j))
    delta = _cat(by["network_super"], lambda s: s.condition("freq_hz") / f0 - 1.0)
    a, *_ = np.linalg.lstsq(np.stack([np.ones_like(delta), delta], axis=1).astype(complex), zeta, rcond=None)
    phi = float(np.angle(a[1])) - np.pi / 2
    rot = np.exp(-1j * phi)
    z0_v = a[0] * rot                      # z0 / V0
    x1_v = float((a[1] * rot).imag)        # (2 L omega0 - Im z0) / V0
    l_v = (x1_v + z0_v.imag) / (2 * omega0)

    def r_over_v(s: Sweep, pickup=0j) -> np.ndarray:
        """R / V0 per point (pickup in A/T removed from the current)."""
        z_v = z_of_omega(z0_v, l_v, 0.0, f0, s.condition("freq_hz"))
        return (_zeta_rot(s, g_abs, phi, pickup) - z_v).real

    # 2. Optical response: P + V0 J~ = K (T^n - T_b^n), with T pinned near T_c by the
    #    electrothermal feedback, so the slope of P against J~ is -V0.
    opt = by["optical_response"]
    p_opt = _cat(opt, lambda s: s.condition("p_opt_w"))
    j_v = _cat(opt, lambda s: _joule_over_v(s, r_over_v(s), z0_v, l_v, f0))
    slope = np.polyfit(j_v, p_opt, 1)[0]
    v0 = -float(slope)
    if not (v0 > 0 and np.isfinite(v0)):
        raise ConfigError("optical response shows no electrothermal response (cannot fix the power scale)")
    # 3. Normal network: R_n / V0.
    rn_v = float(np.median(_cat(by["network_normal"], r_over_v)))
    if not rn_v > abs(z0_v):
        raise ConfigError(f"normal network analysis gives R_n = {rn_v * v0:.3g} Ohm <= |z0|")
    # 4. Transition and thermal parameters from the explicit power balance at every
    #    in-transition point (I-V, optical, R(T); B = 0):
    #    P + V0 J~ = K (T_s(R/R_n)^n - T_b^n), where R/R_n and J~ = J/V0 do not depend on V0.
    pts = [s for k in ("iv_curve", "optical_response", "impedance_temperature") for s in by[k]]
    r_v = _cat(pts, r_over_v)
    frac = r_v / rn_v
    j_v = _cat(pts, lambda s: _joule_over_v(s, r_over_v(s), z0_v, l_v, f0))
    p_in = _cat(pts, lambda s: s.condition("p_opt_w"))
    t_b = _cat(pts, lambda s: s.condition("t_bath_k"))
    sel = (frac > 0.05) & (frac < 0.95) & np.isfinite(j_v)
    if sel.sum() < 6:
        raise ConfigError("too few points inside the transition to start the fit")
    frac, j_v, p_in, t_b = frac[sel], j_v[sel], p_in[sel], t_b[sel]
    tan = np.tan(np.pi * (frac - 0.5))
    p_tot = p_in + v0 * j_v
    mid = np.abs(frac - 0.5) < 0.3
    best = None
    for n in np.linspace(2.0, 6.0, 41):  # linear in (K T_c^n, K) at fixed n, with T = T_c
        a_mat = np.stack([np.ones(mid.sum()), -t_b[mid] ** n], axis=1)
        coef, *_ = np.linalg.lstsq(a_mat, p_tot[mid], rcond=None)
        rss = float(np.sum((a_mat @ coef - p_tot[mid]) ** 2))
        if coef[1] > 0 and coef[0] > 0 and (best is None or rss < best[0]):
            best = (rss, n, coef[1], (coef[0] / coef[1]) ** (1.0 / n))
    if best is None:
        raise ConfigError("cannot start the thermal fit (no positive K)")
    _, n0, k0, t_c0 = best

    def resid(x):
        v, t_c, log_iqr, log_k, n = x
        t = np.maximum(t_c + 0.5 * np.exp(log_iqr) * tan, 1e-6)
        return (p_in + v * v0 * j_v - np.exp(log_k) * (t**n - t_b**n)) / (k0 * t_c0**n0)

    sol = least_squares(resid, [1.0, t_c0, np.log(1e-3 * t_c0 / 0.18 + 1e-5), np.log(k0), n0])
    v0 *= sol.x[0]
    t_c, iqr, k, n = sol.x[1], float(np.exp(sol.x[2])), float(np.exp(sol.x[3])), sol.x[4]
    z0, l_h, r_n = z0_v * v0, l_v * v0, rn_v * v0
    # 5. Pickup from the most-normal field sweep, then c1, c2 from the others.
    fields = by["field_sensitivity"]
    pickup, c1, c2 = 0j, 0.0, 0.0
    if fields:
        frac_f = [float(np.median(r_over_v(s) * v0)) / r_n for s in fields]
        hi = fields[int(np.argmax(frac_f))]
        b = hi.condition("b_field_t")
        i_a = hi.counts * g_abs * np.exp(1j * phi)
        coef = np.polyfit(b, i_a, 2)
        pickup = complex(coef[1])
        bb, dt = [], []
        for s, fr in zip(fields, frac_f):
            if not 0.1 < fr < 0.9:
                continue
            rr = r_over_v(s, pickup) * v0
            vv = s.condition("bias_ratio") * v0
            pt = s.condition("p_opt_w") + vv**2 * rr / np.abs(rr + z0) ** 2
            t = (s.condition("t_bath_k") ** n + pt / k) ** (1.0 / n)
            ts = t_c + 0.5 * iqr * np.tan(np.pi * (rr / r_n - 0.5))
            bb.append(s.condition("b_field_t"))
            dt.append(t - ts)
        if bb:
            c2, c1, _ = np.polyfit(np.concatenate(bb), np.concatenate(dt), 2)
    theta = np.zeros(N_PARAMS)
    for name, value in (
        ("t_c_k", t_c), ("iqr_k", iqr), ("r_n_ohm", r_n), ("k_w_per_k_n", k), ("n", n), ("v_thev_v", v0),
        ("z_re_ohm", max(z0.real, 1e-6 * r_n)), ("z_im_ohm", z0.imag), ("l_series_h", l_h), ("r_slope_ohm", 0.0),
        ("t_c_shift_k_per_t", c1), ("t_c_shift_k_per_t2", c2),
        ("pickup_re_a_per_t", pickup.real), ("pickup_im_a_per_t", pickup.imag), ("gain_phase_rad", phi),
    ):
        theta[_IX[name]] = float(value)
    if not np.all(np.isfinite(theta)):
        raise ConfigError("starting values are not finite")
    return theta


def _zeta_rot(s: Sweep, g_abs: float, phi: float, pickup) -> np.ndarray:
    """``sqrt(2) bias_ratio / i``, i = counts |g| exp(1j phi) - m B: ``(R + z) / V0`` at the right phi."""
    i = s.counts * g_abs * np.exp(1j * phi)
    return SQRT2 * s.condition("bias_ratio") / (i - pickup * s.condition("b_field_t"))


def _joule_over_v(s: Sweep, r_v, z0_v, l_v, f0):
    z_v = z_of_omega(z0_v, l_v, 0.0, f0, s.condition("freq_hz"))
    return s.condition("bias_ratio") ** 2 * r_v / np.abs(r_v + z_v) ** 2


# --------------------------------------------------------------------------- joint fit


def _scales_and_bounds(theta0: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Typical magnitude of each parameter (fit variables are theta / scale) and bounds on theta."""
    t = dict(zip(PARAM_NAMES, theta0))
    z_abs = math.hypot(t["z_re_ohm"], t["z_im_ohm"])
    scale = {
        "t_c_k": t["iqr_k"], "iqr_k": t["iqr_k"], "r_n_ohm": t["r_n_ohm"], "k_w_per_k_n": t["k_w_per_k_n"],
        "n": 0.1, "v_thev_v": t["v_thev_v"], "z_re_ohm": z_abs, "z_im_ohm": z_abs,
        "l_series_h": t["l_series_h"], "r_slope_ohm": 0.1 * t["r_n_ohm"], "t_c_shift_k_per_t": 1.0,
        "t_c_shift_k_per_t2": 1e3, "pickup_re_a_per_t": 1e-4, "pickup_im_a_per_t": 1e-4, "gain_phase_rad": 0.01,
    }
    inf = np.inf
    bounds = {
        "t_c_k": (0.5 * t["t_c_k"], 2.0 * t["t_c_k"]), "iqr_k": (1e-3 * t["iqr_k"], 1e2 * t["iqr_k"]),
        "r_n_ohm": (0.1 * t["r_n_ohm"], 10 * t["r_n_ohm"]), "k_w_per_k_n": (1e-2 * t["k_w_per_k_n"], 1e2 * t["k_w_per_k_n"]),
        "n": (1.05, 10.0), "v_thev_v": (0.1 * t["v_thev_v"], 10 * t["v_thev_v"]), "z_re_ohm": (0.0, inf),
        "l_series_h": (0.0, inf),
    }
    s = np.array([scale[k] for k in PARAM_NAMES], dtype=float)
    lo = np.array([bounds.get(k, (-inf, inf))[0] for k in PARAM_NAMES], dtype=float)
    hi = np.array([bounds.get(k, (-inf, inf))[1] for k in PARAM_NAMES], dtype=float)
    return s, lo, hi


class _Problem:
    """Weighted residuals and a finite-difference Jacobian evaluated in one vectorised model call."""

    def __init__(self, design: Design, theta0: np.ndarray, scale: np.ndarray, lo: np.ndarray, hi: np.ndarray):
        self.design, self.theta0, self.scale = design, theta0, scale
        self.u_lo, self.u_hi = (lo - theta0) / scale, (hi - theta0) / scale
        self.weight = 1.0 / design.sigma_counts

    def theta(self, u: np.ndarray) -> np.ndarray:
        return self.theta0 + self.scale * np.asarray(u)

    def _resid(self, model: np.ndarray) -> np.ndarray:
        d = (model - self.design.counts) * self.weight
        return np.concatenate([d.real, d.imag], axis=-1)

    def fun(self, u: np.ndarray) -> np.ndarray:
        return self._resid(predict_counts(self.theta(u), self.design))

    def jac(self, u: np.ndarray, central: bool = False, h: float = 1e-6) -> np.ndarray:
        u = np.asarray(u, dtype=float)
        eye = np.eye(u.size)
        step = np.where(u + h <= self.u_hi, h, -h)  # stay inside the bounds
        if central:
            sets = np.concatenate([u + step[:, None] * eye, u - step[:, None] * eye])
            r = self._resid(predict_counts(self.theta(sets), self.design))
            return ((r[: u.size] - r[u.size:]) / (2 * step[:, None])).T
        sets = np.concatenate([u[None, :], u + step[:, None] * eye])
        r = self._resid(predict_counts(self.theta(sets), self.design))
        return ((r[1:] - r[0]) / step[:, None]).T


def fit_detector(det: DetectorCalibration, options: FitOptions = FitOptions()) -> DetectorFit:
    """Fit one detector; never raises on bad data (returns a ``failed``/``flagged`` result).

    Returns
    -------
    DetectorFit
    """
    sweeps, notes, problems = prepare(det, options)
    if problems:
        return DetectorFit(det.detector_id, "failed", tuple(problems), tuple(notes))
    try:
        theta0 = initial_guess(det, sweeps)
    except (MntesError, ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        return DetectorFit(det.detector_id, "failed", (f"no starting values: {exc}",), tuple(notes))
    design = Design.from_detector(det, sweeps)
    scale, lo, hi = _scales_and_bounds(theta0)
    prob = _Problem(design, theta0, scale, lo, hi)
    try:
        with np.errstate(all="ignore"):
            sol = least_squares(
                prob.fun, np.zeros(N_PARAMS), jac=prob.jac, bounds=(prob.u_lo, prob.u_hi), method="trf",
                x_scale="jac", xtol=1e-10, ftol=1e-10, gtol=1e-10, max_nfev=options.max_nfev,
            )
        jac = prob.jac(sol.x, central=True)
        resid = prob.fun(sol.x)
    except (MntesError, ValueError, FloatingPointError, np.linalg.LinAlgError) as exc:
        return DetectorFit(det.detector_id, "failed", (f"fit failed: {type(exc).__name__}: {exc}",), tuple(notes))
    theta = prob.theta(sol.x)
    theta[_IX["gain_phase_rad"]] = float(np.angle(np.exp(1j * theta[_IX["gain_phase_rad"]])))
    reasons = []
    if not np.all(np.isfinite(resid)) or not np.all(np.isfinite(jac)):
        return DetectorFit(det.detector_id, "failed", ("model not finite at the solution",), tuple(notes))
    # Covariance of theta = S (J^T J)^-1 S, via the SVD of J (in scaled variables).
    _, sv, vt = np.linalg.svd(jac, full_matrices=False)
    cond = float(sv[0] / sv[-1]) if sv[-1] > 0 else math.inf
    cov_u = (vt.T / np.where(sv > 0, sv, np.inf) ** 2) @ vt
    cov = cov_u * np.outer(scale, scale)
    chi2 = float(resid @ resid)
    ndf = resid.size - N_PARAMS
    # Per-sweep chi2, in the order of ``sweeps``.
    n_pts = len(design)
    per_point = resid[:n_pts] ** 2 + resid[n_pts:] ** 2
    sweep_chi2 = tuple(
        (s.kind, len(s), float(per_point[design.sweep_index == k].sum())) for k, s in enumerate(sweeps)
    )
    if sol.status <= 0:
        reasons.append(f"did not converge: {sol.message}")
    z_all = (chi2 - ndf) / math.sqrt(2 * ndf) if ndf > 0 else math.inf
    if z_all > options.chi2_z_max:
        reasons.append(f"poor fit: chi2/ndf = {chi2 / max(ndf, 1):.3g} (ndf {ndf})")
    for k, (kind, n, c2) in enumerate(sweep_chi2):
        z_k = (c2 - 2 * n) / math.sqrt(4 * n)
        if z_k > options.chi2_z_max:
            reasons.append(f"poor fit in {kind} sweep {k}: chi2/point = {c2 / (2 * n):.3g}")
    at_bound = [PARAM_NAMES[k] for k in range(N_PARAMS)
                if np.isfinite(lo[k]) and abs(theta[k] - lo[k]) <= 1e-6 * scale[k]
                or np.isfinite(hi[k]) and abs(theta[k] - hi[k]) <= 1e-6 * scale[k]]
    if at_bound:
        reasons.append("parameter(s) at a bound: " + ", ".join(at_bound))
    if cond > options.cond_max:
        reasons.append(f"degenerate parameters (Jacobian condition number {cond:.2g})")
    params = readout = None
    try:
        params, readout = params_from_theta(theta, det)
    except ConfigError as exc:
        reasons.append(f"unphysical parameters: {exc}")
    status = "flagged" if reasons else "ok"
    return DetectorFit(
        det.detector_id, status, tuple(reasons), tuple(notes), theta, cov, chi2, ndf, int(sol.nfev),
        sweep_chi2, params, readout, tuple(sweeps),
    )


# --------------------------------------------------------------------------- tabulated outcome


def transition_points(fit: DetectorFit) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(T_s, R, sigma_R)`` of every R(T) point, through the fitted readout and power balance.

    R comes straight from the counts (``R = Re(sqrt(2) V / i - z)``); the TES
    temperature from the explicit power balance with the probe's Joule power
    and the optical load (the self-heating), then the field shift removed.
    """
    if fit.params is None:
        raise ConfigError(f"{fit.detector_id}: no fitted parameters")
    p, ro = fit.params, fit.readout
    t_out, r_out, s_out = [], [], []
    for s in fit.used_sweeps:
        if s.kind != "impedance_temperature":
            continue
        b = s.condition("b_field_t")
        v = s.condition("bias_ratio") * p.v_thev_v
        z = z_of_omega(p.z_thev_ohm, ro.l_series_h, ro.r_slope_ohm, ro.bias_freq_hz, s.condition("freq_hz"))
        i = s.counts * p.gain_a_per_count - p.pickup_a_per_t * b
        r = (SQRT2 * v / i - z).real
        p_tot = s.condition("p_opt_w") + v**2 * r / np.abs(r + z) ** 2
        t = (s.condition("t_bath_k") ** p.n + p_tot / p.k_w_per_k_n) ** (1.0 / p.n)
        t_out.append(t - p.t_c_shift_k_per_t * b - p.t_c_shift_k_per_t2 * b**2)
        r_out.append(r)
        s_out.append(np.abs(SQRT2 * v / i**2) * np.abs(p.gain_a_per_count) * s.sigma_counts)
    if not t_out:
        raise ConfigError(f"{fit.detector_id}: no R(T) measurement")
    t, r, sig = (np.concatenate(x) for x in (t_out, r_out, s_out))
    order = np.argsort(t)
    return t[order], r[order], sig[order]


def tabulated_transition(fit: DetectorFit, n_table: int = 400) -> TabulatedTransition:
    """A tabulated transition built from the R(T) measurement of a fitted detector.

    ``R(T) = R_arctan(T) + Delta(T)``: the fitted arctan plus a cubic smoothing
    spline through the measured residuals ``R_j - R_arctan(T_j)`` (weights
    1/sigma_R^2, strength by generalised cross-validation), tabulated on
    ``n_table`` temperatures across the measured span. Where the arctan
    describes the data the correction is smoothed to ~0 and the table inherits
    the arctan's well-determined curvature; where it does not, the correction
    follows the data. (A spline through the R(T) points alone, with no model
    to shrink towards, leaves noise in the curvature, which is exactly what the
    nonlinearity depends on: |eps_eff| up to ~0.03 pW^-1 at the simulated noise.)
    Outside the measured span the transition is undefined and conversion flags it.
    """
    t, r, sig = transition_points(fit)
    keep = np.concatenate([[True], np.diff(t) > 0])
    t, r, sig = t[keep], r[keep], sig[keep]
    if t.size < 5:
        raise ConfigError(f"{fit.detector_id}: too few R(T) points to tabulate the transition")
    arctan = fit.params.transition
    correction = make_smoothing_spline(t, r - arctan.resistance_ohm(t), w=1.0 / sig**2)
    grid = np.linspace(t[0], t[-1], n_table)
    r_grid = np.maximum.accumulate(arctan.resistance_ohm(grid) + correction(grid))
    rising = np.concatenate([[True], np.diff(r_grid) > 0]) & (r_grid >= 0)
    return TabulatedTransition(t_k=tuple(float(x) for x in grid[rising]),
                               r_ohm=tuple(float(x) for x in r_grid[rising]))
