"""Per-sample power uncertainty sigma_P and the LOW_RESPONSIVITY flag (pure, no I/O).

Readout noise ``sigma_i`` per quadrature (white readout noise and the counts'
quantisation ``|g| / sqrt(12)``, added in quadrature) moves the measured
complex current ``i``; the converter reads ``P(i)`` through
``R = Re(sqrt(2) V / i - z)`` and ``|i|``::

    P = K (T_s(R) + delta - gamma |i|)^n - K T_bath^n - V^2 R / |R + z|^2

so with isotropic noise on I and Q::

    sigma_P = sigma_i |grad_i P|,
    |grad_i P|^2 = A^2 (sqrt(2) V / |i|^2)^2 + B^2 - 2 A B (R + Re z) / |i|

with ``A = dP/dR`` at fixed ``|i|`` and ``B = dP/d|i| = -K n T^(n-1) gamma``.
Without a current shift this is ``sigma_i / |dI/dP|`` along the response
curve (the responsivity); with one it is the inverse's own gradient (never
below ``sigma_i / |dI/dP|``). Bath temperature does not enter.

Where the responsivity falls (the top of the transition), sigma_P grows far
above the detector's nominal ``sigma_P`` at its operating point: such a
sample gets ``LOW_RESPONSIVITY`` (a warning bit; with
``low_responsivity_unusable`` its value is dropped too) where sigma_P
exceeds ``sigma_p_factor`` times the nominal, or ``sigma_p_tolerance_w``
when that is set.

Two routes give the same number: :func:`sigma_p_model` from the model
(numpy, every kind: the detector's physics at the sample's measured state)
and, for the ``"table"`` kind, a compiled kernel reading the converter's own
table bank (``W = K T_s^n``, its slope and ``U = 1/T_s``), at kernel speed.
Computed only when asked (:func:`sigma_p_block`).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from mntes_stream.core import _uncertainty_kernel as _uk
from mntes_stream.core import flags as fl
from mntes_stream.core import model
from mntes_stream.core._kernels import LOW_COLS, binomials, w1_screenable
from mntes_stream.core.ids import parse_detector_id
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.settings import Settings, setting
from mntes_stream.errors import ConfigError, SchemaError

__all__ = [
    "SIGMA_P_FACTOR",
    "UncertaintySettings",
    "NoiseModel",
    "Uncertainty",
    "noise_model",
    "total_sigma_i_a",
    "sigma_p_model",
    "nominal_sigma_p_w",
    "nominal_gradients",
    "sigma_p_block",
    "low_responsivity_block",
    "module_key",
    "white_noise_counts",
    "NoiseWindow",
    "NOISE_FILE_FORMAT",
]

NOISE_FILE_FORMAT = "mntes-noise"

SIGMA_P_FACTOR = 3.0
_RAIL = float(2**31 - 1)  # counts at the int32 rails: ADC saturation or "no data" (core.convert)
SQRT2 = model.SQRT2


@dataclass(frozen=True)
class UncertaintySettings(Settings):
    """The readout noise the converter assumes, and when a sample's noise is too large."""

    readout_noise_a: float = setting(
        model.DEFAULT_READOUT_NOISE_A,
        "white readout noise per quadrature and sample (peak A rms, quantisation excluded); default: the DfMux's "
        "10 pA/sqrt(Hz) over the Nyquist band at 152.6 Hz (2.76e-11 A)", unit="A", ge=0)
    sigma_p_factor: float = setting(
        SIGMA_P_FACTOR, "LOW_RESPONSIVITY where sigma_P exceeds this multiple of the detector's nominal sigma_P "
        "(at its operating point)", gt=1)
    sigma_p_tolerance_w: float | None = setting(
        None, "LOW_RESPONSIVITY where sigma_P exceeds this absolute tolerance instead of the factor", unit="W", gt=0)
    low_responsivity_unusable: bool = setting(
        False, "a LOW_RESPONSIVITY sample loses its value (NaN) as an unusable flag would; default: a warning")
    noise_file: str | None = setting(
        None, "measured readout noise per detector or module (mntes-stream noise RUN --out FILE); where it names "
        "neither, readout_noise_a", path=True)
    readout_noise: str = setting(
        "configured", "the noise LOW_RESPONSIVITY's tolerance and sigma_P use: 'configured' (noise_file, else "
        "readout_noise_a) or 'measured' (each channel's white noise measured live from its counts over "
        "noise_window_samples, the configured one until then)", choices=("configured", "measured"))
    noise_window_samples: int = setting(
        4096, "'measured': second differences (I and Q pooled) per channel behind each live estimate", ge=64)


