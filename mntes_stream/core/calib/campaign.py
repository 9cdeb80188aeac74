"""Campaign-level results: pulls of fitted parameters against a truth (pure).

The parallel driver that fits a whole campaign is at the edge:
:func:`mntes_stream.reports.calib_run.fit_campaign`.
"""

from __future__ import annotations

import numpy as np

from mntes_stream.core.calib.fit import DetectorFit
from mntes_stream.core.calib.forward import PARAM_NAMES, theta_from_params
from mntes_stream.errors import ConfigError

__all__ = ["pulls"]


def pulls(fits: dict[str, DetectorFit], truth: dict) -> tuple[list[str], np.ndarray]:
    """``(fit - truth) / sigma`` per usable detector and parameter (phase difference wrapped).

    Parameters
    ----------
    truth : dict detector id -> (DetectorParams, Readout)

    Returns
    -------
    ids : list of str
    pulls : ndarray, shape (n_ok, N_PARAMS), columns in ``PARAM_NAMES`` order
    """
    ids = [d for d, f in fits.items() if f.ok]
    missing = [d for d in ids if d not in truth]
    if missing:
        raise ConfigError(f"no truth for detector(s) {missing[:5]} (mismatched ids)")
    phase = PARAM_NAMES.index("gain_phase_rad")
    rows = []
    for d in ids:
        diff = fits[d].theta - theta_from_params(*truth[d])
        diff[phase] = np.angle(np.exp(1j * diff[phase]))
        rows.append(diff / fits[d].sigma)
    return ids, np.array(rows).reshape(len(ids), len(PARAM_NAMES))
