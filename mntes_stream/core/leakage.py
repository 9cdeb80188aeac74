"""HWP 2f -> 4f leakage: the effective nonlinearity of a conversion, measured from its power (pure).

A rotating half-wave plate (or a chopped source) puts a line at ``2 f_HWP``
into a detector's optical power. A conversion ``P_x = f(P)`` of the counts
that is not exactly linear in the true power ``P`` up-converts it to
``4 f_HWP``. This module measures that from the converted power alone, with
the definitions of :mod:`mntes_stream.core.validation` (so the numbers agree
with ``mntes-stream validate``).

Relation (the paper's leading-order term)
-----------------------------------------
Expand the conversion about the loading P0,
``f(P0 + dP) = f(P0) + f' dP + f''/2 dP^2 + O(dP^3)``, and call
``eps = f'' / f'`` the effective nonlinearity (for the linear conversion the
paper's ``(d2I/dP2) / (dI/dP)``, compared with LiteBIRD's 0.014 pW^-1).
With ``dP = A cos(2 w t + phi)``, ``cos^2 = (1 + cos(4 w t + 2 phi)) / 2`` gives
a 4f line of complex amplitude ``a4 = f'' A^2 / 4 * exp(2 i phi)`` (in phase
with twice the 2f phase) next to the 2f line ``f' A exp(i phi)``, so::

    eps = 4 Re(a4 exp(-2 i phi)) / (f' A^2)

(in the notation ``P_x = P + e2 P^2``, ``e2 = f''/2 = 2 |a4| / A^2``: half of
``eps``). A line is a complex amplitude ``a`` with ``x(t) = Re(a exp(i w t))``.
``Re(...)`` is the in-phase part; the quadrature part (0 for a memoryless
``f``) is reported as a check. Higher orders change ``eps`` by a relative
``O((A / P_s)^2)``, ``P_s`` ~ 0.3 pW for paper Table 1 (0.1 % at 10 fW).

Two forms:

- :func:`leakage_between` ``(t, p_a, p_b)``: ``a4`` from the difference
  ``p_a - p_b``, ``A`` and ``phi`` from ``p_b``. With ``p_b`` the truth it is
  ``p_a``'s own nonlinearity (validation's measurement). With ``p_a`` the
  linear and ``p_b`` the MNTES conversion *of the same counts* it is the
  nonlinearity MNTES removed (linear's, to MNTES's residual): readout noise
  and any 4f line of the optical signal itself are in both and cancel.
- :func:`leakage_of` ``(t, p)``: the series' own 4f against its own 2f, an
  upper bound (a 4f line in the sky adds to it; readout noise limits it).

Noise: each line's complex amplitude is a least-squares fit (offset, trend,
harmonics 1-6 of f_HWP; flagged samples left out) and its 1-sigma per
quadrature is measured from the fit's residual at ``n_side`` independent
frequencies beside the line (steps of 1/window, away from every harmonic), so
coloured noise counts as it is at that frequency. In :func:`leakage_between`,
transients of the difference (a planet crossing, whose flagged top leaves
edges that spread over every frequency) are left out first. A 2f line weaker
than ``min_snr_2f`` sigma is no line: the result then has
``status = "no_2f_line"`` and no number. :func:`median_nl` sums detectors up:
a median, or a 3-sigma bound where they do not resolve their own.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from mntes_stream.core.validation import REQUIREMENT_PER_PW
from mntes_stream.errors import ConfigError

__all__ = [
    "REQUIREMENT_PER_PW",
    "STATUS_OK",
    "STATUS_NO_2F",
    "STATUS_TOO_SHORT",
    "Line",
    "Leakage",
    "fit_lines",
    "refine_f_hwp",
    "leakage_between",
    "leakage_of",
    "Median",
    "median_nl",
]

STATUS_OK = "ok"
STATUS_NO_2F = "no_2f_line"          # the reference has no 2f line above its noise: nothing to measure
STATUS_TOO_SHORT = "too_few_samples"  # fewer than a few HWP periods of usable samples

_HARMONICS = (1, 2, 3, 4, 5, 6)  # fitted together (as validation fits them); 1, 2, 4 are reported
_MIN_PERIODS = 8  # of f_HWP in the window: fewer cannot separate 1f from the trend


@dataclass(frozen=True)
class Line:
    """A fitted line: complex amplitude (W, ``x = Re(a exp(i w t))``) and the 1-sigma of each quadrature."""

    amplitude_w: complex
    sigma_w: float

    @property
    def snr(self) -> float:
        """``|a| / sigma`` (inf without noise)."""
        return abs(self.amplitude_w) / self.sigma_w if self.sigma_w > 0 else math.inf


@dataclass(frozen=True)
class Leakage:
    """The effective nonlinearity measured on one detector over one window.

    ``nl_per_w`` and ``sigma_nl_per_w`` are None unless ``status == "ok"``;
    ``resolved`` says whether ``|nl|`` exceeds 3 sigma (else quote the sigma,
    not the number). Lines: ``line_1f``, ``line_2f`` of the reference series,
    ``line_4f`` of the difference (of the series itself for :func:`leakage_of`).
    """

    status: str
    f_hwp_hz: float
    window_s: float
    n_samples: int
    line_1f: Line | None = None
    line_2f: Line | None = None
    line_4f: Line | None = None
    gain_2f: float = float("nan")          # f' from the 2f lines
    nl_per_w: float | None = None           # signed in-phase eps = f''/f'
    sigma_nl_per_w: float | None = None
    nl_quadrature_per_w: float | None = None
    n_masked: int = 0                       # samples left out as a transient of the difference

    @property
    def nl_per_pw(self) -> float | None:
        return None if self.nl_per_w is None else self.nl_per_w * 1e-12

    @property
    def sigma_nl_per_pw(self) -> float | None:
        return None if self.sigma_nl_per_w is None else self.sigma_nl_per_w * 1e-12

    @property
    def resolved(self) -> bool:
        return self.nl_per_w is not None and abs(self.nl_per_w) > 3.0 * (self.sigma_nl_per_w or 0.0)


def _usable(t_s, *series) -> tuple[np.ndarray, list[np.ndarray]]:
    t = np.asarray(t_s, dtype=float)
    xs = [np.asarray(x, dtype=float) for x in series]
    if any(x.shape != t.shape for x in xs) or t.ndim != 1:
        raise ConfigError(f"leakage: times {t.shape} and power {[x.shape for x in xs]} must be 1-D of one length")
    ok = np.isfinite(t)
    for x in xs:
        ok &= np.isfinite(x)
    return t[ok], [x[ok] for x in xs]


def _side_noise(t: np.ndarray, resid: np.ndarray, f_line_hz: float, f_hwp_hz: float, n_side: int) -> float:
    """1-sigma per quadrature of a line at ``f_line_hz``, from the residual at ``n_side`` frequencies beside it.

    The residual is shifted down by ``f_line_hz`` onto its sample grid (gaps as zeros) and Fourier
    transformed: bin k is the projection ``sum r exp(-i w t)`` at ``f_line + k / window``, independent
    bins 2, 3, ... out on both sides, skipping any within 1.5 bins of a harmonic of f_HWP. Beside the
    line it is noise alone, with the variance of the fitted line's quadratures (``2 sigma_r^2 / n`` for
    white noise), so coloured noise counts as it is at that frequency.
    """
    dt = float(np.median(np.diff(t)))
    idx = np.rint((t - t[0]) / dt).astype(np.int64)
    buf = np.zeros(int(idx[-1]) + 1, dtype=complex)
    buf[idx] = resid * np.exp(-2j * np.pi * f_line_hz * t)
    spec = np.fft.fft(buf)
    df = 1.0 / (buf.size * dt)
    vals = []
    for k in range(2, buf.size // 2):
        for kk in (k, -k):
            f = f_line_hz + kk * df
            if f > 2 * df and abs(f / f_hwp_hz - round(f / f_hwp_hz)) * f_hwp_hz >= 1.5 * df:
                vals.append(spec[kk])
        if len(vals) >= n_side:
            break
    if not vals:
        return float("nan")
    c = (2.0 / t.size) * np.array(vals[:n_side])
    return float(np.sqrt(np.mean(np.abs(c) ** 2) / 2.0))


def fit_lines(t_s, p_w, f_hwp_hz: float, harmonics=(1, 2, 4), n_side: int = 16) -> dict[int, Line]:
    """Complex amplitudes of harmonics of ``f_hwp_hz`` in ``p_w`` with their noise.

    Parameters
    ----------
    t_s, p_w : ndarray, shape (n,)
        Finite samples only (leave flagged ones out).
    f_hwp_hz : float
    harmonics : tuple of int
        Which lines to return (1..6 are fitted).
    n_side : int
        Residual frequencies per line for its noise.

    Returns
    -------
    dict
        ``{h: Line}``.
    """
    return _fit(t_s, p_w, f_hwp_hz, harmonics, n_side)[0]


def _fit(t_s, p_w, f_hwp_hz: float, harmonics, n_side: int) -> tuple[dict[int, Line], np.ndarray]:
    """:func:`fit_lines` and the fit's residual, shape (n,)."""
    t = np.asarray(t_s, dtype=float)
    x = np.asarray(p_w, dtype=float)
    # The model of validation.harmonic_amplitudes (offset, trend, harmonics 1-6), solved here for this
    # sample set: its cached solver is keyed by the grid's ends and length, not by which samples are left out.
    t0 = t - t.mean()
    cols = [np.ones_like(t), t0 / max(float(np.ptp(t)), 1e-30)]
    for h in _HARMONICS:
        w = 2 * np.pi * h * f_hwp_hz * t
        cols += [np.cos(w), np.sin(w)]
    design = np.column_stack(cols)
    # Normal equations: the columns are O(1) and nearly orthogonal over many periods (well conditioned),
    # and lstsq's SVD costs ~10x more; the series' median is taken out first for precision.
    x = x - np.median(x)
    coef = np.linalg.solve(design.T @ design, design.T @ x)
    resid = x - design @ coef
    amp = {h: complex(coef[2 + 2 * k], -coef[3 + 2 * k]) for k, h in enumerate(_HARMONICS)}
    return {h: Line(amp[h], _side_noise(t, resid, h * f_hwp_hz, f_hwp_hz, n_side)) for h in harmonics}, resid


