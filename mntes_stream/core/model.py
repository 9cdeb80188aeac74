"""The MNTES TES model: power balance, forward solve, exact inverse, small signal.

Power balance (paper eq. 1), with V the RMS Thevenin voltage and z the
Thevenin impedance::

    P_opt + V^2 R / |R + z|^2 = K (T^n - T_bath^n)

The readout reports the peak current ``i = sqrt(2) V / (R + z)`` plus a
magnetic pickup ``m B``. Parameters ``p`` are a :class:`DetectorParams`
(scalars) or a :class:`ParamArray` (columns of shape ``(n_det, 1)``); every
function broadcasts parameters against its sample arrays.

The forward solve is parameterised by R (not T): on the positive-feedback
branch ``R > |z|`` the power-balance residual is strictly decreasing in R, so
a bracket ``(max(|z|, R_min), R_max)`` holds exactly one root, and the
transition enters only through ``T_s(R)``, the direction every model provides.
Below ``|z|`` the electrothermal stability criterion (``dP/dR > 0``, i.e.
loop gain ``L > -1``) decides which states exist: the operating branch
continues down to ``R2`` and a detector may also sit on a low stable branch
(``R0 < R < R1``); where both exist (bistability) its history picks one
(:func:`stability_bounds_ohm`, :func:`solve_operating_point`).
"""

from __future__ import annotations

import functools
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
    "STATE_LATCHED",
    "balance_slope_w_per_ohm",
    "stability_bounds_ohm",
    "latch_sequence",
    "FlagThresholds",
    "flag_thresholds",
    "DEFAULT_READOUT_NOISE_A",
    "K_SIGMA",
    "P_RESOLUTION_W",
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
# Off the positive-feedback operating branch but resistive and stable: below
# |z| (loop gain -1 < L <= 0) or on the low branch of a bistable detector.
STATE_LATCHED = 3

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
        ``STATE_TRANSITION`` (``R > |z|``), ``STATE_LATCHED`` (stable with
        ``R <= |z|``), ``STATE_SUPERCONDUCTING`` (R is the bottom of the
        transition) or ``STATE_NORMAL``.
    dropped : ndarray of bool, shape S, or None
        True where the detector sits on its low branch or superconducting (it
        dropped out of the operating branch); the history the next solve needs.
    """

    r_ohm: np.ndarray
    t_k: np.ndarray
    i_a: np.ndarray
    state: np.ndarray
    dropped: np.ndarray | None = None


@dataclass(frozen=True)
class Inversion:
    """Result of the exact inverse; arrays of shape S.

    ``p_opt_w`` is NaN wherever ``state`` is not ``STATE_TRANSITION``
    (``R > |z|``); ``STATE_LATCHED`` is a resistance between the bottom of the
    transition and that branch.
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
    """Open interval ``(lo, hi)`` of R holding the positive-feedback operating branch.

    ``lo`` is just above ``max(|z|, R_min)`` (below it the loop gain is
    negative: stable down to ``R2`` of :func:`stability_bounds_ohm`, but the
    TES no longer works as a voltage-biased sensor: ``STATE_LATCHED``);
    ``hi`` just below the top of the transition model's domain. Same shape as
    the parameters.
    """
    r_min, r_max = p.transition.r_domain_ohm()
    r_n = p.transition.r_normal_ohm
    lo = np.maximum(np.abs(p.z_thev_ohm), r_min) + 1e-9 * r_n
    hi = np.asarray(r_max, dtype=float) - _EDGE_FRAC * r_n
    return lo, hi