def module_key(detector_id: str) -> str | None:
    """``"b<board>m<module>"`` of a detector id of the readout's form, else None.

    >>> module_key("b0m3c007"), module_key("pixel7")
    ('b0m3', None)"""
    try:
        b, m, _ = parse_detector_id(detector_id)
    except ConfigError:
        return None
    return f"b{b}m{m}"


def white_noise_counts(x: np.ndarray, clip: float = 6.0) -> tuple[np.ndarray, np.ndarray]:
    """White noise per sample of each row of counts, quantisation removed: ``(sigma, n_used)``.

    Second differences ``x[k+1] - 2 x[k] + x[k-1]`` remove offsets, drifts and
    slow signals (an HWP line moves them by ``(2 pi f / f_s)^2`` of its
    amplitude); their variance is ``6 sigma^2`` for white noise. Outliers
    (glitches, steps) beyond ``clip`` robust sigma (from the median absolute
    deviation) are left out. The counts' rounding (``1/12`` count^2 per
    sample) is subtracted: what is left is the readout noise a converter is told.

    Parameters
    ----------
    x : ndarray (n_rows, n_samp)
        Counts of one contiguous stretch (no gaps inside).

    Returns
    -------
    sigma : ndarray (n_rows,)
        Counts rms per sample; NaN for a row with fewer than 3 finite samples.
    n_used : ndarray of int (n_rows,)
        Second differences used.
    """
    x = np.asarray(x, dtype=float)
    if x.ndim != 2:
        raise SchemaError(f"counts: expected shape (n_rows, n_samp), got {x.shape}")
    d2 = x[:, 2:] - 2.0 * x[:, 1:-1] + x[:, :-2]
    sigma = np.full(x.shape[0], np.nan)
    used = np.zeros(x.shape[0], dtype=np.int64)
    for k in range(x.shape[0]):
        d = d2[k][np.isfinite(d2[k])]
        if d.size < 1:
            continue
        med = float(np.median(d))
        # At least one count: integer differences of a quiet channel have a MAD of 0.
        s0 = max(1.4826 * float(np.median(np.abs(d - med))), 1.0)
        kept = d[np.abs(d - med) <= clip * s0]
        used[k] = kept.size
        sigma[k] = math.sqrt(max(float(np.mean((kept - kept.mean()) ** 2)) / 6.0 - 1.0 / 12.0, 0.0))
    return sigma, used


