"""Numerical helpers of the quick-look monitor: decimation, spectra, HWP harmonics.

Pure numpy/scipy, no I/O. Everything the page plots is reduced here, on the
server, to a few hundred points per trace, whatever the stream's rate.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "HARMONICS",
    "F_HWP_SEARCH_HZ",
    "decimate_minmax",
    "welch_psd",
    "log_bin",
    "hwp_harmonics_hz",
    "estimate_f_hwp",
]

#: HWP harmonics marked on the spectrum (1f, 2f, 4f).
HARMONICS = (1, 2, 4)
#: Where an estimated f_HWP is searched. Narrower than an octave, so a comb
#: with only its 2f line present cannot also match at f/2 or 2f; it covers
#: LiteBIRD's three rotation frequencies (0.65, 0.77, 1.02 Hz).
F_HWP_SEARCH_HZ = (0.55, 1.1)


def decimate_minmax(t: np.ndarray, y: np.ndarray, max_points: int) -> tuple[np.ndarray, np.ndarray]:
    """Reduce a trace to at most ``max_points`` points, keeping each bucket's min and max.

    Parameters
    ----------
    t : ndarray, shape (n,)
        Sample times (any unit, non-decreasing).
    y : ndarray, shape (n,) or (n_tr, n)
        Values; NaN (flagged samples) is ignored unless a whole bucket is NaN.
    max_points : int
        At least 2.

    Returns
    -------
    t_out : ndarray, shape (m,)
        Bucket times (the first sample time of each half bucket), m <= max_points.
    y_out : ndarray, shape (m,) or (n_tr, m)
        Per bucket the min then the max (in that order), so spikes stay visible.
    """
    t = np.asarray(t)
    y = np.asarray(y, dtype=np.float64)
    one = y.ndim == 1
    y2 = y[None, :] if one else y
    n = t.size
    if n <= max_points:
        return t.copy(), (y2[0] if one else y2).copy()
    n_buckets = max(max_points // 2, 1)
    size = -(-n // n_buckets)  # ceil: every bucket but the last is full
    starts = np.arange(0, n, size)
    lo = np.fmin.reduceat(y2, starts, axis=1)  # fmin ignores NaN unless all are NaN
    hi = np.fmax.reduceat(y2, starts, axis=1)
    half = np.minimum(starts + size // 2, n - 1)
    t_out = np.empty(2 * starts.size, dtype=t.dtype)
    t_out[0::2] = t[starts]
    t_out[1::2] = t[half]
    y_out = np.empty((y2.shape[0], 2 * starts.size))
    y_out[:, 0::2] = lo
    y_out[:, 1::2] = hi
    return t_out, (y_out[0] if one else y_out)


def welch_psd(y: np.ndarray, fs_hz: float, segments: int = 3) -> tuple[np.ndarray, np.ndarray]:
    """One-sided Welch PSD of each row, Hann windows of a power-of-two length, 50% overlap.

    Parameters
    ----------
    y : ndarray, shape (n_tr, n)
        Power samples (W); NaN samples are replaced by the row's mean
        (rows with fewer than half their samples finite give NaN PSD).
    fs_hz : float
    segments : int
        At least this many half-overlapping segments: the segment is the
        longest power of two <= ``2 n / (segments + 1)``. 3 averages noise
        for display; 1 gives the finest resolution (for locating lines).

    Returns
    -------
    f_hz : ndarray, shape (n_f,)
    psd : ndarray, shape (n_tr, n_f)
        W^2/Hz.
    """
    y = np.atleast_2d(np.asarray(y, dtype=np.float64))
    n = y.shape[1]
    if n < 16:
        return np.zeros(0), np.zeros((y.shape[0], 0))
    limit = 2 * n // (max(int(segments), 1) + 1)
    nperseg = 1 << max(int(np.floor(np.log2(max(limit, 8)))), 3)
    finite = np.isfinite(y)
    good = finite.sum(axis=1) >= n / 2
    filled = np.where(finite, y, 0.0)
    mean = filled.sum(axis=1) / np.maximum(finite.sum(axis=1), 1)
    filled = np.where(finite, y, mean[:, None])
    from scipy import signal  # here: scipy.signal costs every service's start ~0.4 s, only the monitor needs it

    f, p = signal.welch(filled, fs=fs_hz, window="hann", nperseg=nperseg, noverlap=nperseg // 2, axis=-1)
    p[~good] = np.nan
    return f, p


def log_bin(f_hz: np.ndarray, psd: np.ndarray, n_out: int) -> tuple[np.ndarray, np.ndarray]:
    """Average a spectrum into ``n_out`` log-spaced bands (the DC bin is dropped).

    Bands narrower than the bin spacing keep single bins, so low frequencies
    (the HWP lines) stay at full resolution while the white-noise tail is
    thinned.

    Parameters
    ----------
    f_hz : ndarray, shape (n_f,)
    psd : ndarray, shape (n_tr, n_f)
    n_out : int

    Returns
    -------
    f_out : ndarray, shape (m,), m <= n_out
        Mean frequency of the bins in each non-empty band.
    psd_out : ndarray, shape (n_tr, m)
    """
    f_hz = np.asarray(f_hz)
    psd = np.atleast_2d(psd)
    keep = f_hz > 0
    f, p = f_hz[keep], psd[:, keep]
    if f.size <= n_out:
        return f, p
    edges = np.geomspace(f[0], f[-1] * (1 + 1e-12), n_out + 1)
    band = np.clip(np.searchsorted(edges, f, side="right") - 1, 0, n_out - 1)
    starts = np.flatnonzero(np.r_[True, band[1:] != band[:-1]])
    counts = np.diff(np.r_[starts, f.size])
    f_out = np.add.reduceat(f, starts) / counts
    p_out = np.add.reduceat(p, starts, axis=1) / counts
    return f_out, p_out


def hwp_harmonics_hz(f_hwp_hz: float) -> list[float]:
    """Frequencies of the marked harmonics (:data:`HARMONICS`) of ``f_hwp_hz``."""
    return [h * float(f_hwp_hz) for h in HARMONICS]


def estimate_f_hwp(
    f_hz: np.ndarray,
    psd: np.ndarray,
    search_hz: tuple[float, float] = F_HWP_SEARCH_HZ,
    min_excess: float = 10.0,
) -> float | None:
    """The HWP frequency whose 1f/2f/4f comb stands highest above the noise floor.

    None when there is no comb, or when the frequency resolution is coarser
    than a quarter of the search range's low end (too little data: lines
    would merge with each other and with DC).

    Score of a candidate f: the sum over h in (1, 2, 4) of ``log(P(h f) / floor(h f))``
    clipped at 0, with the floor a running median of P (lines are narrow, the
    floor is not) and P interpolated in log. Candidates step by a tenth of
    the frequency resolution across ``search_hz``.

    Parameters
    ----------
    f_hz : ndarray, shape (n_f,)
        Linear frequency grid (Welch output).
    psd : ndarray, shape (n_f,) or (n_tr, n_f)
        Several rows are combined by their median after dividing each by its floor.
    search_hz : (float, float)
    min_excess : float
        The best comb's strongest line must exceed the floor by this factor,
        else there is no HWP signal to lock on and None is returned.

    Returns
    -------
    float or None
    """
    f_hz = np.asarray(f_hz, dtype=np.float64)
    p = np.atleast_2d(np.asarray(psd, dtype=np.float64))
    p = p[np.all(np.isfinite(p), axis=1) & np.all(p > 0, axis=1)]
    if p.shape[0] == 0 or f_hz.size < 32:
        return None
    df = f_hz[1] - f_hz[0]
    if df > search_hz[0] / 4:
        return None
    size = max(int(round(0.5 / df)) | 1, 9)  # a 0.5 Hz window: several times a line's width
    from scipy.ndimage import median_filter

    floor = median_filter(p, size=(1, size), mode="nearest")
    excess = np.log(np.median(p / floor, axis=0))
    lo, hi = search_hz
    hi = min(hi, f_hz[-1] / max(HARMONICS))
    if not hi > lo:
        return None
    cand = np.arange(lo, hi, df / 10)
    score = np.zeros_like(cand)
    best_line = np.full_like(cand, -np.inf)
    for h in HARMONICS:
        e = np.interp(h * cand, f_hz, excess)
        score += np.clip(e, 0, None)
        best_line = np.maximum(best_line, e)
    i = int(np.argmax(score))
    if best_line[i] < np.log(min_excess):
        return None
    return float(cand[i])