def balance_slope_w_per_ohm(p, r_ohm, v_thev_v=None, b_field_t=0.0):
    """``dP/dR`` of the power balance along R at fixed bias and field.

    ``P(R) = K (T^n - T_bath^n) - V^2 R / |R + z|^2`` with
    ``T = T_s(R) + shift - gamma |I(R)|``; the bath temperature does not enter.
    An equilibrium is stable against the electrothermal mode exactly where
    this is positive (loop gain ``L > -1``: the heat flow to the bath grows
    faster with R than the Joule power the bias network delivers). Above
    ``|z|`` the Joule power falls with R, so it is always positive there.
    """
    v = np.asarray(p.v_thev_v if v_thev_v is None else v_thev_v, dtype=float)
    r = np.asarray(r_ohm, dtype=float)
    z = p.z_thev_ohm
    x = np.real(z)
    m2 = (r + x) ** 2 + np.imag(z) ** 2
    i_abs = SQRT2 * v / np.sqrt(m2)
    t = effective_temperature_k(p, r, i_abs, b_field_t)
    ts1, _ = p.transition.dtemperature_dr(r)
    t1 = ts1 + p.current_shift_k_per_a * SQRT2 * v * (r + x) / m2**1.5
    j1 = v**2 * (np.abs(z) ** 2 - r**2) / m2**2
    thermal = p.k_w_per_k_n * p.n * np.maximum(t, 0.0) ** (p.n - 1) * t1
    return np.where(t > 0, thermal, 0.0) - j1


# Grid (fractions of [R_min, min(|z|, R_max)]) on which the sign of dP/dR is
# scanned; geometric near the bottom, where the arctan's slope diverges.
_STAB_GRID = np.union1d(np.geomspace(1e-7, 1e-2, 96), np.linspace(1e-2, 1.0, 416))




def stability_bounds_ohm(p, v_thev_v=None, b_field_t=0.0):
    """``(R0, R1, R2)``: the low stable branch ``[R0, R1]`` and the bottom ``R2`` of the operating branch.

    From the sign of ``dP/dR`` (:func:`balance_slope_w_per_ohm`) on
    ``[R_min, min(|z|, R_max)]``: the operating branch is the topmost interval
    where it is positive, ``(R2, ...)``; below the unstable interval
    ``(R1, R2)`` the next stable interval ``(R0, R1)`` is the low branch a
    bistable detector can drop onto. Without an unstable interval all three
    are ``R_min``; without a low branch ``R0 = R1 = R_min``. Elementwise over
    the broadcast shape S of parameters, bias and field.

    Returns
    -------
    r0_ohm, r1_ohm, r2_ohm : ndarray, shape S
    """
    v = np.asarray(p.v_thev_v if v_thev_v is None else v_thev_v, dtype=float)
    b = np.asarray(b_field_t, dtype=float)
    r_min, r_max = p.transition.r_domain_ohm()
    r_min = np.asarray(r_min, dtype=float)
    top = np.minimum(np.abs(p.z_thev_ohm), np.asarray(r_max, dtype=float))
    shape = np.broadcast_shapes(v.shape, b.shape, r_min.shape, np.shape(top), np.shape(p.k_w_per_k_n))
    v, b, r_min, top = (np.broadcast_to(a, shape) for a in (v, b, r_min, top))
    span = np.maximum(top - r_min, 0.0)

    def positive(r):
        with np.errstate(all="ignore"):
            return balance_slope_w_per_ohm(p, r, v, b) > 0

    grid = r_min[..., None] + span[..., None] * _STAB_GRID  # shape S + (n_grid,)
    # Parameters broadcast against S: move the grid axis first so they still do.
    with np.errstate(all="ignore"):
        pos = np.moveaxis(balance_slope_w_per_ohm(p, np.moveaxis(grid, -1, 0), v, b) > 0, 0, -1)
    pos = np.array(np.broadcast_to(pos, grid.shape))
    pos[..., -1] = True  # at |z| the Joule term vanishes: stable by construction
    k_idx = np.arange(_STAB_GRID.size)

    def last(mask):
        return np.max(np.where(mask, k_idx, -1), axis=-1)

    def at(k):
        return np.take_along_axis(grid, np.clip(k, 0, _STAB_GRID.size - 1)[..., None], axis=-1)[..., 0]

    k2 = last(~pos)                                   # last unstable grid point
    k1 = last(pos & (k_idx < k2[..., None]))          # last stable point below it
    k0 = last(~pos & (k_idx < k1[..., None]))         # last unstable point below that
    # The three sign changes refined together: stacked on a leading axis of 3.
    lo_pos = np.array([False, True, False]).reshape((3,) + (1,) * len(shape))
    a = np.stack([at(k2), at(k1), at(k0)])
    c = np.stack([at(k2 + 1), at(k1 + 1), at(k0 + 1)])
    for _ in range(56):
        m = 0.5 * (a + c)
        same = positive(m) == lo_pos
        a, c = np.where(same, m, a), np.where(same, c, m)
    r2, r1, r0 = c[0], a[1], c[2]
    has2, has1, has0 = k2 >= 0, k1 >= 0, k0 >= 0
    r2 = np.where(has2, r2, r_min)
    r1 = np.where(has2 & has1, r1, r_min)
    r0 = np.where(has2 & has1 & has0, r0, r_min)
    return r0, r1, r2