class NoiseWindow:
    """Each detector's white noise measured live from its counts: :func:`white_noise_counts`'s estimate,
    accumulated chunk by chunk over a window.

    Per chunk and row: second differences of I and of Q (within the chunk: a gap between chunks never
    enters), those beyond ``clip`` robust sigma of the chunk's own (median absolute deviation, at least one
    count) left out, their sum and sum of squares added to the row's detector. When a detector has
    ``window`` of them, its estimate is renewed (variance / 6, less the rounding's 1/12 count^2) and its sums
    start again. Not thread-safe; pure (no I/O).

    Parameters
    ----------
    n_det : int
        Detectors (rows of a converter's order).
    window : int
        Second differences per estimate (>= 64).
    """

    def __init__(self, n_det: int, window: int = 4096, clip: float = 6.0):
        if window < 64:
            raise ConfigError(f"noise window: expected >= 64 second differences, got {window}")
        self.window, self.clip = int(window), float(clip)
        self._s = np.zeros(n_det)
        self._ss = np.zeros(n_det)
        self._n = np.zeros(n_det, dtype=np.int64)
        self.sigma_counts = np.full(n_det, np.nan)  # (n_det,): the latest complete window's, NaN before one

    def add(self, rows: np.ndarray, counts_i: np.ndarray, counts_q: np.ndarray) -> np.ndarray:
        """Add one chunk; returns the detectors (indices) whose estimate was renewed by it.

        Parameters
        ----------
        rows : ndarray of int (n_rows,)
            Each row's detector, -1 for none (skipped).
        counts_i, counts_q : ndarray (n_rows, n_samp)
            One chunk (contiguous samples); non-finite and railed values leave their differences out.
        """
        ci, cq = np.asarray(counts_i, dtype=float), np.asarray(counts_q, dtype=float)
        if ci.ndim != 2 or ci.shape != cq.shape or ci.shape[0] != len(rows):
            raise SchemaError(f"noise window: counts {ci.shape}/{cq.shape} for {len(rows)} rows")
        if ci.shape[1] < 3:
            return np.empty(0, dtype=np.int64)
        with np.errstate(invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)  # a row with no finite difference: nothing kept
            # Railed or non-finite counts (INVALID_INPUT) leave their differences out.
            d = np.concatenate([np.diff(np.where(np.abs(c) < _RAIL, c, np.nan), n=2, axis=1) for c in (ci, cq)],
                               axis=1)
            med = np.nanmedian(d, axis=1, keepdims=True)
            s0 = np.maximum(1.4826 * np.nanmedian(np.abs(d - med), axis=1, keepdims=True), 1.0)
            keep = np.abs(d - med) <= self.clip * s0
        d = np.where(keep, d, 0.0)
        rows = np.asarray(rows, dtype=np.int64)
        ok = rows >= 0
        np.add.at(self._s, rows[ok], d[ok].sum(axis=1))
        np.add.at(self._ss, rows[ok], (d[ok] ** 2).sum(axis=1))
        np.add.at(self._n, rows[ok], keep[ok].sum(axis=1))
        full = np.flatnonzero(self._n >= self.window)
        if full.size:
            n = self._n[full].astype(float)
            var = (self._ss[full] - self._s[full] ** 2 / n) / n
            self.sigma_counts[full] = np.sqrt(np.maximum(var / 6.0 - 1.0 / 12.0, 0.0))
            self._s[full], self._ss[full], self._n[full] = 0.0, 0.0, 0
        return full


def total_sigma_i_a(readout_noise_a, gain_a_per_count) -> np.ndarray:
    """Noise per quadrature and sample: readout noise and quantisation (``|g| / sqrt(12)``) in quadrature."""
    return np.hypot(np.asarray(readout_noise_a, float), np.abs(np.asarray(gain_a_per_count)) / math.sqrt(12.0))


def sigma_p_model(p: DetectorParams, i_meas_a, b_field_t, v_thev_v, sigma_i_a: float) -> np.ndarray:
    """sigma_P (W) of samples of one detector from the model, at their measured current.

    Parameters
    ----------
    p : DetectorParams
    i_meas_a : array_like of complex
        Measured peak current (counts times gain), pickup included.
    b_field_t, v_thev_v : array_like, broadcast to ``i_meas_a``
    sigma_i_a : float
        Noise per quadrature (:func:`total_sigma_i_a`).

    Returns
    -------
    ndarray of float64; NaN where R is off the operating branch.
    """
    v = np.asarray(v_thev_v, dtype=float)
    b = np.asarray(b_field_t, dtype=float)
    i = np.asarray(i_meas_a, dtype=complex) - p.pickup_a_per_t * b
    z = complex(p.z_thev_ohm)
    with np.errstate(all="ignore"):
        m2 = i.real**2 + i.imag**2
        i_abs = np.sqrt(m2)
        r = SQRT2 * v * i.real / m2 - z.real
        lo, hi = model.branch_bounds_ohm(p)
        on = (r > lo) & (r < hi)
        rs = np.where(on, r, 0.5 * (lo + hi))
        t = model.effective_temperature_k(p, rs, i_abs, b)
        ts1, _ = p.transition.dtemperature_dr(rs)
        kn = p.k_w_per_k_n * p.n * np.maximum(t, 0.0) ** (p.n - 1.0)
        j1 = v**2 * (abs(z) ** 2 - rs**2) / ((rs + z.real) ** 2 + z.imag**2) ** 2
        a = kn * ts1 - j1
        bb = -kn * p.current_shift_k_per_a
        grad2 = (a * SQRT2 * v / m2) ** 2 + bb * bb - 2.0 * a * bb * (rs + z.real) / i_abs
        return np.where(on, sigma_i_a * np.sqrt(np.maximum(grad2, 0.0)), np.nan)