def _transients(t: np.ndarray, resid: np.ndarray, clip: float, pad_s: float) -> np.ndarray:
    """Samples to leave out, shape (n,) bool: beyond ``clip`` robust sigmas of the residual, +-``pad_s`` around.

    A planet crossing (or a saturation) makes the two conversions differ by up to ~0.3 pW for a second,
    against fW of 2f: its edges, where flagged samples drop out, would spread over every frequency.
    """
    mad = float(np.median(np.abs(resid - np.median(resid))))
    if not mad > 0:
        return np.zeros(t.size, dtype=bool)
    hit = np.abs(resid) > clip * 1.4826 * mad
    if not hit.any():
        return hit
    edges = t[hit]
    k = np.searchsorted(edges, t)  # the nearest hit on each side
    left = np.abs(t - edges[np.clip(k - 1, 0, edges.size - 1)])
    right = np.abs(edges[np.clip(k, 0, edges.size - 1)] - t)
    return np.minimum(left, right) <= pad_s


def refine_f_hwp(t_s, p_w, f_guess_hz: float, span_bins: float = 3.0) -> float:
    """The HWP frequency that maximises the 2f line's power, near a coarse guess.

    A spectral estimate (the monitor's, :func:`mntes_stream.monitor.analysis.estimate_f_hwp`)
    is good to about a frequency bin, 1/window: at 4f that is a phase slip of
    several radians over the window. This searches ``f_guess +- span_bins /
    (2 window)`` on a grid a twentieth of a 2f bin fine, then interpolates the
    peak (parabola through the best three points). Only positive frequencies:
    a real series' 2f power is the same at -f, so a short window (a wide
    search) around a low guess would otherwise find the mirror line.

    Parameters
    ----------
    t_s : ndarray, shape (n,)
    p_w : ndarray, shape (n,) or (n_det, n)
        Several rows: their 2f powers are summed (NaN samples count as the row's mean).
    f_guess_hz : float

    Returns
    -------
    float
    """
    t = np.asarray(t_s, dtype=float)
    x = np.atleast_2d(np.asarray(p_w, dtype=float))
    if not f_guess_hz > 0 or t.size < 16:
        raise ConfigError(f"refine_f_hwp: need a positive guess and samples, got {f_guess_hz!r}, {t.size}")
    mean = np.nanmean(x, axis=1, keepdims=True)
    x = np.where(np.isfinite(x), x - mean, 0.0)
    x = x[np.any(x != 0, axis=1)]
    window_s = float(np.ptp(t))
    half = span_bins / (2.0 * window_s)
    step = 1.0 / (40.0 * window_s)
    grid = np.arange(f_guess_hz - half, f_guess_hz + half + step / 2, step)
    grid = grid[grid > step]  # f_guess > 0: still the span_bins / (2 window) above it, 60 points
    power = np.zeros(grid.size)
    for k, f in enumerate(grid):
        w = 4 * np.pi * f * t
        # Two real products, not x @ exp(-i w): a real matrix times a complex vector is no BLAS call
        # (~50x slower at 8 x 9,000, and it holds the GIL: the monitor's pages waited on it).
        power[k] = float(np.sum((x @ np.cos(w)) ** 2 + (x @ np.sin(w)) ** 2))
    i = int(np.clip(np.argmax(power), 1, grid.size - 2))
    y0, y1, y2 = power[i - 1], power[i], power[i + 1]
    denom = y0 - 2 * y1 + y2
    shift = 0.5 * (y0 - y2) / denom if denom < 0 else 0.0
    return float(grid[i] + np.clip(shift, -1.0, 1.0) * step)  # > 0: grid[i] > step