_SKIP_FIELDS = ("detector_ids", "detector_id", "transition")


def _array_fields(p) -> dict:
    """The parameters' numeric fields and the arctan transition's, by name."""
    import dataclasses

    out = {f.name: getattr(p, f.name) for f in dataclasses.fields(p) if f.name not in _SKIP_FIELDS}
    tr = p.transition
    if hasattr(tr, "iqr_k"):
        out.update({"transition." + k: getattr(tr, k) for k in ("t_c_k", "iqr_k", "r_n_ohm")})
    return out


def _param_shape(p) -> tuple:
    """Broadcast shape of the parameters' fields (``()`` for one detector)."""
    return np.broadcast_shapes(*(np.shape(x) for x in _array_fields(p).values()))


def _subset(p, shape, index):
    """Parameters broadcast to ``shape`` and taken at the flat ``index`` (scalar parameters pass through)."""
    import dataclasses

    if _param_shape(p) == ():
        return p

    def take(a):
        return np.broadcast_to(np.asarray(a), shape).reshape(-1)[index]

    fields = _array_fields(p)
    kw = {k: take(v) for k, v in fields.items() if not k.startswith("transition.")}
    tr = p.transition
    if "transition.iqr_k" in fields:
        tr = type(tr)(t_c_k=take(tr.t_c_k), iqr_k=take(tr.iqr_k), r_n_ohm=take(tr.r_n_ohm))
    if hasattr(p, "detector_ids"):
        kw["detector_ids"] = ()
    return dataclasses.replace(p, transition=tr, **kw)


def lower_states(p, p_opt_w, t_bath_k, b_field_t, v_thev_v, bounds=None):
    """The states at or below ``|z|`` (1-D sample arrays).

    Returns ``(r_op, op_exists, r_low, low_exists)``: the root on the
    operating branch ``(R2, |z|]`` and on the low branch ``(R0, R1]``
    (NaN where none), or superconducting (``r_low = R_min``) where the power
    is below ``P(R0)``. ``p`` holds scalars or arrays of the samples' shape;
    ``bounds`` is ``(R0, R1, R2)`` if already known.
    """
    p_opt, t_bath, b, v = (np.asarray(a, dtype=float) for a in (p_opt_w, t_bath_k, b_field_t, v_thev_v))
    r0, r1, r2 = stability_bounds_ohm(p, v, b) if bounds is None else bounds
    r_min, r_max = p.transition.r_domain_ohm()
    r_n = p.transition.r_normal_ohm
    r_min = np.broadcast_to(np.asarray(r_min, dtype=float), p_opt.shape)
    top = np.broadcast_to(np.maximum(np.abs(p.z_thev_ohm), r_min) + 1e-9 * r_n, p_opt.shape)
    eps = 1e-9 * r_n

    def resid(r):
        with np.errstate(all="ignore"):
            return p_opt - power_of_resistance_w(p, r, t_bath, b, v)

    def root(mask, a, c):
        out = np.full(p_opt.shape, np.nan)
        if np.any(mask):
            mid = 0.5 * (a + c)
            with np.errstate(all="ignore"):
                x = bracketed_root(lambda r: np.where(mask, resid(r), mid - r), np.where(mask, a, mid - 1),
                                   np.where(mask, c, mid + 1))
            out = np.where(mask, x, np.nan)
        return out

    a2 = np.maximum(r2, r_min) + eps
    op_exists = (resid(a2) > 0) & ~(resid(top) > 0)
    r_op = root(op_exists, a2, top)
    has_low = r1 > r0 + 2 * eps
    f0 = resid(r0 + eps)
    low_branch = has_low & (f0 > 0) & ~(resid(r1) > 0)
    r_low = root(low_branch, r0 + eps, r1)
    sc = ~(f0 > 0)  # colder than the bottom of the transition: zero resistance
    r_low = np.where(sc, r_min, r_low)
    low_exists = low_branch | sc
    return r_op, op_exists, r_low, low_exists