def nominal_sigma_p_w(p: DetectorParams, sigma_i_a: float) -> float:
    """sigma_P at the detector's nominal operating point (its P_opt, bath and bias; B = 0).

    Where that point is off the transition, at the middle of the operating branch.
    """
    op = model.solve_operating_point(p, p.p_opt_w, p.t_bath_k, 0.0, p.v_thev_v)
    if int(op.state) == model.STATE_TRANSITION:
        i = complex(op.i_a)
    else:
        lo, hi = (float(x) for x in model.branch_bounds_ohm(p))
        i = complex(model.tes_current_a(p, 0.5 * (lo + hi)))
    return float(sigma_p_model(p, i, 0.0, p.v_thev_v, sigma_i_a))


@dataclass(frozen=True)
class NoiseModel:
    """Per detector (in a converter's order): the noise assumed and the LOW_RESPONSIVITY tolerance.

    Attributes
    ----------
    detector_ids : tuple of str
    readout_noise_a : ndarray (n_det,)
        White readout noise per quadrature, as declared.
    sigma_i_a : ndarray (n_det,)
        With quantisation (:func:`total_sigma_i_a`).
    nominal_sigma_p_w : ndarray (n_det,)
    tolerance_w : ndarray (n_det,)
        LOW_RESPONSIVITY above this sigma_P.
    source : tuple of str
        Where each detector's readout noise came from: ``"default"``,
        ``"setting"``, ``"measured:detector"`` or ``"measured:module"``.
    unusable : bool
        LOW_RESPONSIVITY drops the value.
    """

    detector_ids: tuple
    readout_noise_a: np.ndarray
    sigma_i_a: np.ndarray
    nominal_sigma_p_w: np.ndarray
    tolerance_w: np.ndarray
    source: tuple
    unusable: bool = False
    measured_from: str = ""
    settings: UncertaintySettings = field(default_factory=UncertaintySettings)
    gain_a_per_count: np.ndarray = field(default_factory=lambda: np.empty(0, complex))
    nominal_gradient: np.ndarray = field(default_factory=lambda: np.empty(0))

    def kernel_record(self, converter) -> np.ndarray:
        """The compiled kernel's per-detector record for ``converter``'s bank (made once, kept)."""
        key = (id(converter), converter.identity)
        cache = self.__dict__.setdefault("_records", {})
        rec = cache.get(key)
        if rec is None:
            cache.clear()
            rec = cache[key] = _uk.row_constants(converter.kernel_constants, self, converter.bank.arrays)
        return rec

    def low_record(self, converter) -> np.ndarray:
        """The conversion kernel's LOW_RESPONSIVITY record (n_det, ``_kernels.LOW_COLS``) for ``converter``:
        noise per quadrature, tolerance, ``C(n - 1, 1..8)``, whether its screen may decide
        (``_kernels.w1_screenable``) (made once, kept)."""
        key = (id(converter), converter.identity)
        cache = self.__dict__.setdefault("_low_records", {})
        rec = cache.get(key)
        if rec is None:
            if self.detector_ids != converter.detector_ids:
                raise ConfigError("the noise model was built for other detectors than the converter's")
            n = np.asarray(converter.kernel_constants, dtype=np.float64)[:, 7]
            a = converter.bank.arrays
            screen = w1_screenable(a["knot_offset"], a["r_knot_ohm"], a["coeffs"]).astype(np.float64)
            cols = [np.asarray(self.sigma_i_a, float), np.asarray(self.tolerance_w, float), *binomials(n - 1.0), screen]
            rec = np.ascontiguousarray(np.stack(cols, axis=1)) if len(n) else np.empty((0, LOW_COLS))
            rec.flags.writeable = False
            cache.clear()
            cache[key] = rec
        return rec

    def with_noise(self, readout_noise_a, source: Sequence[str], measured_from: str = "") -> NoiseModel:
        """This model with other readout noise per detector (e.g. measured live): sigma_i, the nominal
        sigma_P and the tolerance follow (sigma_P is linear in the noise, so no operating point is solved
        again; the same numbers :func:`noise_model` would give).

        Parameters
        ----------
        readout_noise_a : array_like (n_det,)
            White readout noise per quadrature, finite and >= 0.
        source : sequence of str (n_det,)
            Where each came from (see ``source``).
        """
        noise_a = np.asarray(readout_noise_a, dtype=float)
        if noise_a.shape != self.readout_noise_a.shape or not np.all(np.isfinite(noise_a) & (noise_a >= 0)):
            raise ConfigError(f"readout noise: expected {self.readout_noise_a.shape[0]} finite values >= 0 (A)")
        if len(source) != noise_a.size:
            raise ConfigError("readout noise: one source per detector")
        sig = total_sigma_i_a(noise_a, self.gain_a_per_count)
        nominal = sig * self.nominal_gradient
        return NoiseModel(detector_ids=self.detector_ids, readout_noise_a=noise_a, sigma_i_a=sig,
                          nominal_sigma_p_w=nominal, tolerance_w=_tolerance(self.settings, nominal),
                          source=tuple(source), unusable=self.unusable, measured_from=measured_from,
                          settings=self.settings, gain_a_per_count=self.gain_a_per_count,
                          nominal_gradient=self.nominal_gradient)

    def provenance(self, sigma_p: bool = True) -> dict:
        """What the converter's provenance records: which noise was used, the tolerance rule, and whether
        sigma_P itself is published (``sigma_p``) or only LOW_RESPONSIVITY flagged."""
        src, n = np.unique(np.array(self.source, dtype=object).astype(str), return_counts=True)
        s = self.settings
        return {
            "readout_noise_a_default": model.DEFAULT_READOUT_NOISE_A,
            "readout_noise_a_setting": s.readout_noise_a,
            "readout_noise_sources": {str(a): int(b) for a, b in zip(src, n)},
            "readout_noise_measured_from": self.measured_from,
            "readout_noise_a_range": ([float(self.readout_noise_a.min()), float(self.readout_noise_a.max())]
                                      if self.readout_noise_a.size else []),
            "low_responsivity": (f"sigma_P > {s.sigma_p_tolerance_w:g} W" if s.sigma_p_tolerance_w else
                                 f"sigma_P > {s.sigma_p_factor:g} x nominal sigma_P"),
            "low_responsivity_unusable": self.unusable,
            "sigma_p_published": bool(sigma_p),
        }