def _result(t, ref_lines, lines_4f, f_hwp_hz, min_snr_2f, gain_ref=None, n_masked=0) -> Leakage:
    window_s = float(np.ptp(t)) + float(np.median(np.diff(t)))
    l2 = ref_lines[2]
    base = dict(f_hwp_hz=float(f_hwp_hz), window_s=window_s, n_samples=int(t.size), n_masked=int(n_masked),
                line_1f=ref_lines[1], line_2f=l2, line_4f=lines_4f[4])
    if not l2.snr >= min_snr_2f:
        return Leakage(status=STATUS_NO_2F, **base)
    amp = abs(l2.amplitude_w)
    rot = np.conj(l2.amplitude_w / amp)  # exp(-i phi)
    gain = 1.0 + ((gain_ref * rot).real / amp if gain_ref is not None else 0.0)
    c4 = lines_4f[4].amplitude_w * rot * rot
    scale = 4.0 / (gain * amp * amp)
    eps = scale * c4.real
    # The 4f noise, and the 2f amplitude's (eps ~ 1/A^2), in quadrature.
    sigma = math.hypot(scale * lines_4f[4].sigma_w, 2.0 * eps * l2.sigma_w / amp)
    return Leakage(status=STATUS_OK, gain_2f=float(gain), nl_per_w=float(eps), sigma_nl_per_w=float(sigma),
                   nl_quadrature_per_w=float(scale * c4.imag), **base)