@functools.lru_cache(maxsize=4096)
def _cached_bounds_key(p, v: float):
    return tuple(float(x) for x in stability_bounds_ohm(p, v, 0.0))


def _cached_bounds(p, v: float):
    """Stability bounds of one detector at bias ``v`` and B = 0, cached (parameters are frozen)."""
    try:
        return _cached_bounds_key(p, v)
    except TypeError:  # unhashable parameters
        return tuple(float(x) for x in stability_bounds_ohm(p, v, 0.0))


def _bounds_by_bias(p, shape, v, idx):
    """``stability_bounds_ohm`` at B = 0 for the flat sample indices ``idx``, once per (detector, bias) pair.

    The field enters the bounds only through ``K n T^(n-1)`` (a relative
    change ~ c1 B / T, 1e-4 at 100 uT): the bounds are evaluated at B = 0.
    """
    v = np.broadcast_to(np.asarray(v, dtype=float), shape).reshape(-1)[idx]
    pshape = _param_shape(p)
    n_par = int(np.prod(pshape))
    det = np.broadcast_to(np.arange(n_par).reshape(pshape), shape).reshape(-1)[idx]
    keys = np.stack([det.astype(float), v], axis=1)
    uniq, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.reshape(-1)
    if pshape == ():
        bounds = tuple(np.array(x) for x in zip(*(_cached_bounds(p, float(u)) for u in uniq[:, 1])))
    else:
        bounds = stability_bounds_ohm(_subset(p, pshape, uniq[:, 0].astype(np.int64)), uniq[:, 1], 0.0)
    return tuple(np.broadcast_to(np.asarray(x), (uniq.shape[0],))[inverse] for x in bounds)


def latch_sequence(op_exists, low_exists, dropped0=None):
    """Hysteresis along the last axis (time): where the detector sits at each sample.

    A detector with only its low state available drops (True); with only its
    operating state available it is back on the branch (False); where both
    exist it keeps its previous state. ``dropped0`` (shape ``S[:-1]``) is the
    state before the first sample (default: on the branch).

    >>> latch_sequence(np.array([1, 1, 0, 1, 1, 1], bool), np.array([0, 1, 1, 1, 0, 1], bool)).tolist()
    [False, False, True, True, False, False]
    """
    op_exists, low_exists = np.broadcast_arrays(np.asarray(op_exists, bool), np.asarray(low_exists, bool))
    shape = op_exists.shape
    n = shape[-1]
    event = np.where(low_exists & ~op_exists, 1, np.where(op_exists & ~low_exists, -1, 0))
    d0 = np.zeros(shape[:-1], bool) if dropped0 is None else np.broadcast_to(np.asarray(dropped0, bool), shape[:-1])
    idx = np.where(event != 0, np.arange(n), -1)
    last = np.maximum.accumulate(idx, axis=-1)
    ev = np.take_along_axis(event, np.maximum(last, 0), axis=-1)
    return np.where(last >= 0, ev == 1, d0[..., None])


