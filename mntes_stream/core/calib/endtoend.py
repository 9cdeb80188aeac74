"""End-to-end check of a calibration: HWP 2f signal -> counts (truth) -> power (fitted).

The science requirement (paper section 2, 0.014 pW^-1) is on the leakage of
the half-wave-plate signal at 2 f_HWP into 4 f_HWP. Write the reconstructed
power as ``P_rec = P + (eps/2) dP^2`` (eps in 1/W: the effective nonlinearity
left after conversion) with ``dP = A cos(theta)``, ``theta = 2 omega_HWP t``.
Then ``dP^2 = (A^2/2) (1 + cos 2 theta)``, so the 4f line has amplitude
``a4 = eps A^2 / 4``, i.e.::

    eps_eff = 4 a4 / A^2

For the linear conversion ``P = P0 + dI / S`` this gives back the paper's
leading-order nonlinearity ``(d2I/dP2) / S``; for MNTES with exact parameters
it is zero; with fitted parameters it measures what the calibration errors leave.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from mntes_stream.core.model import invert_current, readout_current_a, solve_operating_point, small_signal
from mntes_stream.core.params import DetectorParams
from mntes_stream.errors import ConfigError

__all__ = ["REQUIREMENT_PER_W", "HwpResult", "hwp_harmonics", "hwp_counts", "effective_nonlinearity",
           "exact_converter", "linear_converter"]

REQUIREMENT_PER_W = 0.014e12  # 0.014 pW^-1


@dataclass(frozen=True)
class HwpResult:
    """Harmonics of the reconstructed power over one HWP 2f period.

    Attributes
    ----------
    eps_eff_per_w : float
        ``4 a4 / A^2`` with the sign of the 4f cosine term (1/W).
    a2_w, a4_w : float
        Amplitudes of the 2f and 4f lines of the reconstructed power.
    gain_error : float
        ``a2 / A - 1``: the calibration's responsivity error at 2f.
    offset_w : float
        Mean reconstructed minus mean true power.
    """

    eps_eff_per_w: float
    a2_w: float
    a4_w: float
    gain_error: float
    offset_w: float

    @property
    def eps_eff_per_pw(self) -> float:
        return self.eps_eff_per_w * 1e-12


def hwp_harmonics(p_true_w: np.ndarray, p_rec_w: np.ndarray, amplitude_w: float) -> HwpResult:
    """Harmonics of ``p_rec_w`` sampled uniformly over one period of ``theta`` (shape (n,))."""
    p_rec = np.asarray(p_rec_w, dtype=float)
    if not np.all(np.isfinite(p_rec)):
        raise ConfigError("reconstructed power has non-finite samples (outside the calibrated transition?)")
    n = p_rec.size
    theta = 2 * np.pi * np.arange(n) / n
    c2 = 2.0 / n * np.sum(p_rec * np.exp(-1j * theta))
    c4 = 2.0 / n * np.sum(p_rec * np.exp(-2j * theta))
    return HwpResult(
        eps_eff_per_w=float(4.0 * c4.real / amplitude_w**2),
        a2_w=float(abs(c2)),
        a4_w=float(abs(c4)),
        gain_error=float(c2.real / amplitude_w - 1.0),
        offset_w=float(np.mean(p_rec) - np.mean(p_true_w)),
    )


def hwp_counts(true: DetectorParams, amplitude_w: float = 0.1e-12, n_phase: int = 64):
    """Noise-free counts of the true detector seeing ``P0 + A cos(theta)`` on nominal loading.

    Returns
    -------
    p_true_w : ndarray, shape (n_phase,)
    counts : ndarray of complex, shape (n_phase,)
    """
    theta = 2 * np.pi * np.arange(n_phase) / n_phase
    p_true = true.p_opt_w + amplitude_w * np.cos(theta)
    op = solve_operating_point(true, p_true)
    if np.any(op.state != 0):
        raise ConfigError(f"{true.detector_id}: the HWP signal leaves the transition")
    return p_true, readout_current_a(true, op.i_a) / true.gain_a_per_count


def exact_converter(params: DetectorParams) -> Callable[[np.ndarray], np.ndarray]:
    """Counts -> power with the exact per-sample inverse at the nominal environment."""
    def convert(counts):
        return invert_current(params, np.asarray(counts) * params.gain_a_per_count).p_opt_w
    return convert


def linear_converter(params: DetectorParams) -> Callable[[np.ndarray], np.ndarray]:
    """The baseline: ``P = P0 + Re(dI conj(S)) / |S|^2`` at the nominal operating point."""
    op = solve_operating_point(params, params.p_opt_w)
    s = small_signal(params, op.r_ohm).di_dp_a_per_w
    i0 = readout_current_a(params, op.i_a)

    def convert(counts):
        di = np.asarray(counts) * params.gain_a_per_count - i0
        return params.p_opt_w + (di * np.conj(s)).real / abs(s) ** 2
    return convert


def effective_nonlinearity(true: DetectorParams, convert: Callable[[np.ndarray], np.ndarray],
                           amplitude_w: float = 0.1e-12, n_phase: int = 64) -> HwpResult:
    """Forward with the TRUE parameters, reconstruct with ``convert`` (counts -> W)."""
    p_true, counts = hwp_counts(true, amplitude_w, n_phase)
    return hwp_harmonics(p_true, convert(counts), amplitude_w)