def _short(t, f_hwp_hz) -> Leakage | None:
    if not f_hwp_hz > 0:
        raise ConfigError(f"leakage: f_HWP must be > 0, got {f_hwp_hz!r}")
    window_s = float(np.ptp(t)) if t.size else 0.0
    if t.size < 64 or window_s * f_hwp_hz < _MIN_PERIODS:
        return Leakage(status=STATUS_TOO_SHORT, f_hwp_hz=float(f_hwp_hz), window_s=window_s, n_samples=int(t.size))
    return None


def leakage_between(t_s, p_a_w, p_b_w, f_hwp_hz: float, *, min_snr_2f: float = 10.0,
                    n_side: int = 16, clip: float = 8.0, pad_s: float = 1.0) -> Leakage:
    """Effective nonlinearity of ``p_a`` relative to the reference ``p_b`` (module docstring).

    Parameters
    ----------
    t_s : ndarray, shape (n,)
        Sample times (s).
    p_a_w, p_b_w : ndarray, shape (n,)
        Two power series on those times (W); samples not finite in either are left out.
        ``p_b`` is the reference: the truth, or the MNTES conversion of the same counts.
    f_hwp_hz : float
        HWP rotation frequency (the 2f line is at twice it).
    min_snr_2f : float
        The reference's 2f line must stand this many sigma above its noise.
    clip, pad_s : float
        Transients of the difference (a planet crossing, a saturation: ``|residual|`` beyond
        ``clip`` robust sigmas) are left out with ``pad_s`` either side (``n_masked``), then
        both series are fitted again; ``clip = inf`` keeps every sample.

    Returns
    -------
    Leakage
        ``nl_per_w``: ``4 Re(a4 exp(-2 i phi)) / (f' A^2)`` with ``a4`` the 4f line of
        ``p_a - p_b``, ``A exp(i phi)`` the 2f line of ``p_b`` and ``f' = 1 + Re(a2_diff exp(-i phi)) / A``.
    """
    t, (a, b) = _usable(t_s, p_a_w, p_b_w)
    short = _short(t, f_hwp_hz)
    if short is not None:
        return short
    diff, resid = _fit(t, a - b, f_hwp_hz, (2, 4), n_side)
    drop = _transients(t, resid, clip, pad_s) if math.isfinite(clip) else np.zeros(t.size, dtype=bool)
    if drop.any():
        t, a, b = t[~drop], a[~drop], b[~drop]
        short = _short(t, f_hwp_hz)
        if short is not None:
            return short
        diff = fit_lines(t, a - b, f_hwp_hz, (2, 4), n_side)
    ref = fit_lines(t, b, f_hwp_hz, (1, 2), n_side)
    return _result(t, ref, diff, f_hwp_hz, min_snr_2f, gain_ref=diff[2].amplitude_w, n_masked=int(drop.sum()))