def lower_candidates(p, shape, p_opt, t_bath, b, v, r, below, normal, history: bool = True):
    """States below ``|z|`` and low branches for the samples that can have them (arrays of ``shape``).

    ``r`` holds the roots above ``|z|`` where ``~below & ~normal``. Returns
    ``(r, op_exists, low_exists, r_low)``: ``r`` with the operating roots
    below ``|z|`` filled in, where the operating branch and a low state exist,
    and the low state's R (NaN where none). Without ``history`` (no latch
    state to keep) a detector above ``|z|`` stays on its operating branch, so
    only the samples below ``|z|`` are examined.
    """
    r_min = np.broadcast_to(np.asarray(p.transition.r_domain_ohm()[0], dtype=float), shape)
    r = np.array(r, dtype=float)
    op_exists = np.array(~below)
    low_exists = np.zeros(shape, bool)
    r_low_all = np.full(shape, np.nan)
    # Candidates for a state below |z|: powers a resistance below |z| can balance at all
    # (heat flow at T_s(|z|) with no Joule heating bounds P from above there).
    t_z = effective_temperature_k(p, np.maximum(np.abs(p.z_thev_ohm), r_min), 0.0, b)
    cand = (~normal & (p_opt <= p.k_w_per_k_n * (np.maximum(t_z, 0.0) ** p.n - t_bath**p.n))) | below
    if not history:
        cand = below
    if not np.any(cand):
        return r, op_exists, low_exists, r_low_all
    idx = np.flatnonzero(cand)
    r0_, r1_, r2_ = _bounds_by_bias(p, shape, v, idx)
    if np.any(cand & ~below):
        # Above |z| a low branch needs P <= P(R1).
        sub = _subset(p, shape, idx)
        flat = [a.reshape(-1)[idx] for a in (t_bath, b, v)]
        with np.errstate(all="ignore"):
            p_r1 = power_of_resistance_w(sub, r1_, *flat)
        keep = below.reshape(-1)[idx] | ((r1_ > r0_) & (p_opt.reshape(-1)[idx] <= p_r1))
        idx, r0_, r1_, r2_ = idx[keep], r0_[keep], r1_[keep], r2_[keep]
    if idx.size:
        sub = _subset(p, shape, idx)
        flat = [a.reshape(-1)[idx] for a in (p_opt, t_bath, b, v)]
        r_op, op_ex, r_low, low_ex = lower_states(sub, *flat, bounds=(r0_, r1_, r2_))
        was_below = below.reshape(-1)[idx]
        rf, of, lf, rl = (a.reshape(-1) for a in (r, op_exists, low_exists, r_low_all))
        rf[idx] = np.where(was_below & op_ex, r_op, rf[idx])
        op_ex = np.where(was_below, op_ex, True)  # above |z| the operating root stands
        of[idx] = op_ex
        lf[idx] = low_ex
        rl[idx] = r_low
    return r, op_exists, low_exists, r_low_all


