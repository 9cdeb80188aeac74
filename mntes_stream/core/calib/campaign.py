"""Fit every detector of a campaign, in parallel worker processes."""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed

import numpy as np

from mntes_stream.core.calib.fit import DetectorFit, FitOptions, fit_detector
from mntes_stream.core.calib.forward import PARAM_NAMES, theta_from_params
from mntes_stream.core.calib.measurements import Campaign
from mntes_stream.errors import ConfigError

__all__ = ["fit_campaign", "pulls"]


def fit_campaign(
    campaign: Campaign,
    options: FitOptions = FitOptions(),
    workers: int = 1,
    progress: Callable[[Iterable, int], Iterable] | None = None,
) -> dict[str, DetectorFit]:
    """Fit all detectors; results in campaign order, orphans as ``failed``.

    Parameters
    ----------
    workers : int
        Worker processes (``spawn`` start method: safe next to zenoh sessions
        and threads); 1 fits in this process.
    progress : callable, optional
        ``progress(iterable, total)`` wrapping the stream of finished fits,
        e.g. ``lambda it, total: tqdm(it, total=total)``.
    """
    if workers < 1:
        raise ConfigError("workers must be >= 1")
    dets = list(campaign.detectors.values())
    wrap = progress or (lambda it, total: it)
    done: dict[str, DetectorFit] = {}
    if workers == 1 or len(dets) <= 1:
        for fit in wrap((fit_detector(d, options) for d in dets), len(dets)):
            done[fit.detector_id] = fit
    else:
        ctx = multiprocessing.get_context("spawn")
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool:
            futures = [pool.submit(fit_detector, d, options) for d in dets]
            for fut in wrap(as_completed(futures), len(futures)):
                fit = fut.result()
                done[fit.detector_id] = fit
    out = {d.detector_id: done[d.detector_id] for d in dets}
    for det_id, reason in campaign.orphans.items():
        out[det_id] = DetectorFit(det_id, "failed", (reason,))
    return out


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
