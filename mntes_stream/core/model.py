"""The MNTES TES model: power balance, forward solve, exact inverse, small signal.

Power balance (paper eq. 1), with V the RMS Thevenin voltage and z the
Thevenin impedance::

    P_opt + V^2 R / |R + z|^2 = K (T^n - T_bath^n)

The readout reports the peak current ``i = sqrt(2) V / (R + z)`` plus a
magnetic pickup ``m B``. Parameters ``p`` are a :class:`DetectorParams`
(scalars) or a :class:`ParamArray` (columns of shape ``(n_det, 1)``); every
function broadcasts parameters against its sample arrays.

The forward solve is parameterised by R (not T): on the stable branch
``R > |z|`` the power-balance residual is strictly decreasing in R, so a
bracket ``(max(|z|, R_min), R_max)`` holds exactly one root, and the
transition enters only through ``T_s(R)``, the direction every model provides.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mntes_stream.core.solve import bracketed_root
from mntes_stream.errors import ConfigError

__all__ = [
    "SQRT2",
    "STATE_TRANSITION",
    "STATE_SUPERCONDUCTING",
    "STATE_NORMAL",
    "OperatingPoint",
    "Inversion",
    "SmallSignal",
    "effective_temperature_k",
    "tes_current_a",
    "joule_power_w",
    "solve_operating_point",
    "readout_current_a",
    "invert_current",
    "power_of_resistance_w",
    "branch_bounds_ohm",
    "LOOP_GAIN_NORMAL",
    "saturation_resistance_ohm",
    "small_signal",
    "tune_bias_v",
]

SQRT2 = float(np.sqrt(2.0))
STATE_TRANSITION = 0
STATE_SUPERCONDUCTING = 1
STATE_NORMAL = 2

# Keep the solve off the exact ends of the transition, where T_s diverges.
_EDGE_FRAC = 1e-12


@dataclass(frozen=True)
class OperatingPoint:
    """Equilibrium of the power balance; arrays share the broadcast shape S.

    Attributes
    ----------
    r_ohm, t_k : ndarray, shape S
    i_a : ndarray of complex, shape S
        TES current, peak amplitude (no pickup).
    state : ndarray of int8, shape S
        ``STATE_TRANSITION``, ``STATE_SUPERCONDUCTING`` (latched below the
        stable branch; R is the bottom of the transition) or ``STATE_NORMAL``.
    """

    r_ohm: np.ndarray
    t_k: np.ndarray
    i_a: np.ndarray
    state: np.ndarray


@dataclass(frozen=True)
class Inversion:
    """Result of the exact inverse; arrays of shape S.

    ``p_opt_w`` is NaN wherever ``state`` is not ``STATE_TRANSITION``.
    ``x_residual_ohm`` is ``Im(sqrt(2) V / i - z)``: zero for a consistent
    measurement, non-zero for a wrong phase, gain or pickup.
    """

    p_opt_w: np.ndarray
    r_ohm: np.ndarray
    t_k: np.ndarray
    state: np.ndarray
    x_residual_ohm: np.ndarray


@dataclass(frozen=True)
class SmallSignal:
    """Linear response at an operating point (arrays of shape S).

    ``responsivity_a_per_w`` is paper eq. 3 (complex, peak current);
    ``di_dp_a_per_w`` and ``d2i_dp2_a_per_w2`` are exact implicit derivatives of
    the power balance along the response curve.
    """

    alpha: np.ndarray
    beta: np.ndarray
    loop_gain: np.ndarray
    responsivity_a_per_w: np.ndarray
    di_dp_a_per_w: np.ndarray
    d2i_dp2_a_per_w2: np.ndarray
    g_w_per_k: np.ndarray
    tau0_s: np.ndarray
    tau_eff_s: np.ndarray

    @property
    def nonlinearity_per_w(self) -> np.ndarray:
        """Leading-order nonlinearity ``|d2I/dP2| / |dI/dP|`` in 1/W."""
        return np.abs(self.d2i_dp2_a_per_w2) / np.abs(self.di_dp_a_per_w)


def _tc_shift_k(p, b_field_t):
    b = np.asarray(b_field_t, dtype=float)
    return p.t_c_shift_k_per_t * b + p.t_c_shift_k_per_t2 * b * b


def effective_temperature_k(p, r_ohm, i_abs_a, b_field_t=0.0):
    """TES temperature at resistance R, current |I| (peak) and field B."""
    return (
        p.transition.temperature_k(r_ohm)
        + _tc_shift_k(p, b_field_t)
        - p.current_shift_k_per_a * np.asarray(i_abs_a, dtype=float)
    )


def tes_current_a(p, r_ohm, v_thev_v=None):
    """Peak TES current ``sqrt(2) V / (R + z)`` (complex)."""
    v = p.v_thev_v if v_thev_v is None else v_thev_v
    return SQRT2 * np.asarray(v, dtype=float) / (np.asarray(r_ohm, dtype=float) + p.z_thev_ohm)


def joule_power_w(p, r_ohm, v_thev_v=None):
    """Electrical power ``V^2 R / |R + z|^2`` dissipated in the TES."""
    v = p.v_thev_v if v_thev_v is None else v_thev_v
    r = np.asarray(r_ohm, dtype=float)
    return np.asarray(v, dtype=float) ** 2 * r / np.abs(r + p.z_thev_ohm) ** 2


def power_of_resistance_w(p, r_ohm, t_bath_k, b_field_t=0.0, v_thev_v=None):
    """Optical power that puts the TES at resistance R: the explicit inverse.

    ``P = K (T^n - T_bath^n) - V^2 R / |R + z|^2`` with ``T`` from the
    transition at the current that R implies.
    """
    v = p.v_thev_v if v_thev_v is None else v_thev_v
    r = np.asarray(r_ohm, dtype=float)
    i_abs = SQRT2 * np.asarray(v, dtype=float) / np.abs(r + p.z_thev_ohm)
    t = effective_temperature_k(p, r, i_abs, b_field_t)
    t_bath = np.asarray(t_bath_k, dtype=float)
    return p.k_w_per_k_n * (np.maximum(t, 0.0) ** p.n - t_bath**p.n) - joule_power_w(p, r, v)


def branch_bounds_ohm(p):
    """Open interval ``(lo, hi)`` of R holding the stable transition branch.

    ``lo`` is just above ``max(|z|, R_min)`` (below it the loop gain is
    negative and the TES latches); ``hi`` just below the top of the
    transition model's domain. Same shape as the parameters.
    """
    r_min, r_max = p.transition.r_domain_ohm()
    r_n = p.transition.r_normal_ohm
    lo = np.maximum(np.abs(p.z_thev_ohm), r_min) + 1e-9 * r_n
    hi = np.asarray(r_max, dtype=float) - _EDGE_FRAC * r_n
    return lo, hi


def solve_operating_point(p, p_opt_w, t_bath_k=None, b_field_t=0.0, v_thev_v=None) -> OperatingPoint:
    """Solve the power balance for the TES state (forward model).

    Parameters
    ----------
    p : DetectorParams or ParamArray
    p_opt_w, t_bath_k, b_field_t, v_thev_v : array_like
        Broadcast together (and with the parameters) to shape S. ``t_bath_k``
        and ``v_thev_v`` default to the parameters' nominal values.

    Returns
    -------
    OperatingPoint with arrays of shape S.
    """
    t_bath = p.t_bath_k if t_bath_k is None else t_bath_k
    v = p.v_thev_v if v_thev_v is None else v_thev_v
    lo, hi = branch_bounds_ohm(p)
    arrays = np.broadcast_arrays(
        np.asarray(p_opt_w, dtype=float),
        np.asarray(t_bath, dtype=float),
        np.asarray(b_field_t, dtype=float),
        np.asarray(v, dtype=float),
        lo,
        hi,
        np.asarray(p.k_w_per_k_n, dtype=float),
    )
    p_opt, t_bath, b, v, lo, hi = (np.array(a, dtype=float) for a in arrays[:6])
    if np.any(v <= 0) or not np.all(np.isfinite(v)):
        raise ConfigError("solve_operating_point: bias voltage must be finite and > 0")

    def resid(r):
        return p_opt - power_of_resistance_w(p, r, t_bath, b, v)

    f_lo = resid(lo)
    # T_s diverges at the top of the transition: -inf there is the right sign.
    with np.errstate(over="ignore"):
        f_hi = resid(hi)
    sc = ~(f_lo > 0)
    normal = ~sc & ~(f_hi < 0)
    ok = ~sc & ~normal
    # Elements off the branch get a dummy linear residual so one vectorised
    # bracket covers everything.
    mid = 0.5 * (lo + hi)

    def g(r):
        return np.where(ok, resid(r), mid - r)

    with np.errstate(over="ignore"):
        r = bracketed_root(g, lo, hi)
    r_min, r_max = p.transition.r_domain_ohm()
    r = np.where(sc, np.broadcast_to(r_min, r.shape), r)
    r = np.where(normal, np.broadcast_to(r_max, r.shape), r)
    i = tes_current_a(p, r, v)
    t = effective_temperature_k(p, np.clip(r, lo, hi), np.abs(i), b)
    # Off the branch the temperature follows from the balance with R fixed.
    t_off = (t_bath**p.n + (p_opt + joule_power_w(p, r, v)) / p.k_w_per_k_n) ** (1.0 / p.n)
    t = np.where(ok, t, t_off)
    state = np.where(sc, STATE_SUPERCONDUCTING, np.where(normal, STATE_NORMAL, STATE_TRANSITION))
    return OperatingPoint(r_ohm=r, t_k=t, i_a=i, state=state.astype(np.int8))


def readout_current_a(p, i_tes_a, b_field_t=0.0):
    """What the readout measures: TES current plus magnetic pickup ``m B``."""
    return np.asarray(i_tes_a) + p.pickup_a_per_t * np.asarray(b_field_t, dtype=float)


def invert_current(p, i_meas_a, t_bath_k=None, b_field_t=0.0, v_thev_v=None) -> Inversion:
    """Exact inverse: measured complex current to optical power, per sample.

    ``R = Re(sqrt(2) V / i - z)`` with the pickup removed from ``i``, then
    ``T = T(R, |i|, B)`` and ``P = K (T^n - T_bath^n) - V^2 R/|R+z|^2``.
    No root finding, exact in bath temperature, bias and field.

    Parameters
    ----------
    p : DetectorParams or ParamArray
    i_meas_a : array_like of complex, shape S
        Measured peak current (counts times gain), pickup included.
    t_bath_k, b_field_t, v_thev_v : array_like, broadcast to S

    Returns
    -------
    Inversion
    """
    t_bath = p.t_bath_k if t_bath_k is None else t_bath_k
    v = np.asarray(p.v_thev_v if v_thev_v is None else v_thev_v, dtype=float)
    b = np.asarray(b_field_t, dtype=float)
    i = np.asarray(i_meas_a, dtype=complex) - p.pickup_a_per_t * b
    with np.errstate(divide="ignore", invalid="ignore"):
        zr = SQRT2 * v / i - p.z_thev_ohm
    r = zr.real
    lo, hi = branch_bounds_ohm(p)
    in_branch = (r > lo) & (r < hi)
    state = np.where(
        r >= hi, STATE_NORMAL, np.where(in_branch, STATE_TRANSITION, STATE_SUPERCONDUCTING)
    ).astype(np.int8)
    r_safe = np.where(in_branch, r, 0.5 * (lo + hi))
    with np.errstate(invalid="ignore"):
        t = effective_temperature_k(p, r_safe, np.abs(i), b)
        p_opt = power_of_resistance_w(p, r_safe, t_bath, b, v)
    return Inversion(
        p_opt_w=np.where(in_branch, p_opt, np.nan),
        r_ohm=r,
        t_k=np.where(in_branch, t, np.nan),
        state=state,
        x_residual_ohm=zr.imag,
    )


def small_signal(p, r_ohm, t_bath_k=None, b_field_t=0.0, v_thev_v=None) -> SmallSignal:
    """Loop gain (eq. 2), responsivity (eq. 3) and exact derivatives at R.

    Along the response curve at fixed environment, both ``I(R)`` and
    ``P(R)`` are explicit, so ``dI/dP = I'/P'`` and
    ``d2I/dP2 = (I'' P' - I' P'') / P'^3`` (primes: d/dR) are exact.
    """
    v = np.asarray(p.v_thev_v if v_thev_v is None else v_thev_v, dtype=float)
    t_bath = np.asarray(p.t_bath_k if t_bath_k is None else t_bath_k, dtype=float)
    r = np.asarray(r_ohm, dtype=float)
    z = p.z_thev_ohm
    x = np.real(z)
    z2 = np.abs(z) ** 2
    k, n, gamma = p.k_w_per_k_n, p.n, p.current_shift_k_per_a
    m2 = (r + x) ** 2 + np.imag(z) ** 2  # |R + z|^2
    mod = np.sqrt(m2)
    i_c = SQRT2 * v / (r + z)
    i_abs = SQRT2 * v / mod
    # |I|(R) and its derivatives.
    a1 = -SQRT2 * v * (r + x) / mod**3
    a2 = -SQRT2 * v * (1.0 / mod**3 - 3.0 * (r + x) ** 2 / mod**5)
    ts1, ts2 = p.transition.dtemperature_dr(r)
    t = effective_temperature_k(p, r, i_abs, b_field_t)
    t1 = ts1 - gamma * a1
    t2 = ts2 - gamma * a2
    # Joule power J(R) = V^2 R / |R+z|^2 and derivatives.
    j1 = v**2 * (z2 - r**2) / m2**2
    j2 = v**2 * (-2.0 * r / m2**2 - 4.0 * (z2 - r**2) * (r + x) / m2**3)
    p1 = k * n * t ** (n - 1) * t1 - j1
    p2 = k * n * (n - 1) * t ** (n - 2) * t1**2 + k * n * t ** (n - 1) * t2 - j2
    i1 = -SQRT2 * v / (r + z) ** 2
    i2 = 2.0 * SQRT2 * v / (r + z) ** 3
    di_dp = i1 / p1
    d2i_dp2 = (i2 * p1 - i1 * p2) / p1**3
    # Paper eqs. 2 and 3 in closed form.
    alpha = t / (r * ts1)
    beta = i_abs * gamma / (r * ts1)
    loop_gain = (
        alpha * v**2 / (k * n * t**n * r)
        * r**2 * (r**2 - z2)
        / (m2 * (m2 + beta * r * (r + x)))
    )
    responsivity = (
        -SQRT2 / v * loop_gain / (loop_gain + 1.0)
        * (1.0 + 2.0 * np.conj(z) * (r + x) / (r**2 - z2))
    )
    g = k * n * t ** (n - 1)
    tau0 = p.c_heat_j_per_k / g
    del i_c, t_bath
    return SmallSignal(
        alpha=alpha,
        beta=beta,
        loop_gain=loop_gain,
        responsivity_a_per_w=responsivity,
        di_dp_a_per_w=di_dp,
        d2i_dp2_a_per_w2=d2i_dp2,
        g_w_per_k=g,
        tau0_s=tau0,
        tau_eff_s=tau0 / (1.0 + loop_gain),
    )


# Below this electrothermal loop gain the TES has left the transition in
# practice: its response is < 0.1 % of an ideal voltage-biased TES and readout
# noise is amplified > 1000x, so converters flag it SATURATED.
LOOP_GAIN_NORMAL = 0.001


def saturation_resistance_ohm(p, loop_gain_min: float = LOOP_GAIN_NORMAL, n_grid: int = 400) -> float:
    """Lowest R above the nominal operating point where the loop gain < ``loop_gain_min``.

    Evaluated at the nominal bias, bath temperature and B = 0. The arctan
    placeholder only approaches R_n asymptotically, so "normal" needs a
    physical criterion; this one applies to every transition model. Returns
    the top of the stable branch if the loop gain never falls that low.

    Parameters
    ----------
    p : DetectorParams (one detector)
    """
    lo, hi = (float(x) for x in branch_bounds_ohm(p))
    op = solve_operating_point(p, p.p_opt_w)
    r0 = float(op.r_ohm) if int(op.state) == STATE_TRANSITION else 0.5 * (lo + hi)
    # Geometric spacing towards the top, where the loop gain collapses.
    r = hi - (hi - r0) * np.geomspace(1.0, 1e-9, n_grid)
    with np.errstate(all="ignore"):
        loop_gain = small_signal(p, r).loop_gain
    below = np.flatnonzero(~(loop_gain >= loop_gain_min))
    if below.size == 0:
        return hi
    k = int(below[0])
    if k == 0:
        return r0
    # Linear interpolation between the last grid point above and the first below.
    l0, l1 = float(loop_gain[k - 1]), float(loop_gain[k])
    frac = (l0 - loop_gain_min) / (l0 - l1) if np.isfinite(l1) and l0 != l1 else 1.0
    return float(r[k - 1] + frac * (r[k] - r[k - 1]))


def tune_bias_v(p, r_frac, p_opt_w=None, t_bath_k=None, b_field_t=0.0):
    """Bias voltage that puts the TES at ``R = r_frac R_n`` (vectorised).

    Without current dependence this is closed form,
    ``V^2 = (K (T^n - T_bath^n) - P) |R+z|^2 / R``; with it, the residual is
    monotone in V and is solved in a bracket.

    Raises
    ------
    ConfigError
        If ``r_frac`` is outside the stable branch or the loading exceeds what
        the detector can absorb at that resistance.
    """
    p_opt = np.asarray(p.p_opt_w if p_opt_w is None else p_opt_w, dtype=float)
    t_bath = np.asarray(p.t_bath_k if t_bath_k is None else t_bath_k, dtype=float)
    r = np.asarray(r_frac, dtype=float) * p.transition.r_normal_ohm
    lo, hi = branch_bounds_ohm(p)
    if np.any(r <= lo) or np.any(r >= hi):
        raise ConfigError(f"tune_bias_v: r_frac {r_frac} is outside the stable transition branch")
    m2 = np.abs(r + p.z_thev_ohm) ** 2

    def v_closed(i_abs):
        t = effective_temperature_k(p, r, i_abs, b_field_t)
        excess = p.k_w_per_k_n * (np.maximum(t, 0.0) ** p.n - t_bath**p.n) - p_opt
        return excess

    excess0 = v_closed(0.0)
    if np.any(excess0 <= 0):
        raise ConfigError("tune_bias_v: loading exceeds the saturation power at this resistance")
    v0 = np.sqrt(excess0 * m2 / r)
    if np.all(np.asarray(p.current_shift_k_per_a) == 0):
        return v0

    def resid(v):
        return v**2 * r / m2 - v_closed(SQRT2 * v / np.sqrt(m2))

    lo_v = np.zeros(np.broadcast(v0, r).shape)
    # resid(v0) >= 0 because current only lowers T; widen by rounding.
    return bracketed_root(resid, lo_v, np.broadcast_to(v0 * (1 + 1e-9), lo_v.shape).copy())


def describe(p, p_opt_w=None, t_bath_k=None, b_field_t=0.0, v_thev_v=None) -> dict[str, Any]:
    """Scalar summary of one detector's operating point (Table 1 style)."""
    p_opt = p.p_opt_w if p_opt_w is None else p_opt_w
    t_bath = p.t_bath_k if t_bath_k is None else t_bath_k
    v = p.v_thev_v if v_thev_v is None else v_thev_v
    op = solve_operating_point(p, p_opt, t_bath, b_field_t, v)
    if int(op.state) != STATE_TRANSITION:
        raise ConfigError(
            f"operating point is not in the transition (state {int(op.state)}); retune the bias"
        )
    ss = small_signal(p, op.r_ohm, t_bath, b_field_t, v)
    t_c = float(p.transition.temperature_k(0.5 * p.transition.r_normal_ohm))
    p_sat = p.k_w_per_k_n * (t_c**p.n - t_bath**p.n)
    return {
        "detector_id": p.detector_id,
        "units": "SI; currents are peak amplitudes, i = sqrt(2) V / (R + z)",
        "p_opt_w": float(p_opt),
        "t_bath_k": float(t_bath),
        "b_field_t": float(b_field_t),
        "v_thev_v": float(v),
        "r_ohm": float(op.r_ohm),
        "r_frac": float(op.r_ohm / p.transition.r_normal_ohm),
        "t_tes_k": float(op.t_k),
        "i_peak_a": float(np.abs(op.i_a)),
        "p_electrical_w": float(joule_power_w(p, op.r_ohm, v)),
        "p_sat_w": float(p_sat),
        "k_w_per_k_n": float(p.k_w_per_k_n),
        "n": float(p.n),
        "alpha": float(ss.alpha),
        "beta": float(ss.beta),
        "loop_gain": float(ss.loop_gain),
        "responsivity_a_per_w": [float(np.real(ss.responsivity_a_per_w)), float(np.imag(ss.responsivity_a_per_w))],
        "abs_responsivity_a_per_w": float(np.abs(ss.responsivity_a_per_w)),
        "abs_di_dp_implicit_a_per_w": float(np.abs(ss.di_dp_a_per_w)),
        "g_dynamic_w_per_k": float(ss.g_w_per_k),
        "g_bar_w_per_k": float(p_sat / (t_c - t_bath)),
        "tau0_s": float(ss.tau0_s),
        "tau_eff_s": float(ss.tau_eff_s),
        "d2i_dp2_a_per_w2": float(np.abs(ss.d2i_dp2_a_per_w2)),
        "nonlinearity_per_pw": float(ss.nonlinearity_per_w) * 1e-12,
    }