def leakage_of(t_s, p_w, f_hwp_hz: float, *, min_snr_2f: float = 10.0, n_side: int = 16) -> Leakage:
    """Effective nonlinearity from one series' own 4f and 2f lines (``f' = 1``): an upper bound.

    Parameters and result as :func:`leakage_between`, with ``p_b = p`` for the 2f
    line and ``a4`` the 4f line of ``p`` itself (any 4f of the optical signal included).
    """
    t, (x,) = _usable(t_s, p_w)
    short = _short(t, f_hwp_hz)
    if short is not None:
        return short
    lines = fit_lines(t, x, f_hwp_hz, (1, 2, 4), n_side)
    return _result(t, lines, lines, f_hwp_hz, min_snr_2f)


@dataclass(frozen=True)
class Median:
    """The median effective nonlinearity over detectors (pW^-1), or a bound on it.

    ``value_per_pw`` is the median of ``|nl|`` over the detectors measured (status ok) when
    most of them resolve their own (``|nl| > 3 sigma``), else None: a median of ``|noise|``
    would be a noise floor, not a nonlinearity. ``sigma_per_pw`` is the median's 1-sigma,
    ``1.2533 median(sigma) / sqrt(n)`` (a median of n Gaussian estimates).
    ``bound_per_pw`` (3 sigma) holds either way: the detectors' true values have a mean
    square ``mean(nl^2 - sigma^2)`` (the noise's variance taken out; taken as 0 when negative),
    bounded by it plus 3 standard errors, and no median of ``|x|`` exceeds ``sqrt(2)`` times its rms
    (Markov: ``P(x^2 >= 2 rms^2) <= 1/2``). ``detector_sigma_per_pw``: the median
    per-detector 1-sigma (the resolution of one detector).
    """

    value_per_pw: float | None
    sigma_per_pw: float | None
    bound_per_pw: float | None
    detector_sigma_per_pw: float | None
    n_detectors: int
    n_resolved: int

    @property
    def resolved(self) -> bool:
        return self.value_per_pw is not None


def median_nl(results) -> Median:
    """:class:`Median` of a sequence of :class:`Leakage` (those without a number are left out)."""
    ok = [r for r in results if r.nl_per_w is not None]
    if not ok:
        return Median(None, None, None, None, 0, 0)
    n = len(ok)
    n_resolved = sum(r.resolved for r in ok)
    nl = np.array([r.nl_per_pw for r in ok])
    sig = np.array([r.sigma_nl_per_pw for r in ok])
    excess = nl**2 - sig**2
    se = float(np.std(excess, ddof=1)) / math.sqrt(n) if n > 1 else float(excess[0] + 2 * sig[0] ** 2)
    # A negative mean (noise over-estimated, or a fluctuation) never lowers the bound below 3 standard errors.
    bound = math.sqrt(2.0 * (max(float(np.mean(excess)), 0.0) + 3.0 * max(se, 0.0)))
    sigma = 1.2533 * float(np.median(sig)) / math.sqrt(n)
    value = float(np.median(np.abs(nl))) if 2 * n_resolved > n else None
    return Median(value, sigma, bound, float(np.median(sig)), n, n_resolved)
