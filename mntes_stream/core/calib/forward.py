"""Measurement model: what the DAN reports for each calibration point.

For a point with conditions ``(P, B, bias_ratio, T_bath, omega)``::

    V     = bias_ratio * V0                          (RMS Thevenin voltage)
    z     = z(omega)                                 (readout model below)
    R     = solution of the power balance (paper eq. 1) at P, T_bath, B, V, z
    i     = sqrt(2) V / (R + z) + m B                (peak current plus pickup)
    count = i / g,   g = |g| exp(1j phi)             (complex DAN gain)

Readout model: the Thevenin impedance of a series LC(R) resonator plus
parasitics, with the bias frequency ``omega0`` as reference and ``w = omega/omega0``::

    z(omega) = z0 + r1 (w - 1) + 1j [ Im(z0) (1/w - 1) + L omega0 (w - 1/w) ]

``z0 = z(omega0)`` is the MNTES ``z_thev_ohm``; ``L`` the series inductance;
``Im z0 = omega0 L - 1/(omega0 C)`` is the residual reactance that the
capacitor leaves at the bias frequency (this is the 1/w term); ``r1`` a
frequency-dependent loss (ESR slope). The Thevenin voltage and the DAN gain
are taken as flat over a network-analysis sweep (a few kHz around a MHz carrier).

Biased sweeps (optical, field, I-V) are solved with the core model's
electrothermal branch (``core.model.solve_operating_point``, which latches
superconducting below ``R = |z|`` exactly as the converter assumes). Probe
sweeps (R(T), network analyses) sit at a bias so small that there is no
electrothermal feedback: the TES follows its transition, heated by the
optical load and the probe's own Joule power (self-heating), over the whole
range ``0 < R < R_n``. Both use the same explicit power balance
``core.model.power_of_resistance_w``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from mntes_stream.core.calib.measurements import PROBE_KINDS, DetectorCalibration, Sweep
from mntes_stream.core.model import SQRT2, power_of_resistance_w, solve_operating_point
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.solve import bracketed_root
from mntes_stream.core.transition import ArctanTransition
from mntes_stream.errors import ConfigError

__all__ = [
    "PARAM_NAMES",
    "PARAM_UNITS",
    "N_PARAMS",
    "Readout",
    "Design",
    "z_of_omega",
    "theta_from_params",
    "params_from_theta",
    "predict_counts",
]

# The fitted parameters, in order. |g| is not among them: it fixes the scale gauge.
PARAM_NAMES = (
    "t_c_k",
    "iqr_k",
    "r_n_ohm",
    "k_w_per_k_n",
    "n",
    "v_thev_v",
    "z_re_ohm",
    "z_im_ohm",
    "l_series_h",
    "r_slope_ohm",
    "t_c_shift_k_per_t",
    "t_c_shift_k_per_t2",
    "pickup_re_a_per_t",
    "pickup_im_a_per_t",
    "gain_phase_rad",
)
PARAM_UNITS = {
    "t_c_k": "K", "iqr_k": "K", "r_n_ohm": "Ohm", "k_w_per_k_n": "W/K^n", "n": "",
    "v_thev_v": "V (RMS)", "z_re_ohm": "Ohm", "z_im_ohm": "Ohm", "l_series_h": "H",
    "r_slope_ohm": "Ohm per unit omega/omega0", "t_c_shift_k_per_t": "K/T",
    "t_c_shift_k_per_t2": "K/T^2", "pickup_re_a_per_t": "A/T", "pickup_im_a_per_t": "A/T",
    "gain_phase_rad": "rad",
}
N_PARAMS = len(PARAM_NAMES)
_IX = {name: k for k, name in enumerate(PARAM_NAMES)}
_EDGE = 1e-12  # probe solve bracket, fraction of R_n from each end
_FIXED_POINT_ITER = 40


@dataclass(frozen=True)
class Readout:
    """Readout parameters beyond ``DetectorParams``: the frequency dependence of z.

    Attributes
    ----------
    bias_freq_hz : float
        ``omega0 / 2 pi``, where ``z0 = z_thev_ohm``.
    l_series_h : float
        Series inductance of the resonator.
    r_slope_ohm : float
        ``d Re z / d w`` with ``w = omega / omega0``.
    """

    bias_freq_hz: float
    l_series_h: float
    r_slope_ohm: float = 0.0

    def to_dict(self) -> dict:
        return {"bias_freq_hz": self.bias_freq_hz, "l_series_h": self.l_series_h, "r_slope_ohm": self.r_slope_ohm}


def z_of_omega(z0, l_series_h, r_slope_ohm, bias_freq_hz, freq_hz):
    """Thevenin impedance at ``freq_hz`` (broadcasts all arguments), complex Ohm."""
    w = np.asarray(freq_hz, dtype=float) / bias_freq_hz
    z0 = np.asarray(z0, dtype=complex)
    omega0 = 2.0 * np.pi * bias_freq_hz
    re = z0.real + r_slope_ohm * (w - 1.0)
    im = z0.imag / w + l_series_h * omega0 * (w - 1.0 / w)
    return re + 1j * im


def theta_from_params(p: DetectorParams, readout: Readout) -> np.ndarray:
    """Parameter vector (shape ``(N_PARAMS,)``) of an arctan detector."""
    if not isinstance(p.transition, ArctanTransition):
        raise ConfigError(f"{p.detector_id}: the calibration fit parameterises the arctan transition")
    t = p.transition
    g = p.gain_a_per_count
    return np.array([
        float(t.t_c_k), float(t.iqr_k), float(t.r_n_ohm), p.k_w_per_k_n, p.n, p.v_thev_v,
        p.z_thev_ohm.real, p.z_thev_ohm.imag, readout.l_series_h, readout.r_slope_ohm,
        p.t_c_shift_k_per_t, p.t_c_shift_k_per_t2, p.pickup_a_per_t.real, p.pickup_a_per_t.imag,
        float(np.angle(g)),
    ])


def params_from_theta(theta: np.ndarray, det: DetectorCalibration, **extra: Any) -> tuple[DetectorParams, Readout]:
    """``DetectorParams`` and ``Readout`` from a parameter vector.

    Raises ConfigError if the values are unphysical (e.g. ``|z0| >= R_n``).
    """
    th = dict(zip(PARAM_NAMES, (float(x) for x in theta)))
    p = DetectorParams(
        detector_id=det.detector_id,
        transition=ArctanTransition(t_c_k=th["t_c_k"], iqr_k=th["iqr_k"], r_n_ohm=th["r_n_ohm"]),
        k_w_per_k_n=th["k_w_per_k_n"],
        n=th["n"],
        z_thev_ohm=complex(th["z_re_ohm"], th["z_im_ohm"]),
        v_thev_v=th["v_thev_v"],
        t_bath_k=det.t_bath_k,
        p_opt_w=det.p_opt_w,
        t_c_shift_k_per_t=th["t_c_shift_k_per_t"],
        t_c_shift_k_per_t2=th["t_c_shift_k_per_t2"],
        pickup_a_per_t=complex(th["pickup_re_a_per_t"], th["pickup_im_a_per_t"]),
        gain_a_per_count=det.gain_abs_a_per_count * np.exp(1j * th["gain_phase_rad"]),
        **extra,
    )
    return p, Readout(det.bias_freq_hz, th["l_series_h"], th["r_slope_ohm"])


@dataclass(frozen=True)
class Design:
    """All points of one detector's sweeps, concatenated (every array shape (n,)).

    ``kind_index[j]`` is the index into ``sweeps`` of point j's sweep.
    """

    sweeps: tuple
    p_opt_w: np.ndarray
    b_field_t: np.ndarray
    bias_ratio: np.ndarray
    t_bath_k: np.ndarray
    freq_hz: np.ndarray
    probe: np.ndarray
    sweep_index: np.ndarray
    counts: np.ndarray
    sigma_counts: np.ndarray
    bias_freq_hz: float
    gain_abs_a_per_count: float

    @classmethod
    def from_detector(cls, det: DetectorCalibration, sweeps: tuple[Sweep, ...] | None = None) -> Design:
        sweeps = tuple(det.sweeps if sweeps is None else sweeps)
        if not sweeps:
            raise ConfigError(f"{det.detector_id}: no sweeps")
        cat = lambda name: np.concatenate([s.condition(name) for s in sweeps])  # noqa: E731
        return cls(
            sweeps=sweeps,
            p_opt_w=cat("p_opt_w"),
            b_field_t=cat("b_field_t"),
            bias_ratio=cat("bias_ratio"),
            t_bath_k=cat("t_bath_k"),
            freq_hz=cat("freq_hz"),
            probe=np.concatenate([np.full(len(s), s.kind in PROBE_KINDS) for s in sweeps]),
            sweep_index=np.concatenate([np.full(len(s), k) for k, s in enumerate(sweeps)]),
            counts=np.concatenate([s.counts for s in sweeps]),
            sigma_counts=np.concatenate([s.sigma_counts for s in sweeps]),
            bias_freq_hz=det.bias_freq_hz,
            gain_abs_a_per_count=det.gain_abs_a_per_count,
        )

    def __len__(self) -> int:
        return int(self.p_opt_w.size)


@dataclass(frozen=True)
class _Columns:
    """Duck-typed parameters for ``core.model``: each field broadcasts as (n_sets, 1) or (n_sets, n)."""

    transition: ArctanTransition
    k_w_per_k_n: np.ndarray
    n: np.ndarray
    z_thev_ohm: np.ndarray
    t_c_shift_k_per_t: np.ndarray
    t_c_shift_k_per_t2: np.ndarray
    current_shift_k_per_a: float = 0.0


def _probe_resistance(cols: _Columns, p_opt, t_bath, b, v, r_n):
    """R on the full transition (no latching) at a small probe bias.

    Fixed-point iteration on the TES temperature, ``T <- (T_b^n + (P + J(R(T)))/K)^(1/n)``,
    which contracts by the probe's loop gain (<< 1); points where it has not
    converged to rounding fall back to the bracketed root of the core power balance.
    """
    k, n, z = cols.k_w_per_k_n, cols.n, cols.z_thev_ohm
    shift = cols.t_c_shift_k_per_t * b + cols.t_c_shift_k_per_t2 * b * b
    base = t_bath**n + p_opt / k
    t = base ** (1.0 / n)
    r_min, r_max = _EDGE * r_n, (1.0 - _EDGE) * r_n
    bad = np.ones(np.shape(t), dtype=bool)
    for _ in range(_FIXED_POINT_ITER):
        r = np.clip(cols.transition.resistance_ohm(t - shift), r_min, r_max)
        t_new = (base + v**2 * r / (k * np.abs(r + z) ** 2)) ** (1.0 / n)
        bad = ~(np.abs(t_new - t) <= 1e-15 * t)
        t = t_new
        if not np.any(bad):
            break
    r = np.clip(cols.transition.resistance_ohm(t - shift), r_min, r_max)
    if np.any(bad):
        lo = np.broadcast_to(r_min, v.shape).copy()
        hi = np.broadcast_to(r_max, v.shape).copy()
        root = bracketed_root(lambda x: p_opt - power_of_resistance_w(cols, x, t_bath, b, v), lo, hi)
        r = np.where(bad, root, r)
    return r


def predict_counts(theta: np.ndarray, design: Design) -> np.ndarray:
    """Model DAN output for one or many parameter vectors.

    Parameters
    ----------
    theta : ndarray, shape (N_PARAMS,) or (n_sets, N_PARAMS)
    design : Design with n points

    Returns
    -------
    ndarray of complex, shape (n,) or (n_sets, n)
    """
    th = np.asarray(theta, dtype=float)
    single = th.ndim == 1
    th = np.atleast_2d(th)
    col = lambda name: th[:, _IX[name]][:, None]  # noqa: E731
    r_n = col("r_n_ohm")
    transition = ArctanTransition(t_c_k=col("t_c_k"), iqr_k=col("iqr_k"), r_n_ohm=r_n)
    z = z_of_omega(
        col("z_re_ohm") + 1j * col("z_im_ohm"), col("l_series_h"), col("r_slope_ohm"),
        design.bias_freq_hz, design.freq_hz[None, :],
    )
    v = col("v_thev_v") * design.bias_ratio[None, :]
    shape = v.shape
    r = np.empty(shape)
    for probe in (False, True):
        sel = design.probe == probe
        if not np.any(sel):
            continue
        cols = _Columns(transition, col("k_w_per_k_n"), col("n"), z[:, sel],
                        col("t_c_shift_k_per_t"), col("t_c_shift_k_per_t2"))
        p_opt, t_bath, b = (np.broadcast_to(a[sel], (shape[0], int(sel.sum())))
                            for a in (design.p_opt_w, design.t_bath_k, design.b_field_t))
        if probe:
            r[:, sel] = _probe_resistance(cols, p_opt, t_bath, b, v[:, sel], r_n)
        else:
            r[:, sel] = solve_operating_point(cols, p_opt, t_bath, b, v[:, sel]).r_ohm
    pickup = col("pickup_re_a_per_t") + 1j * col("pickup_im_a_per_t")
    i = SQRT2 * v / (r + z) + pickup * design.b_field_t[None, :]
    counts = i / (design.gain_abs_a_per_count * np.exp(1j * col("gain_phase_rad")))
    return counts[0] if single else counts