def nominal_gradients(converter) -> np.ndarray:
    """``|grad_i P|`` at each of ``converter``'s detectors' nominal operating point (n_det,): the nominal sigma_P
    per unit noise (:func:`nominal_sigma_p_w`), one forward solve per detector (ms each), kept on the
    converter so that a converter restored from a restart snapshot does not solve again."""
    grad = converter.__dict__.get("_nominal_gradient")
    if grad is None or grad.shape != (len(converter.params),):
        grad = np.array([nominal_sigma_p_w(p, 1.0) for p in converter.params], dtype=float)
        converter.__dict__["_nominal_gradient"] = grad
    return grad


def noise_model(params: Sequence[DetectorParams], settings: UncertaintySettings | None = None,
                measured_a: Mapping[str, float] | None = None, measured_from: str = "",
                gradients: np.ndarray | None = None) -> NoiseModel:
    """The noise of each detector, from a measurement (per detector or per module) or the setting.

    Parameters
    ----------
    params : sequence of DetectorParams
        In the converter's order (``converter.params``).
    settings : UncertaintySettings
    measured_a : mapping, optional
        Readout noise (A per quadrature) by detector id or by module (``"b0m3"``),
        e.g. from ``mntes-stream noise RUN``; a detector's own entry wins over its module's.
    measured_from : str
        Where the measurement came from (for the provenance).
    gradients : ndarray (n_det,), optional
        :func:`nominal_gradients` of these detectors, if known (else solved here).
    """
    s = settings or UncertaintySettings()
    measured = dict(measured_a or {})
    for k, val in measured.items():
        if not (isinstance(val, (int, float)) and math.isfinite(val) and val >= 0):
            raise ConfigError(f"readout noise of {k!r}: expected a finite number >= 0 (A), got {val!r}")
    default = s.readout_noise_a == model.DEFAULT_READOUT_NOISE_A
    noise, source = [], []
    for p in params:
        mk = module_key(p.detector_id)
        if p.detector_id in measured:
            noise.append(float(measured[p.detector_id]))
            source.append("measured:detector")
        elif mk is not None and mk in measured:
            noise.append(float(measured[mk]))
            source.append("measured:module")
        else:
            noise.append(s.readout_noise_a)
            source.append("default" if default else "setting")
    noise_a = np.array(noise, dtype=float)
    gain = np.array([p.gain_a_per_count for p in params], dtype=complex)
    sig = total_sigma_i_a(noise_a, gain)
    # sigma_P is the noise times |grad_i P|: the nominal gradient is solved once, any noise scales it.
    grad = (np.array([nominal_sigma_p_w(p, 1.0) for p in params], dtype=float) if gradients is None else
            np.asarray(gradients, dtype=float))
    if grad.shape != (len(params),):
        raise ConfigError(f"nominal gradients: expected {len(params)}, got shape {grad.shape}")
    nominal = sig * grad
    return NoiseModel(detector_ids=tuple(p.detector_id for p in params), readout_noise_a=noise_a, sigma_i_a=sig,
                      nominal_sigma_p_w=nominal, tolerance_w=_tolerance(s, nominal), source=tuple(source),
                      unusable=bool(s.low_responsivity_unusable), measured_from=measured_from, settings=s,
                      gain_a_per_count=gain, nominal_gradient=grad)


