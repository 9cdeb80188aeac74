"""End to end: HWP 2f signal -> counts (TRUE parameters) -> power (FITTED parameters).

The requirement (paper section 2, 0.014 pW^-1) is on the leakage of the
half-wave-plate signal at 2 f_HWP into 4 f_HWP. Writing the reconstructed
power as ``P_rec = P + (eps/2) dP^2`` with ``dP = A cos(theta)``:
``dP^2 = (A^2/2)(1 + cos 2 theta)``, so the 4f line has amplitude
``a4 = eps A^2 / 4`` and ``eps_eff = 4 a4 / A^2`` (divided by the 2f gain
``f'``, which is 1 up to the calibration's gain error). The harmonic analysis is
``core.validation.effective_nonlinearity`` (one definition for the project).

Each true detector sees ``P0 + A cos(4 pi f_HWP t)`` on its nominal loading,
at nominal bath temperature, zero field and its tuned bias; its noise-free
counts (``i / g_true``) go through ``core.convert.make_converter(kind, fitted)``
exactly as flight data would.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from mntes_stream.core.convert import EnvironmentBlock, make_converter
from mntes_stream.core.model import readout_current_a, solve_operating_point
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.validation import REQUIREMENT_PER_PW, Nonlinearity, effective_nonlinearity
from mntes_stream.errors import ConfigError

__all__ = ["REQUIREMENT_PER_PW", "hwp_counts", "calibration_nonlinearity"]


def hwp_counts(true: list[DetectorParams], amplitude_w: float = 0.1e-12, n_samples: int = 64,
               f_hwp_hz: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noise-free counts of the true detectors over one HWP rotation.

    Returns
    -------
    t_s : ndarray, shape (n_samples,)
    p_true_w : ndarray, shape (n_det, n_samples)
    counts : ndarray of complex, shape (n_det, n_samples)
        ``I + 1j Q`` as floats (no quantisation: the check is of the calibration alone).
    """
    t = np.arange(n_samples) / (n_samples * f_hwp_hz)
    dp = amplitude_w * np.cos(4 * np.pi * f_hwp_hz * t)
    p_true = np.array([p.p_opt_w + dp for p in true])
    counts = np.empty(p_true.shape, complex)
    for k, p in enumerate(true):
        op = solve_operating_point(p, p_true[k])
        if np.any(op.state != 0):
            raise ConfigError(f"{p.detector_id}: the HWP signal leaves the transition")
        counts[k] = readout_current_a(p, op.i_a) / p.gain_a_per_count
    return t, p_true, counts


def calibration_nonlinearity(
    truth: Mapping[str, DetectorParams],
    fitted: Mapping[str, DetectorParams],
    kind: str = "table",
    amplitude_w: float = 0.1e-12,
    n_samples: int = 64,
) -> dict[str, Nonlinearity]:
    """Effective nonlinearity left by converting with ``fitted`` what ``truth`` produced.

    Parameters
    ----------
    truth, fitted : mapping detector id -> DetectorParams
        Every fitted detector must have a truth.
    kind : str
        ``core.convert`` converter kind ("table", "exact", "linear", ...).

    Returns
    -------
    dict detector id -> core.validation.Nonlinearity
    """
    missing = sorted(set(fitted) - set(truth))
    if missing:
        raise ConfigError(f"no truth for fitted detector(s) {missing[:5]}{'...' if len(missing) > 5 else ''}")
    ids = list(fitted)
    f_hwp = 1.0
    t, p_true, counts = hwp_counts([truth[d] for d in ids], amplitude_w, n_samples, f_hwp)
    converter = make_converter(kind, dict(fitted))
    env = EnvironmentBlock(
        t_bath_k=np.array([fitted[d].t_bath_k for d in ids])[:, None] * np.ones(n_samples),
        b_field_t=np.zeros(n_samples),
    )
    block = converter.convert(ids, np.ascontiguousarray(counts.real), np.ascontiguousarray(counts.imag), env)
    out = {}
    for k, det_id in enumerate(ids):
        if not np.all(np.isfinite(block.p_opt_w[k])):
            raise ConfigError(f"{det_id}: conversion flagged samples of the HWP signal (flags {np.unique(block.flags[k])})")
        out[det_id] = effective_nonlinearity(t, p_true[k], block.p_opt_w[k], f_hwp)
    return out