def solve_operating_point(p, p_opt_w, t_bath_k=None, b_field_t=0.0, v_thev_v=None, dropped=None,
                          sequential: bool = False) -> OperatingPoint:
    """Solve the power balance for the TES state (forward model), with latching.

    Above ``|z|`` the balance has exactly one root on the operating branch;
    at lower power the states below ``|z|`` decided by the stability
    criterion (:func:`lower_states`): the operating branch continues down to
    ``R2`` and a low branch or the superconducting state may exist too.
    Where both exist (bistability) the detector's history picks: ``dropped``.

    Parameters
    ----------
    p : DetectorParams or ParamArray
    p_opt_w, t_bath_k, b_field_t, v_thev_v : array_like
        Broadcast together (and with the parameters) to shape S. ``t_bath_k``
        and ``v_thev_v`` default to the parameters' nominal values.
    dropped : array_like of bool, optional
        True where the detector was off its operating branch before: shape S,
        or with ``sequential`` the state before the first sample (``S[:-1]``).
    sequential : bool
        The last axis is time: the latch carries from sample to sample
        (:func:`latch_sequence`).

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
    shape = p_opt.shape
    if np.any(v <= 0) or not np.all(np.isfinite(v)):
        raise ConfigError("solve_operating_point: bias voltage must be finite and > 0")

    def resid(r):
        return p_opt - power_of_resistance_w(p, r, t_bath, b, v)

    f_lo = resid(lo)
    # T_s diverges at the top of the transition: -inf there is the right sign.
    with np.errstate(over="ignore"):
        f_hi = resid(hi)
    below = ~(f_lo > 0)
    normal = ~below & ~(f_hi < 0)
    ok = ~below & ~normal
    mid = 0.5 * (lo + hi)

    def g(r):
        return np.where(ok, resid(r), mid - r)

    with np.errstate(over="ignore"):
        r = bracketed_root(g, lo, hi)
    r_min, r_max = p.transition.r_domain_ohm()
    r_min = np.broadcast_to(np.asarray(r_min, dtype=float), shape)
    history = sequential or dropped is not None
    r, op_exists, low_exists, r_low_all = lower_candidates(p, shape, p_opt, t_bath, b, v, r, below, normal, history)
    if sequential and p_opt.ndim >= 1:
        use_low = latch_sequence(op_exists, low_exists, dropped)
    else:
        prev = np.zeros(shape, bool) if dropped is None else np.broadcast_to(np.asarray(dropped, bool), shape)
        use_low = low_exists & (~op_exists | prev)
    use_low &= low_exists
    r = np.where(use_low, r_low_all, r)
    sc = use_low & (r_low_all <= r_min)
    r = np.where(sc, r_min, r)
    r = np.where(normal, np.broadcast_to(r_max, shape), r)
    i = tes_current_a(p, r, v)
    on_transition = ~normal & ~sc
    r_safe = np.where(on_transition, r, 0.5 * (lo + hi))
    t = effective_temperature_k(p, r_safe, np.abs(i), b)
    # Off the transition the temperature follows from the balance with R fixed.
    t_off = (t_bath**p.n + (p_opt + joule_power_w(p, r, v)) / p.k_w_per_k_n) ** (1.0 / p.n)
    t = np.where(on_transition, t, t_off)
    state = np.select([sc, normal, ~(r > np.abs(p.z_thev_ohm) + 1e-9 * p.transition.r_normal_ohm)],
                      [STATE_SUPERCONDUCTING, STATE_NORMAL, STATE_LATCHED], STATE_TRANSITION)
    return OperatingPoint(r_ohm=r, t_k=t, i_a=i, state=state.astype(np.int8), dropped=use_low)


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
    r_bottom = np.asarray(p.transition.r_domain_ohm()[0], dtype=float) + 1e-9 * p.transition.r_normal_ohm
    state = np.select([r >= hi, in_branch, r > r_bottom], [STATE_NORMAL, STATE_TRANSITION, STATE_LATCHED],
                      STATE_SUPERCONDUCTING).astype(np.int8)
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


# Readout noise per quadrature and sample (peak A, rms): the DfMux's 10 pA/sqrt(Hz)
# over the Nyquist band at 152.6 Hz; flag thresholds keep K_SIGMA of it as margin.
DEFAULT_READOUT_NOISE_A = 10e-12 * float(np.sqrt(20e6 / 2**17 / 2.0))
K_SIGMA = 7.0
# Optional resolution criterion (off by default): the power error rounding the counts
# (half a count in I and Q) may cause in an unflagged sample. Off because it would
# flag bright sources (Jupiter at 1.3 pW: ~1e-16 W per count, 1e-4 of the signal)
# that the paper wants reconstructed; quantisation counts as readout noise instead.
P_RESOLUTION_W = None


@dataclass(frozen=True)
class FlagThresholds:
    """Per-detector flag thresholds on ``R = Re(sqrt(2) V / i - z)`` and on the quadrature.

    Noise moves the measured R by ``sigma_R = sigma_i |R + z|^2 / (sqrt(2) V)``:
    each threshold is a model resistance plus or minus a margin ``k / V``
    (``k = k_sigma sigma_i |R + z|^2 / sqrt(2)``, Ohm V), exact at every
    sample's bias (:meth:`at_bias`). A sample is

    - ``SUPERCONDUCTING`` where ``R <= r_z_ohm + k_z / V`` (not certainly above ``|z|``: loop
      gain <= 0, off the operating branch), with ``LATCHED`` too where also
      ``R > r_bottom_ohm + k_bottom / V`` (resistive: latched, not at the bottom);
    - ``SATURATED`` where ``R >= r_top_ohm - k_top / V`` (the top of the transition) or
      ``R >= r_cap_ohm`` (loop gain < ``LOOP_GAIN_NORMAL``, or the optional resolution criterion);
    - ``PHASE_RESIDUAL`` where the current the model does not explain,
      ``|Im(sqrt(2) V / i - z)| |i|^2 / (sqrt(2) V)``, exceeds ``phase_limit_a``.
    """

    r_bottom_ohm: float
    k_bottom_ohm_v: float
    r_z_ohm: float
    k_z_ohm_v: float
    r_top_ohm: float
    k_top_ohm_v: float
    r_cap_ohm: float
    sigma_i_a: float
    phase_limit_a: float

    def at_bias(self, v_thev_v):
        """``(r_superconducting, r_latched, r_saturated)`` at bias V (broadcasts)."""
        v = np.asarray(v_thev_v, dtype=float)
        return (self.r_bottom_ohm + self.k_bottom_ohm_v / v, self.r_z_ohm + self.k_z_ohm_v / v,
                np.minimum(self.r_top_ohm - self.k_top_ohm_v / v, self.r_cap_ohm))

    @property
    def r_superconducting_ohm(self) -> float:
        """At or below (nominal bias): at the bottom, SUPERCONDUCTING without LATCHED."""
        return float(self.at_bias(self._v_ref)[0])

    @property
    def r_latched_ohm(self) -> float:
        """At or below (nominal bias): off the operating branch, SUPERCONDUCTING (+ LATCHED if resistive)."""
        return float(self.at_bias(self._v_ref)[1])

    @property
    def r_saturated_ohm(self) -> float:
        """At or above (nominal bias): SATURATED."""
        return float(self.at_bias(self._v_ref)[2])


def flag_thresholds(p, readout_noise_a: float = DEFAULT_READOUT_NOISE_A, k_sigma: float = K_SIGMA,
                    p_resolution_w: float | None = P_RESOLUTION_W, v_frac=(0.9, 1.1)) -> FlagThresholds:
    """Flag thresholds of one detector from its model, readout noise and counts quantisation.

    Noise ``sigma_i`` per quadrature (readout noise and ``|g|/sqrt(12)``);
    margins of ``k_sigma`` sigma in R at the sample's own bias (see
    :class:`FlagThresholds`). SATURATED also starts where the loop gain falls
    below ``LOOP_GAIN_NORMAL`` and, with ``p_resolution_w``, where rounding
    the counts moves the power by more than that (``|dP/dR| |R+z|^2 |g| / (2 V)``,
    at the lowest bias of ``v_frac``). The ``r_*_ohm`` properties give the
    thresholds at the nominal bias.

    Parameters
    ----------
    p : DetectorParams (one detector)
    readout_noise_a : float
        Readout noise per quadrature and sample (peak A, rms), without quantisation.
    """
    if not (readout_noise_a >= 0 and np.isfinite(readout_noise_a)):
        raise ConfigError(f"readout_noise_a must be finite and >= 0, got {readout_noise_a}")
    g = abs(complex(p.gain_a_per_count))
    sigma_i = float(np.hypot(readout_noise_a, g / np.sqrt(12.0)))
    z = complex(p.z_thev_ohm)
    r_n = float(p.transition.r_normal_ohm)

    def k(r):
        return float(k_sigma * sigma_i * abs(r + z) ** 2 / SQRT2)

    r_min, r_max = (float(x) for x in p.transition.r_domain_ohm())
    r_z = max(abs(z), r_min)
    lo, hi = (float(x) for x in branch_bounds_ohm(p))
    r_cap = min(hi, saturation_resistance_ohm(p))
    if p_resolution_w is not None:
        v_lo = float(v_frac[0]) * float(p.v_thev_v)
        op = solve_operating_point(p, p.p_opt_w)
        r0 = float(op.r_ohm) if int(op.state) == STATE_TRANSITION else 0.5 * (lo + hi)
        r = hi - (hi - r0) * np.geomspace(1.0, 1e-9, 2000)
        with np.errstate(all="ignore"):
            dp_count = np.abs(balance_slope_w_per_ohm(p, r, v_lo)) * np.abs(r + z) ** 2 * g / (2.0 * v_lo)
        above = np.flatnonzero(~(dp_count <= p_resolution_w))
        if above.size:
            r_cap = min(r_cap, float(r[above[0]]))
    th = FlagThresholds(r_bottom_ohm=r_min + 1e-9 * r_n, k_bottom_ohm_v=k(r_min), r_z_ohm=r_z + 1e-9 * r_n,
                        k_z_ohm_v=k(r_z), r_top_ohm=r_max, k_top_ohm_v=k(r_max), r_cap_ohm=r_cap,
                        sigma_i_a=sigma_i, phase_limit_a=k_sigma * sigma_i)
    object.__setattr__(th, "_v_ref", float(p.v_thev_v))
    return th


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