def _tolerance(s: UncertaintySettings, nominal_w: np.ndarray) -> np.ndarray:
    """Per detector, LOW_RESPONSIVITY above this sigma_P (W); inf for a detector without a nominal sigma_P
    (never on its branch)."""
    tol = np.full(nominal_w.shape, s.sigma_p_tolerance_w) if s.sigma_p_tolerance_w else s.sigma_p_factor * nominal_w
    return np.where(np.isfinite(tol), tol, np.inf)


@dataclass(frozen=True)
class Uncertainty:
    """A converted block with its uncertainty.

    Attributes
    ----------
    p_opt_w : ndarray (n_det, n_samp)
        The block's power (NaN where LOW_RESPONSIVITY when that is unusable).
    flags : ndarray of uint16 (n_det, n_samp)
        The block's flags with LOW_RESPONSIVITY.
    sigma_p_w : ndarray of float32 (n_det, n_samp)
        NaN where the power is NaN.
    """

    p_opt_w: np.ndarray
    flags: np.ndarray
    sigma_p_w: np.ndarray


def low_responsivity_block(converter, detector_ids: Sequence[str], counts_i: np.ndarray, counts_q: np.ndarray,
                           env, noise: NoiseModel):
    """Convert a block with LOW_RESPONSIVITY flagged: the flags :func:`sigma_p_block` gives, without sigma_P.

    A compiled ``"table"`` converter flags it in its own pass (``NoiseModel.low_record``; its cost:
    ``bench convert``, ``low_responsivity.cost_ratio``); any other converts, then runs the full sigma_P pass.

    Returns
    -------
    PowerBlock
        Its power NaN where LOW_RESPONSIVITY when that is unusable.

    Raises
    ------
    ConfigError
        A noise model of other detectors.
    """
    if not getattr(converter, "fuses_low_responsivity", False):  # sigma_p_block checks the detectors
        block = converter.convert(detector_ids, counts_i, counts_q, env)
        u = sigma_p_block(converter, detector_ids, counts_i, counts_q, env, block, noise)
        return replace(block, p_opt_w=u.p_opt_w, flags=u.flags)
    # low_record checks the detectors once per converter (a live chunk's call must stay cheap).
    block = converter.convert(detector_ids, counts_i, counts_q, env, low_responsivity=noise.low_record(converter))
    if noise.unusable:
        block = replace(block, p_opt_w=np.where((block.flags & fl.LOW_RESPONSIVITY) != 0, np.nan, block.p_opt_w))
    return block


