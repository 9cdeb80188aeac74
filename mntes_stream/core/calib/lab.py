"""The lab's own calibration (IV and bias-step results) against the MNTES model: check and seed (pure).

A lab characterises its detectors with IV curves and bias steps (Simons
Observatory: sodetlib's analyses, stored by sotodlib's ``det_cal`` pipeline
as a ``ResultSet`` per observation; ``io/sotodlib_cal.py`` reads it). Those
numbers are quantities the MNTES model predicts from a detector's parameters:

- ``r_n_ohm``: the transition's normal resistance;
- ``p_sat_w``: sotodlib's "saturation power", the electrical bias power of a
  dark IV where R = 0.9 R_n: ``K (T^n - T_bath^n)`` at that R with no
  optical power (``T`` at the IV's current there, found by iteration when the
  transition depends on current);
- ``r_frac``, ``loop_gain``, ``s_i_per_v``, ``p_bias_w``: at the operating
  point (the detector's nominal loading, bath and bias): R / R_n, the
  electrothermal loop gain, the current responsivity magnitude (RMS current
  per watt: an AC-biased TES's peak responsivity over sqrt(2)) and the Joule power.

:func:`compare` gives, per quantity the lab measured, the model's value and
the relative disagreement; :func:`seed` takes R_n (arctan transitions) and K
(from P_sat) from the lab as a starting point for the MNTES fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mntes_stream.core import model
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.transition import ArctanTransition
from mntes_stream.errors import ConfigError

__all__ = ["LAB_QUANTITIES", "LabCalibration", "mntes_predictions", "compare", "seed", "IV_P_SAT_R_FRAC"]

# sotodlib's P_sat: the bias power where the IV reaches this fraction of R_n.
IV_P_SAT_R_FRAC = 0.9
LAB_QUANTITIES = ("r_n_ohm", "p_sat_w", "r_frac", "loop_gain", "s_i_per_v", "p_bias_w")


@dataclass(frozen=True)
class LabCalibration:
    """One detector's IV and bias-step results (NaN: not measured).

    Attributes
    ----------
    detector_id : str
    r_n_ohm, p_sat_w, r_frac, loop_gain, s_i_per_v, p_bias_w : float
        See the module docstring; ``s_i_per_v`` as a magnitude (A/W = 1/V).
    source : str
        Where it came from (file and dataset).
    """

    detector_id: str
    r_n_ohm: float = math.nan
    p_sat_w: float = math.nan
    r_frac: float = math.nan
    loop_gain: float = math.nan
    s_i_per_v: float = math.nan
    p_bias_w: float = math.nan
    source: str = ""

    def measured(self) -> dict[str, float]:
        """The quantities the lab gave (finite values only)."""
        return {k: float(getattr(self, k)) for k in LAB_QUANTITIES if math.isfinite(getattr(self, k))}


def _iv_p_sat_w(p: DetectorParams, t_bath_k: float, r_frac: float = IV_P_SAT_R_FRAC) -> float:
    """Bias power of a dark IV at ``R = r_frac R_n``: ``K (T^n - T_bath^n)`` with T at the IV's current."""
    r = r_frac * float(p.transition.r_normal_ohm)
    p_j = 0.0
    for _ in range(50):  # |I| depends on P_J through the current shift: a contraction for physical gamma
        i_abs = math.sqrt(2.0 * p_j / r) if p_j > 0 else 0.0
        t = float(model.effective_temperature_k(p, r, i_abs, 0.0))
        new = p.k_w_per_k_n * (max(t, 0.0) ** p.n - t_bath_k**p.n)
        if abs(new - p_j) <= 1e-12 * abs(new):
            return float(new)
        p_j = new
    return float(p_j)


def mntes_predictions(p: DetectorParams) -> dict[str, float]:
    """What the model says the lab should measure (see the module docstring).

    The operating-point quantities are NaN when the nominal point is off the transition.
    """
    out = {"r_n_ohm": float(p.transition.r_normal_ohm), "p_sat_w": _iv_p_sat_w(p, p.t_bath_k)}
    op = model.solve_operating_point(p, p.p_opt_w, p.t_bath_k, 0.0, p.v_thev_v)
    if int(op.state) != model.STATE_TRANSITION:
        return {**out, **{k: math.nan for k in ("r_frac", "loop_gain", "s_i_per_v", "p_bias_w")}}
    r0 = float(op.r_ohm)
    ss = model.small_signal(p, r0)
    out.update({
        "r_frac": r0 / out["r_n_ohm"],
        "loop_gain": float(ss.loop_gain),
        "s_i_per_v": float(abs(complex(ss.responsivity_a_per_w))) / model.SQRT2,
        "p_bias_w": float(model.joule_power_w(p, r0)),
    })
    return out


def compare(p: DetectorParams, lab: LabCalibration) -> dict[str, dict[str, float]]:
    """Per quantity the lab measured: ``{"lab", "mntes", "rel_diff"}`` (``(mntes - lab) / |lab|``)."""
    if lab.detector_id != p.detector_id:
        raise ConfigError(f"lab calibration of {lab.detector_id!r} compared with parameters of {p.detector_id!r}")
    pred = mntes_predictions(p)
    out = {}
    for k, v in lab.measured().items():
        m = pred[k]
        out[k] = {"lab": v, "mntes": m, "rel_diff": (m - v) / abs(v) if v != 0 else math.inf}
    return out


def seed(p: DetectorParams, lab: LabCalibration) -> DetectorParams:
    """``p`` with R_n (arctan transitions) and K (so the model's IV P_sat is the lab's) taken from the lab.

    Raises
    ------
    ConfigError
        A lab R_n for a tabulated transition (its curve carries its own R_n).
    """
    q = p
    if math.isfinite(lab.r_n_ohm):
        if not isinstance(p.transition, ArctanTransition):
            raise ConfigError(f"{p.detector_id}: the lab's R_n seeds only an arctan transition")
        q = q.replace(r_n_ohm=float(lab.r_n_ohm))
    if math.isfinite(lab.p_sat_w):
        if not lab.p_sat_w > 0:
            raise ConfigError(f"{p.detector_id}: lab P_sat must be > 0 W, got {lab.p_sat_w}")
        for _ in range(20):  # P_sat is proportional to K but for the current shift: a few ratios converge
            ratio = lab.p_sat_w / _iv_p_sat_w(q, q.t_bath_k)
            q = q.replace(k_w_per_k_n=q.k_w_per_k_n * ratio)
            if abs(ratio - 1.0) < 1e-12:
                break
    return q


def table(results: dict[str, dict[str, dict[str, float]]]) -> dict[str, dict[str, float]]:
    """Per quantity over detectors: median and largest absolute relative disagreement, and how many."""
    out = {}
    for k in LAB_QUANTITIES:
        d = np.array([r[k]["rel_diff"] for r in results.values() if k in r], dtype=float)
        if d.size:
            out[k] = {"n": int(d.size), "median_rel_diff": float(np.median(d)),
                      "max_abs_rel_diff": float(np.max(np.abs(d)))}
    return out
