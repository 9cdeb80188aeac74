"""Fit every detector of a calibration campaign in parallel worker processes.

An edge module: it starts processes. The per-detector fit is pure
(:func:`mntes_stream.core.calib.fit.fit_detector`).
"""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed

from mntes_stream.core.calib.fit import DetectorFit, FitOptions, fit_detector
from mntes_stream.core.calib.measurements import Campaign
from mntes_stream.errors import ConfigError

__all__ = ["fit_campaign"]


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