def sigma_p_block(converter, detector_ids: Sequence[str], counts_i: np.ndarray, counts_q: np.ndarray, env,
                  block, noise: NoiseModel, backend: str = "auto") -> Uncertainty:
    """sigma_P and LOW_RESPONSIVITY for a block the converter has converted.

    Parameters
    ----------
    converter : core.convert converter
    detector_ids, counts_i, counts_q, env
        What was given to ``converter.convert``.
    block : PowerBlock
        What it returned.
    noise : NoiseModel
        Built for ``converter.params`` (:func:`noise_model`).
    backend : {"auto", "numba", "numpy"}
        The ``"table"`` kind's compiled kernel or the model route.

    Raises
    ------
    ConfigError
        A noise model of other detectors.
    SchemaError
        Arrays that are not the block's.
    """
    if noise.detector_ids != converter.detector_ids:
        raise ConfigError("the noise model was built for other detectors than the converter's")
    inp = converter.inputs(detector_ids, counts_i, counts_q, env)
    shape = inp.counts_i.shape
    if block.p_opt_w.shape != shape or block.flags.shape != shape:
        raise SchemaError(f"power block {block.p_opt_w.shape} is not of the counts' shape {shape}")
    sigma = np.empty(shape, dtype=np.float32)
    flags = np.array(block.flags, dtype=np.uint16)
    bank = getattr(converter, "bank", None)
    use_kernel = (bank is not None and bank.kind == "table" and backend != "numpy" and _uk.available())
    if backend == "numba" and not use_kernel:
        raise ConfigError("backend 'numba' needs a 'table' converter and numba")
    if use_kernel:
        a = bank.arrays
        _uk.run(inp.counts_i, inp.counts_q, inp.b_field_t, inp.v_thev_v, inp.rows, noise.kernel_record(converter),
                a["r_knot_ohm"], a["cell_interval"], a["coeffs"], sigma, flags)
    else:
        rows = np.maximum(inp.rows, 0)
        usable = ((flags & fl.UNUSABLE) == 0) & (inp.rows >= 0)[:, None]
        i_meas = converter.measured_current(inp, rows)
        sigma[:] = np.nan
        for k in np.flatnonzero(usable.any(axis=1)):
            d = inp.rows[k]
            idx = np.flatnonzero(usable[k])
            sigma[k, idx] = sigma_p_model(converter.params[d], i_meas[k, idx], inp.b_field_t[k, idx],
                                          inp.v_thev_v[k, idx], float(noise.sigma_i_a[d]))
        with np.errstate(invalid="ignore"):
            low = usable & (sigma > noise.tolerance_w[rows][:, None])
        flags[low] |= fl.LOW_RESPONSIVITY
    p = block.p_opt_w
    if noise.unusable:
        p = np.where((flags & fl.LOW_RESPONSIVITY) != 0, np.nan, p)
        sigma[(flags & fl.LOW_RESPONSIVITY) != 0] = np.nan
    return Uncertainty(p_opt_w=p, flags=flags, sigma_p_w=sigma)

