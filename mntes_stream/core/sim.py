"""Simulator of a DfMux TES array: optical signals and environment in, counts out.

Pure computation (no I/O). An :class:`ArraySimulator` holds the truth: one
:class:`~mntes_stream.core.params.DetectorParams` per channel (scattered around
a preset, bias tuned to ``r_frac`` at the nominal loading), and produces the
stream block by block (:meth:`ArraySimulator.next_block`). Every sample is a
quasi-static solution of the power balance (the paper's assumption), the
measured current (TES current plus magnetic pickup) is divided by the channel's
complex gain, readout noise is added and the result rounded to int32 counts.

Optical power per detector (watts at the TES)::

    P = P_load + HWP(1f, 2f, 4f) + Jupiter + dipole + photon noise (white + 1/f)

Environment: bath temperature (slow wander + fluctuations + optional ramp),
magnetic field (spin-synchronous sinusoid + fluctuations), bias steps. Each is
also reported as housekeeping at its own cadence with its own timestamps
(:class:`HkReadings`). The truth (optical power, environment and TES state at
every sample) travels in :class:`SimBlock` fields whose names start with
``truth_``; a converter must never read them.

Reproducibility: everything follows from ``SimConfig.seed``. Random numbers are
drawn in fixed blocks of samples keyed by ``(seed, stream, block index)``, and
the 1/f filters carry their state, so the stream does not depend on how it is
cut into blocks. Environment fluctuations are sums of sinusoids with seeded
frequencies and phases: a continuous function of time that housekeeping
readings can sample at any instant.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np

from mntes_stream.core import model
from mntes_stream.core.align import sample_times_ns
from mntes_stream.core.ids import detector_id
from mntes_stream.core.params import PRESETS, ParamArray
from mntes_stream.core.settings import Settings, build, setting
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.core.transition import ArctanTransition
from mntes_stream.errors import ConfigError, MntesError

__all__ = [
    "HWP_FREQUENCIES_HZ",
    "CHANNEL_OK",
    "CHANNEL_SATURATED",
    "CHANNEL_LATCHED",
    "SimConfig",
    "SimChannel",
    "HkReadings",
    "SimBlock",
    "ArraySimulator",
    "CHANNEL_BISTABLE",
    "cmb_dpdt_w_per_k",
    "solve_quasi_static",
]

# LiteBIRD half-wave-plate rotation frequencies per telescope.
HWP_FREQUENCIES_HZ = {"LFT": 0.77, "MFT": 0.65, "HFT": 1.02}

CHANNEL_OK = "ok"
CHANNEL_SATURATED = "saturated"  # optical loading above saturation: TES normal
CHANNEL_LATCHED = "latched"      # bias far below the tuned value: TES below |z| (loop gain < 0)
CHANNEL_BISTABLE = "bistable"    # bias in the bistable window at its loading: starts latched on the low
                                 # branch, re-enters the transition once its power exceeds P(R1)

_H_J_S = 6.62607015e-34
_KB_J_PER_K = 1.380649e-23
T_CMB_K = 2.7255

# Stream ids of the seeded random-number blocks.
_S_PHOTON, _S_PINK, _S_READ_I, _S_READ_Q, _S_HK_TBATH, _S_HK_B = range(6)
_NOISE_BLOCK = 4096


@dataclass(frozen=True)
class SimConfig(Settings):
    """Everything the simulator needs (SI units; frozen, so a run is its config).

    Scatter values are 1-sigma (fractional where the name ends in ``_frac``).
    Assumptions not fixed by the paper are marked "assumed" and stated in the
    README: the magnetic coefficients, the dipole band and efficiency, the
    noise levels.
    """

    # --- array -----------------------------------------------------------------------
    boards: int = setting(1, "readout boards", ge=1)
    modules: int = setting(1, "modules per board", ge=1)
    channels: int = setting(64, "per module (DfMux: 64 or 128)", ge=1, le=1024)
    sample_rate_hz: float = setting(DFMUX_SAMPLE_RATE_HZ, "DfMux ground rate, 20 MHz / 2**17 exactly; 19.1 Hz is flight-like",
                                          unit="Hz", gt=0)
    seed: int = setting(0, "random seed: a run is reproduced by its config", ge=0)
    # --- detectors: preset, tuning, scatter ------------------------------------------
    preset: str = setting("table1", "detector parameter preset (core.params.PRESETS)", choices=tuple(PRESETS))
    r_frac: float = setting(0.7, "bias tuned to R = r_frac R_n at nominal loading", unit="fraction", gt=0, lt=1)
    loading_w: float = setting(0.5e-12, "nominal optical loading (tuning point)", unit="W", ge=0)
    loading_offset_frac: float = setting(0.0, "actual loading = nominal (1 + this): not re-tuned", unit="fraction")
    scatter_t_c_frac: float = setting(0.01, "1-sigma scatter of T_c", unit="fraction", ge=0)
    scatter_r_n_frac: float = setting(0.03, "1-sigma scatter of R_n", unit="fraction", ge=0)
    scatter_k_frac: float = setting(0.05, "1-sigma scatter of the thermal conductance coefficient", unit="fraction", ge=0)
    scatter_iqr_frac: float = setting(0.10, "1-sigma scatter of the transition width parameters", unit="fraction", ge=0)
    scatter_z_ohm: float = setting(0.005, "on Re z and Im z each", unit="Ohm", ge=0)
    scatter_loading_frac: float = setting(0.05, "1-sigma scatter of the optical loading", unit="fraction", ge=0)
    scatter_gain_frac: float = setting(0.05, "1-sigma scatter of the readout gain", unit="fraction", ge=0)
    gain_a_per_count: float = setting(1e-12, "|gain|; the demodulation phase is random per channel", unit="A/count", gt=0)
    t_c_shift_k_per_t: float = setting(2.0, "c1, assumed: 2 uK per uT", unit="K/T")
    t_c_shift_k_per_t2: float = setting(1.0e4, "c2, assumed: 25 uK at 50 uT", unit="K/T^2")
    pickup_a_per_t: float = setting(2.0e-4, "|m|, assumed: 0.2 nA per uT; random phase", unit="A/T")
    scatter_b_coeff_frac: float = setting(0.2, "1-sigma scatter of the magnetic coefficients", unit="fraction", ge=0)
    saturated_per_module: int = setting(1, "channels per module with loading above saturation", ge=0)
    latched_per_module: int = setting(1, "channels per module biased into the superconducting state", ge=0)
    saturated_loading_factor: float = setting(3.0, "x P_sat (arctan tails: R ~ 0.997 R_n, not exactly normal)", gt=0)
    latched_bias_factor: float = setting(0.25, "x tuned bias", gt=0)
    bistable_per_module: int = setting(0, "channels per module biased into the bistable window, starting latched",
                                       ge=0)
    bias_per_module: bool = setting(False, "one bias for every channel of a module (the median of their tuned "
                                    "biases), as a per-module bias table gives it; False: each channel its own")
    # --- optical signals ---------------------------------------------------------------
    f_hwp_hz: float = setting(HWP_FREQUENCIES_HZ["LFT"], "half-wave-plate rotation frequency (LFT by default)", unit="Hz", ge=0)
    hwp_1f_w: float = setting(0.0, "HWP-synchronous signal at 1 f_HWP", unit="W")
    hwp_2f_w: float = setting(10e-15, "HWP-synchronous signal at 2 f_HWP", unit="W")
    hwp_4f_w: float = setting(0.0, "HWP-synchronous signal at 4 f_HWP", unit="W")
    hwp_random_phase: bool = setting(True, "per-detector phase of each harmonic")
    jupiter_peak_w: float = setting(0.8e-12, "at the beam centre (448 GHz, paper sect. 2.2)", unit="W")
    jupiter_t_s: float = setting(30.0, "first crossing (beam-centre detector)", unit="s")
    jupiter_period_s: float = setting(600.0, "0: only one crossing", unit="s", ge=0)
    jupiter_fwhm_s: float = setting(1.0, "beam FWHM / scan speed", unit="s", ge=0)
    jupiter_spread: bool = setting(True, "per-detector impact parameter and delay")
    dipole_k: float = setting(3.36e-3, "CMB dipole amplitude, K_CMB", unit="K")
    dipole_period_s: float = setting(1200.0, "spin period (0.05 rpm)", unit="s", ge=0)
    band_center_hz: float = setting(140e9, "assumed band for the dipole conversion", unit="Hz", gt=0)
    fractional_bandwidth: float = setting(0.30, "fractional bandwidth of the assumed band", gt=0)
    optical_efficiency: float = setting(0.5, "assumed optical efficiency for the dipole", gt=0, le=1)
    # --- noise -------------------------------------------------------------------------
    nep_w_rthz: float = setting(1.0e-17, "photon NEP (one-sided PSD = NEP^2)", unit="W/rtHz", ge=0)
    f_knee_hz: float = setting(0.02, "1/f knee of the optical noise", unit="Hz", ge=0)
    nei_a_rthz: float = setting(10e-12, "readout noise current per quadrature", unit="A/rtHz", ge=0)
    # --- environment -------------------------------------------------------------------
    t_bath_k: float = setting(0.100, "nominal (tuning point)", unit="K", gt=0)
    t_bath_offset_k: float = setting(0.0, "environment offset from nominal at t = 0: not re-tuned", unit="K")
    t_bath_ramp_k_per_s: float = setting(0.0, "linear bath temperature drift", unit="K/s")
    t_bath_wander_k: float = setting(0.2e-3, "slow sinusoidal drift amplitude", unit="K", ge=0)
    t_bath_wander_period_s: float = setting(1800.0, "period of the slow bath drift", unit="s", gt=0)
    t_bath_fluct_k: float = setting(5e-6, "rms of fluctuations between 1 mHz and 1 Hz", unit="K", ge=0)
    b_field_t: float = setting(0.0, "static field (the tuning point)", unit="T")
    b_field_offset_t: float = setting(0.0, "offset from it at t = 0: not re-tuned", unit="T")
    b_field_amp_t: float = setting(10e-6, "spin-synchronous amplitude", unit="T", ge=0)
    b_field_period_s: float = setting(1200.0, "period of the spin-synchronous field", unit="s", gt=0)
    b_field_ramp_t_per_s: float = setting(0.0, "linear field drift", unit="T/s")
    b_field_fluct_t: float = setting(0.1e-6, "rms field fluctuation", unit="T", ge=0)
    bias_steps: tuple[tuple[float, float], ...] = setting(((90.0, 0.01),), "(time s, fractional change of every bias)")
    # --- housekeeping ------------------------------------------------------------------
    hk_t_bath_rate_hz: float = setting(5.0, "bath thermometer readout rate", unit="Hz", ge=0)
    hk_b_field_rate_hz: float = setting(10.0, "magnetometer readout rate", unit="Hz", ge=0)
    hk_bias_rate_hz: float = setting(1.0, "bias readback rate", unit="Hz", ge=0)
    hk_t_bath_noise_k: float = setting(1e-6, "bath thermometer noise (rms per reading)", unit="K", ge=0)
    hk_b_field_noise_t: float = setting(0.05e-6, "magnetometer noise (rms per reading)", unit="T", ge=0)

    def __post_init__(self) -> None:
        super().__post_init__()  # every declared setting: type, range, choices
        if self.saturated_per_module + self.latched_per_module + self.bistable_per_module > self.channels:
            raise ConfigError("more saturated + latched + bistable channels than channels per module")
        if any(1.0 + f <= 0 for _, f in self.bias_steps):
            raise ConfigError("a bias step may not take the bias to zero or below")
        object.__setattr__(self, "bias_steps", tuple(sorted(self.bias_steps)))

    @property
    def n_detectors(self) -> int:
        return self.boards * self.modules * self.channels

    def replace(self, **changes: Any) -> SimConfig:
        return dataclasses.replace(self, **changes)

    def to_dict(self) -> dict:
        d = dataclasses.asdict(self)
        d["bias_steps"] = [list(s) for s in self.bias_steps]
        return d

    @classmethod
    def from_dict(cls, d: dict, where: str = "simulator") -> SimConfig:
        """Build from a mapping (e.g. a TOML table), every value checked against its declaration."""
        return build(cls, d, where)

    @classmethod
    def noise_free(cls, **changes: Any) -> SimConfig:
        """A single clean detector: no scatter, noise, environment changes or extra signals."""
        base = dict(
            boards=1, modules=1, channels=1, saturated_per_module=0, latched_per_module=0,
            scatter_t_c_frac=0.0, scatter_r_n_frac=0.0, scatter_k_frac=0.0, scatter_iqr_frac=0.0,
            scatter_z_ohm=0.0, scatter_loading_frac=0.0, scatter_gain_frac=0.0, scatter_b_coeff_frac=0.0,
            hwp_2f_w=0.0, hwp_random_phase=False, jupiter_peak_w=0.0, jupiter_spread=False, dipole_k=0.0,
            nep_w_rthz=0.0, nei_a_rthz=0.0, t_bath_wander_k=0.0, t_bath_fluct_k=0.0,
            b_field_amp_t=0.0, b_field_fluct_t=0.0, bias_steps=(), hk_t_bath_noise_k=0.0,
            hk_b_field_noise_t=0.0,
        )
        base.update(changes)
        return cls(**base)


@dataclass(frozen=True)
class SimChannel:
    """Where a simulated detector sits and what it is driven into."""

    detector_id: str
    board: int
    module: int
    channel: int
    kind: str  # CHANNEL_OK, CHANNEL_SATURATED, CHANNEL_LATCHED or CHANNEL_BISTABLE


@dataclass(frozen=True)
class HkReadings:
    """Housekeeping readings of one sensor in one block.

    ``value`` has shape ``(n,)`` (t_bath in K, b_field in T) or ``(n, n_ch)``
    for ``bias`` (RMS Thevenin voltage per channel of one module, V).
    """

    sensor: str
    t_ns: np.ndarray
    value: np.ndarray
    unit: str
    board: int | None = None
    module: int | None = None
    channels: np.ndarray | None = None


@dataclass(frozen=True)
class SimBlock:
    """A block of simulated samples for the whole array.

    Attributes
    ----------
    start_index : int
        Index of the first sample since the start of the run.
    t_ns : ndarray of int64, shape (n_samp,)
        ``t_first + round(k * 1e9 / sample_rate_hz)`` with ``t_first`` the time of
        sample ``start_index`` of the run: exactly what a counts chunk with
        ``t0_ns = t_first`` and the sample rate describes.
    counts_i, counts_q : ndarray of int32, shape (n_det, n_samp)
        What the converter sees.
    hk : tuple of HkReadings
        Housekeeping readings whose timestamps fall in this block's span.
    truth_p_opt_w : ndarray, shape (n_det, n_samp)
        TRUTH: optical power at each sample. Never an input to a converter.
    truth_t_bath_k, truth_b_field_t : ndarray, shape (n_samp,)
        TRUTH: environment at each sample.
    truth_v_thev_v : ndarray, shape (n_det, n_samp)
        TRUTH: bias (RMS) at each sample (also reported as housekeeping).
    truth_state : ndarray of int8, shape (n_det, n_samp)
        TRUTH: ``model.STATE_*`` of each sample.
    """

    start_index: int
    t_ns: np.ndarray
    counts_i: np.ndarray
    counts_q: np.ndarray
    hk: tuple
    truth_p_opt_w: np.ndarray
    truth_t_bath_k: np.ndarray
    truth_b_field_t: np.ndarray
    truth_v_thev_v: np.ndarray
    truth_state: np.ndarray

    @property
    def n_samples(self) -> int:
        return int(self.t_ns.shape[0])


def cmb_dpdt_w_per_k(band_center_hz: float, fractional_bandwidth: float, optical_efficiency: float,
                     t_cmb_k: float = T_CMB_K) -> float:
    """dP/dT_CMB of a single-mode, single-polarisation detector with a top-hat band.

    ``P = eta * integral h nu / (exp(h nu / k T) - 1) d nu``, so
    ``dP/dT = eta * k_B * integral x^2 e^x / (e^x - 1)^2 d nu`` with ``x = h nu / k T``.
    """
    if not (band_center_hz > 0 and 0 < fractional_bandwidth < 2 and optical_efficiency >= 0):
        raise ConfigError("dipole band: need band_center_hz > 0, 0 < fractional_bandwidth < 2, efficiency >= 0")

    def integrand(nu):
        x = _H_J_S * nu / (_KB_J_PER_K * t_cmb_k)
        return x * x * math.exp(x) / math.expm1(x) ** 2

    from scipy import integrate  # here, not at import: every service's start imports this module (registry)

    lo = band_center_hz * (1 - fractional_bandwidth / 2)
    hi = band_center_hz * (1 + fractional_bandwidth / 2)
    value, _ = integrate.quad(integrand, lo, hi)
    return optical_efficiency * _KB_J_PER_K * value


class _NoiseStream:
    """Standard normals indexed by (row, sample), independent of how they are requested.

    Drawn in blocks of samples keyed by ``(seed, stream, block index)``; the
    block length shrinks for wide arrays so a cached block stays near 16 MB.
    """

    def __init__(self, seed: int, stream: int, rows: int):
        self._key = (int(seed) & 0xFFFFFFFF, int(stream))
        self.rows = rows
        self.block = int(np.clip(2 ** int(math.log2(max(1, (1 << 21) // max(rows, 1)))), 64, _NOISE_BLOCK))
        self._cache: dict[int, np.ndarray] = {}

    def _get(self, b: int) -> np.ndarray:
        if b not in self._cache:
            if len(self._cache) >= 2:
                self._cache.pop(min(self._cache))
            rng = np.random.default_rng([*self._key, b])
            self._cache[b] = rng.standard_normal((self.rows, self.block))
        return self._cache[b]

    def take(self, start: int, n: int) -> np.ndarray:
        """Shape ``(rows, n)`` for samples ``start .. start + n - 1``."""
        if n == 0:
            return np.zeros((self.rows, 0))
        b0, b1 = start // self.block, (start + n - 1) // self.block
        parts = []
        for b in range(b0, b1 + 1):
            lo = max(start - b * self.block, 0)
            hi = min(start + n - b * self.block, self.block)
            parts.append(self._get(b)[:, lo:hi])
        return parts[0] if len(parts) == 1 else np.concatenate(parts, axis=1)


class _PinkNoise:
    """Unit-white-referenced 1/f noise: a sum of independent AR(1) (Lorentzian) processes.

    With poles log-spaced by ``d = ln 10`` (one per decade, +-6% ripple) and each
    process of variance ``s^2 = S_w f_knee d``, the one-sided PSD is
    ``S_w f_knee / f`` between the lowest pole and ``f_max``, where
    ``S_w = 2 / fs`` is the PSD of unit white noise per sample. Each process
    starts in its stationary distribution, so there is no warm-up transient.
    """

    def __init__(self, seed: int, rows: int, fs: float, f_knee: float):
        f_lo, f_hi = 1e-4, max(min(100.0 * f_knee, fs / 4.0), 2e-4)
        d = math.log(10.0)
        n_poles = int(math.ceil(math.log(f_hi / f_lo) / d)) + 1
        poles = f_lo * np.exp(d * np.arange(n_poles))
        self._a = np.exp(-2.0 * np.pi * poles / fs)
        s = math.sqrt(2.0 * f_knee * d / fs)
        self._b = s * np.sqrt(1.0 - self._a**2)
        self._white = [_NoiseStream(seed, _S_PINK + 16 * (j + 1), rows) for j in range(n_poles)]
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, _S_PINK, 1 << 30])
        self._zi = self._a[None, :] * s * rng.standard_normal((rows, n_poles))
        self._pos = 0

    def next(self, n: int) -> np.ndarray:
        from scipy.signal import lfilter  # scipy.signal costs ~0.4 s to import: only a simulation pays it

        out = np.zeros((self._zi.shape[0], n))
        for j, a in enumerate(self._a):
            w = self._white[j].take(self._pos, n)
            y, zf = lfilter([self._b[j]], [1.0, -a], w, axis=1, zi=self._zi[:, j : j + 1])
            self._zi[:, j : j + 1] = zf
            out += y
        self._pos += n
        return out


class _Fluctuation:
    """A seeded random function of time: sum of sinusoids with a 1/f power spectrum."""

    def __init__(self, seed: int, tag: int, rms: float, f_lo: float = 1e-3, f_hi: float = 1.0, n: int = 24):
        rng = np.random.default_rng([int(seed) & 0xFFFFFFFF, 100 + tag])
        edges = np.geomspace(f_lo, f_hi, n + 1)
        self.f = edges[:-1] * np.exp(rng.uniform(0, 1, n) * np.log(edges[1:] / edges[:-1]))
        self.phase = rng.uniform(0, 2 * np.pi, n)
        # Equal power per logarithmic bin is a 1/f spectrum.
        self.amp = np.full(n, rms * math.sqrt(2.0 / n))

    def __call__(self, t_s: np.ndarray) -> np.ndarray:
        t = np.asarray(t_s, dtype=float)
        if not np.any(self.amp):
            return np.zeros_like(t)
        # An explicit row sum, not a matrix product: BLAS may sum in a different order
        # for a different number of rows, and the stream must not depend on block size.
        return (np.sin(2 * np.pi * np.multiply.outer(t, self.f) + self.phase) * self.amp).sum(axis=-1)


def _power_and_slope(p, r, t_bath, b, v):
    """Power balance along R: ``P(R)`` (optical power that puts the TES at R) and ``dP/dR``."""
    z = p.z_thev_ohm
    m2 = (r + z.real) ** 2 + z.imag**2
    i_abs = model.SQRT2 * v / np.sqrt(m2)
    t = model.effective_temperature_k(p, r, i_abs, b)
    ts1, _ = p.transition.dtemperature_dr(r)
    t1 = ts1 + p.current_shift_k_per_a * model.SQRT2 * v * (r + z.real) / m2**1.5
    tn1 = np.maximum(t, 0.0) ** (p.n - 1.0)
    power = p.k_w_per_k_n * (tn1 * t - t_bath**p.n) - v * v * r / m2
    slope = p.k_w_per_k_n * p.n * tn1 * t1 - v * v * (np.abs(z) ** 2 - r * r) / m2**2
    return power, slope


# The fields the power balance along R needs (see model.effective_temperature_k).
_BALANCE_FIELDS = ("k_w_per_k_n", "n", "z_thev_ohm", "t_c_shift_k_per_t", "t_c_shift_k_per_t2",
                   "current_shift_k_per_a")


def _gather(pa: ParamArray, index) -> ParamArray:
    """Per-element parameters ``arr[index]`` of the power-balance fields (others zeroed)."""
    kw = {f.name: 0.0 for f in dataclasses.fields(pa) if f.name not in ("detector_ids", "transition")}
    kw.update({name: np.asarray(getattr(pa, name))[index] for name in _BALANCE_FIELDS})
    tr = pa.transition
    transition = ArctanTransition(t_c_k=np.asarray(tr.t_c_k)[index], iqr_k=np.asarray(tr.iqr_k)[index],
                                  r_n_ohm=np.asarray(tr.r_n_ohm)[index])
    return ParamArray(detector_ids=(), transition=transition, **kw)


def solve_quasi_static(pa: ParamArray, p_opt_w, t_bath_k, b_field_t, v_thev_v, r_guess_ohm=None,
                       max_iter: int = 100, dropped0=None) -> model.OperatingPoint:
    """Same result as :func:`model.solve_operating_point`, faster for time streams.

    Safeguarded Newton in R: the bracket ``(a, b)`` always holds the root (the
    residual is monotone on the stable branch), a Newton step that leaves it
    is replaced by bisection, and converged elements drop out. Starts from
    ``r_guess_ohm`` (broadcast to the sample shape) or mid-branch. Below
    ``|z|`` the states come from the stability criterion
    (:func:`model.lower_states`) with hysteresis along the samples
    (:func:`model.latch_sequence`), starting from ``dropped0`` (n_det,).

    Parameters
    ----------
    pa : ParamArray
        Columns of shape ``(n_det, 1)``.
    p_opt_w, t_bath_k, b_field_t, v_thev_v : array_like, broadcast to (n_det, n_samp)

    Returns
    -------
    model.OperatingPoint with arrays of shape (n_det, n_samp).
    """
    lo, hi = model.branch_bounds_ohm(pa)
    p_opt, t_bath, b, v, lo, hi = (
        np.ascontiguousarray(x, dtype=float)
        for x in np.broadcast_arrays(p_opt_w, t_bath_k, b_field_t, v_thev_v, lo, hi)
    )
    shape = p_opt.shape
    n_det = np.shape(pa.k_w_per_k_n)[0]
    if p_opt.ndim != 2 or shape[0] != n_det:
        raise ConfigError(f"solve_quasi_static: samples must broadcast to (n_det={n_det}, n_samp)")
    if np.any(v <= 0) or not np.all(np.isfinite(v)):
        raise ConfigError("solve_quasi_static: bias voltage must be finite and > 0")
    p_lo, _ = _power_and_slope(pa, lo, t_bath, b, v)
    p_hi, _ = _power_and_slope(pa, hi, t_bath, b, v)
    sc = ~(p_opt - p_lo > 0)
    normal = ~sc & ~(p_opt - p_hi < 0)
    ok = ~sc & ~normal
    rows, cols = np.nonzero(ok)
    flat = rows * shape[1] + cols
    sub = _gather(pa, (rows, 0))
    po, tb, bb, vv = (x.ravel()[flat] for x in (p_opt, t_bath, b, v))
    a, bnd = lo.ravel()[flat], hi.ravel()[flat]
    if r_guess_ohm is None:
        x = 0.5 * (a + bnd)
    else:
        x = np.clip(np.broadcast_to(r_guess_ohm, shape).ravel()[flat], a, bnd)
        x = np.where((x <= a) | (x >= bnd), 0.5 * (a + bnd), x)
    r_out = np.empty(flat.size)
    idx = np.arange(flat.size)
    tol = 4e-16 * sub.transition.r_n_ohm
    active = np.ones(flat.size, dtype=bool)
    dx = dx_old = bnd - a  # last step and the one before it (rtsafe bookkeeping)
    for _ in range(max_iter):
        if not active.any():
            break
        # Drop converged elements once they are the majority (gathering costs an iteration).
        if active.sum() < 0.5 * active.size:
            keep = np.nonzero(active)[0]
            sub = _gather(sub, keep)
            idx, x, a, bnd, po, tb, bb, vv, tol, dx, dx_old = (
                arr[keep] for arr in (idx, x, a, bnd, po, tb, bb, vv, tol, dx, dx_old))
            active = np.ones(keep.size, dtype=bool)
        pw, slope = _power_and_slope(sub, x, tb, bb, vv)
        f = po - pw  # strictly decreasing in R
        a = np.where(f > 0, x, a)
        bnd = np.where(f < 0, x, bnd)
        with np.errstate(divide="ignore", invalid="ignore"):
            x_new = x + f / slope
        # Bisect where Newton leaves the bracket or shrinks it too slowly (rtsafe rule;
        # near R_n the slope is huge and plain Newton would crawl). A step a rounding
        # error past the bracket is a converging step: clip it instead.
        bad = (~np.isfinite(x_new) | (x_new < a - tol) | (x_new > bnd + tol)
               | (np.abs(2 * f) > np.abs(dx_old * slope)))
        x_new = np.where(f == 0, x, np.where(bad, 0.5 * (a + bnd), np.clip(x_new, a, bnd)))
        dx_old, dx = dx, np.abs(x_new - x)
        now_done = active & ((np.abs(x_new - x) <= tol) | (bnd - a <= tol))
        r_out[idx[now_done]] = x_new[now_done]
        active &= ~now_done
        x = np.where(active, x_new, x)
    else:
        if active.any():
            raise MntesError("solve_quasi_static: Newton iteration did not converge")
    r_min, r_max = pa.transition.r_domain_ohm()
    r = np.where(sc, np.broadcast_to(r_min, shape), np.broadcast_to(r_max, shape)).astype(float)
    r.ravel()[flat] = r_out
    # Below |z| the operating branch continues to R2; a low branch or R = 0 may exist too.
    r, op_exists, low_exists, r_low = model.lower_candidates(pa, shape, p_opt, t_bath, b, v, r, sc, normal)
    dropped = model.latch_sequence(op_exists, low_exists, dropped0) & low_exists
    r = np.where(dropped, r_low, r)
    at_bottom = dropped & ~(r > r_min)
    r = np.where(at_bottom, np.broadcast_to(r_min, shape), r)
    i = model.tes_current_a(pa, r, v)
    latched = ~normal & ~at_bottom & ~(r > np.abs(pa.z_thev_ohm) + 1e-9 * pa.transition.r_n_ohm)
    state = np.select([at_bottom, normal, latched],
                      [model.STATE_SUPERCONDUCTING, model.STATE_NORMAL, model.STATE_LATCHED],
                      model.STATE_TRANSITION).astype(np.int8)
    # Temperature: on the transition from its shape, off it from the balance at fixed R.
    on = ~normal & ~at_bottom
    t_on = model.effective_temperature_k(pa, np.where(on, r, 0.5 * (lo + hi)), np.abs(i), b)
    t_off = (t_bath**pa.n + (p_opt + model.joule_power_w(pa, r, v)) / pa.k_w_per_k_n) ** (1.0 / pa.n)
    return model.OperatingPoint(r_ohm=r, t_k=np.where(on, t_on, t_off), i_a=i, state=state, dropped=dropped)


def _bistable_bias_v(p, load_w: float, v_tuned: float) -> float:
    """A bias putting ``load_w`` inside the detector's bistable window, at 30% of it from the bottom.

    Scans 0.3-0.8 of the tuned bias for the window ``(P(R2), P(R1))`` of the
    stability criterion (:func:`model.stability_bounds_ohm`) at the nominal bath.
    """
    fracs = np.linspace(0.3, 0.8, 51)
    best, best_d = None, np.inf
    for f in fracs:
        v = f * v_tuned
        r0, r1, r2 = (float(x) for x in model.stability_bounds_ohm(p, v))
        if not r1 > r0:
            continue
        p1, p2 = (float(model.power_of_resistance_w(p, r, p.t_bath_k, 0.0, v)) for r in (r1, r2))
        if not p1 > p2:
            continue
        d = abs((load_w - p2) / (p1 - p2) - 0.3)
        if d < best_d:
            best, best_d = v, d
    if best is None or best_d > 0.3:
        raise ConfigError(f"{p.detector_id}: no bias puts its loading in a bistable window")
    return float(best)


def _readings_in(t0_ns: int, rate_hz: float, phase: float, start_ns: int, end_ns: int):
    """Indices ``j >= 0`` and times of readings ``t0 + round((j + phase)/rate s)`` in [start, end)."""
    if rate_hz <= 0 or end_ns <= start_ns:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    j_lo = max(int(math.floor((start_ns - t0_ns) * 1e-9 * rate_hz - phase)) - 1, 0)
    j_hi = int(math.ceil((end_ns - t0_ns) * 1e-9 * rate_hz - phase)) + 1
    j = np.arange(j_lo, max(j_hi, j_lo) + 1, dtype=np.int64)
    t = np.int64(t0_ns) + np.round((j + phase) * (1e9 / rate_hz)).astype(np.int64)
    keep = (t >= start_ns) & (t < end_ns)
    return j[keep], t[keep]


class ArraySimulator:
    """A seeded DfMux array: truth parameters, signals, environment; counts block by block.

    Parameters
    ----------
    config : SimConfig
    t0_ns : int
        Time of sample 0 (int64 ns since the epoch).

    Attributes
    ----------
    channels : tuple of SimChannel
        Order of the detector axis (board, module, channel).
    truth_params : tuple of DetectorParams
        The simulator's truth (bias tuned; latched channels carry their low bias).
    dpdt_cmb_w_per_k : float
        Dipole conversion, W per K_CMB, for the stated band and efficiency.
    """

    def __init__(self, config: SimConfig, t0_ns: int = 0):
        self.config = c = config
        self.t0_ns = int(t0_ns)
        self.fs = float(c.sample_rate_hz)
        n_det = c.n_detectors
        seed = int(c.seed)
        rng = np.random.default_rng([seed & 0xFFFFFFFF, 1])
        normal = lambda: rng.standard_normal(n_det)  # noqa: E731
        uniform = lambda lo, hi: rng.uniform(lo, hi, n_det)  # noqa: E731
        kinds = np.full(c.channels, CHANNEL_OK, dtype=object)
        n_sat, n_lat, n_bi = c.saturated_per_module, c.latched_per_module, c.bistable_per_module
        if n_lat:
            kinds[c.channels - n_lat:] = CHANNEL_LATCHED
        if n_sat:
            kinds[c.channels - n_lat - n_sat: c.channels - n_lat] = CHANNEL_SATURATED
        if n_bi:
            kinds[c.channels - n_lat - n_sat - n_bi: c.channels - n_lat - n_sat] = CHANNEL_BISTABLE
        self.channels = tuple(
            SimChannel(detector_id(b, m, ch), b, m, ch, str(kinds[ch]))
            for b in range(c.boards) for m in range(c.modules) for ch in range(c.channels)
        )
        # Draw every scatter in a fixed order so a config always gives the same array.
        d_tc, d_rn, d_k, d_iqr = normal(), normal(), normal(), normal()
        d_zr, d_zi, d_load, d_gain = normal(), normal(), normal(), normal()
        d_c1, d_c2, d_m = normal(), normal(), normal()
        ph_m, ph_gain = uniform(0, 2 * np.pi), uniform(0, 2 * np.pi)
        ph_hwp = rng.uniform(0, 2 * np.pi, (n_det, 3))
        jup_x, jup_delay = uniform(-1.5, 1.5), uniform(0.0, 5.0)
        base = PRESETS[c.preset]("detector parameter preset (core.params.PRESETS)")
        if not isinstance(base.transition, ArctanTransition):
            raise ConfigError("simulator: the preset must use the arctan transition")
        tr = base.transition
        nominal_load = c.loading_w * (1 + c.scatter_loading_frac * d_load)
        if np.any(nominal_load <= 0):
            raise ConfigError("simulator: loading scatter produced non-positive loading")
        params = []
        for k, ch in enumerate(self.channels):
            params.append(base.replace(
                detector_id=ch.detector_id,
                t_c_k=float(tr.t_c_k) * (1 + c.scatter_t_c_frac * d_tc[k]),
                r_n_ohm=float(tr.r_n_ohm) * (1 + c.scatter_r_n_frac * d_rn[k]),
                iqr_k=float(tr.iqr_k) * (1 + c.scatter_iqr_frac * d_iqr[k]),
                k_w_per_k_n=base.k_w_per_k_n * (1 + c.scatter_k_frac * d_k[k]),
                z_thev_ohm=base.z_thev_ohm + c.scatter_z_ohm * complex(d_zr[k], d_zi[k]),
                t_bath_k=c.t_bath_k,
                p_opt_w=float(nominal_load[k]),
                t_c_shift_k_per_t=c.t_c_shift_k_per_t * (1 + c.scatter_b_coeff_frac * d_c1[k]),
                t_c_shift_k_per_t2=c.t_c_shift_k_per_t2 * (1 + c.scatter_b_coeff_frac * d_c2[k]),
                pickup_a_per_t=c.pickup_a_per_t * (1 + c.scatter_b_coeff_frac * d_m[k]) * np.exp(1j * ph_m[k]),
                gain_a_per_count=c.gain_a_per_count * (1 + c.scatter_gain_frac * d_gain[k])
                * np.exp(1j * ph_gain[k]),
            ))
        v_tuned = np.ravel(model.tune_bias_v(ParamArray.from_params(params), c.r_frac,
                                             b_field_t=c.b_field_t))
        if c.bias_per_module:  # channels in order (board, module, channel): a module is a row here
            v_tuned = np.repeat(np.median(v_tuned.reshape(-1, c.channels), axis=1), c.channels)
        is_lat = np.array([ch.kind == CHANNEL_LATCHED for ch in self.channels])
        is_sat = np.array([ch.kind == CHANNEL_SATURATED for ch in self.channels])
        v_set = np.where(is_lat, c.latched_bias_factor * v_tuned, v_tuned)
        is_bi = np.array([ch.kind == CHANNEL_BISTABLE for ch in self.channels])
        for k in np.flatnonzero(is_bi):
            v_set[k] = _bistable_bias_v(params[k], float(nominal_load[k] * (1 + c.loading_offset_frac)), v_tuned[k])
        self.truth_params = tuple(p.replace(v_thev_v=float(v)) for p, v in zip(params, v_set))
        self._pa = ParamArray.from_params(list(self.truth_params))
        p_sat = np.array([p.p_sat_w for p in self.truth_params])
        load = np.where(is_sat, c.saturated_loading_factor * p_sat, nominal_load * (1 + c.loading_offset_frac))
        self._load_w = load[:, None]
        self._v_set = v_set[:, None]
        self._hwp_phase = ph_hwp if c.hwp_random_phase else np.zeros((n_det, 3))
        if c.jupiter_spread:
            self._jup_peak = (c.jupiter_peak_w * np.exp(-0.5 * jup_x**2))[:, None]
            self._jup_delay = jup_delay[:, None]
        else:
            self._jup_peak = np.full((n_det, 1), c.jupiter_peak_w)
            self._jup_delay = np.zeros((n_det, 1))
        self.dpdt_cmb_w_per_k = (
            cmb_dpdt_w_per_k(c.band_center_hz, c.fractional_bandwidth, c.optical_efficiency)
            if c.dipole_k else 0.0
        )
        # Noise: per-sample sigma from one-sided PSDs (white: sigma = NEP sqrt(fs / 2)).
        self._sigma_p_w = c.nep_w_rthz * math.sqrt(self.fs / 2.0)
        self._sigma_counts = (c.nei_a_rthz * math.sqrt(self.fs / 2.0)
                              / np.abs(self._pa.gain_a_per_count))  # (n_det, 1)
        self._photon = _NoiseStream(seed, _S_PHOTON, n_det)
        self._pink = (_PinkNoise(seed, n_det, self.fs, c.f_knee_hz)
                      if c.nep_w_rthz > 0 and c.f_knee_hz > 0 else None)
        self._read_i = _NoiseStream(seed, _S_READ_I, n_det)
        self._read_q = _NoiseStream(seed, _S_READ_Q, n_det)
        self._hk_tb_noise = _NoiseStream(seed, _S_HK_TBATH, 1)
        self._hk_b_noise = _NoiseStream(seed, _S_HK_B, 1)
        self._fluct_tb = _Fluctuation(seed, 0, c.t_bath_fluct_k)
        self._fluct_b = _Fluctuation(seed, 1, c.b_field_fluct_t)
        # A bias step applies from the first sample at or after its time; its instant is
        # put half a sample before that sample so no sample time is ambiguous.
        self._step_index = np.array([math.ceil(t * self.fs - 1e-9) for t, _ in c.bias_steps], dtype=np.int64)
        self._step_ns = np.array([self.sample_time_ns(k) - round(0.5e9 / self.fs) for k in self._step_index],
                                 dtype=np.int64)
        self._step_factor = np.cumprod([1.0 + f for _, f in c.bias_steps])
        self._pos = 0
        self._r_prev = c.r_frac * np.asarray(self._pa.transition.r_n_ohm, dtype=float)
        # Every detector starts on its branch (tuned from normal), but the bistable ones:
        # they sit on their low branch until their power exceeds the re-entry point P(R1).
        self._dropped = np.array([ch.kind == CHANNEL_BISTABLE for ch in self.channels])

    # --- layout ---------------------------------------------------------------------------
    @property
    def detector_ids(self) -> tuple:
        return tuple(ch.detector_id for ch in self.channels)

    @property
    def position(self) -> int:
        """Index of the next sample :meth:`next_block` will produce."""
        return self._pos

    def module_rows(self, board: int, module: int) -> slice:
        """Rows of the detector axis that belong to one module."""
        c = self.config
        if not (0 <= board < c.boards and 0 <= module < c.modules):
            raise ConfigError(f"simulator: no module b{board}m{module}")
        start = (board * c.modules + module) * c.channels
        return slice(start, start + c.channels)

    # --- environment (continuous functions of time) -------------------------------------------
    def t_bath_k(self, t_s) -> np.ndarray:
        c = self.config
        t = np.asarray(t_s, dtype=float)
        wander = (c.t_bath_wander_k * np.sin(2 * np.pi * t / c.t_bath_wander_period_s)
                  if c.t_bath_wander_k and c.t_bath_wander_period_s > 0 else 0.0)
        return c.t_bath_k + c.t_bath_offset_k + c.t_bath_ramp_k_per_s * t + wander + self._fluct_tb(t)

    def b_field_t(self, t_s) -> np.ndarray:
        c = self.config
        t = np.asarray(t_s, dtype=float)
        spin = (c.b_field_amp_t * np.sin(2 * np.pi * t / c.b_field_period_s)
                if c.b_field_amp_t and c.b_field_period_s > 0 else 0.0)
        return c.b_field_t + c.b_field_offset_t + c.b_field_ramp_t_per_s * t + spin + self._fluct_b(t)

    def sample_time_ns(self, k: int) -> int:
        """Time of sample ``k`` of the run."""
        return self.t0_ns + int(round(k * 1e9 / self.fs))

    def bias_factor(self, t_ns) -> np.ndarray:
        """Product of the bias steps in effect at each time (1 before the first)."""
        t = np.asarray(t_ns, dtype=np.int64)
        n_applied = np.searchsorted(self._step_ns, t, side="right")
        return np.concatenate([[1.0], self._step_factor])[n_applied]

    def _bias_factor_of_samples(self, k: np.ndarray) -> np.ndarray:
        n_applied = np.searchsorted(self._step_index, k, side="right")
        return np.concatenate([[1.0], self._step_factor])[n_applied]

    # --- optical signal ------------------------------------------------------------------------
    def optical_components_w(self, t_s) -> dict:
        """Noise-free optical power by component, each of shape ``(n_det, n_samp)``.

        Keys: ``loading``, ``hwp``, ``jupiter``, ``dipole`` (zeros where off).
        """
        c = self.config
        t = np.asarray(t_s, dtype=float)[None, :]
        shape = (len(self.channels), t.shape[1])
        out = {"loading": np.broadcast_to(self._load_w, shape).copy(), "hwp": np.zeros(shape),
               "jupiter": np.zeros(shape), "dipole": np.zeros(shape)}
        theta = 2 * np.pi * c.f_hwp_hz * t
        for j, (harm, amp) in enumerate(((1, c.hwp_1f_w), (2, c.hwp_2f_w), (4, c.hwp_4f_w))):
            if amp:
                out["hwp"] += amp * np.cos(harm * theta + self._hwp_phase[:, j : j + 1])
        if c.jupiter_peak_w:
            sigma = c.jupiter_fwhm_s / (2 * math.sqrt(2 * math.log(2)))
            rel = t - c.jupiter_t_s - self._jup_delay
            if c.jupiter_period_s > 0:
                rel = rel - np.maximum(np.round(rel / c.jupiter_period_s), 0) * c.jupiter_period_s
            out["jupiter"] = self._jup_peak * np.exp(-0.5 * (rel / sigma) ** 2)
        if c.dipole_k:
            out["dipole"] = np.broadcast_to(
                self.dpdt_cmb_w_per_k * c.dipole_k * np.cos(2 * np.pi * t / c.dipole_period_s), shape).copy()
        return out

    def optical_signal_w(self, t_s) -> np.ndarray:
        """Noise-free optical power, shape ``(n_det, n_samp)``: the sum of the components."""
        parts = self.optical_components_w(t_s)
        return parts["loading"] + parts["hwp"] + parts["jupiter"] + parts["dipole"]

    # --- the stream ----------------------------------------------------------------------------
    def next_block(self, n: int) -> SimBlock:
        """The next ``n`` samples of the whole array (sequential: 1/f filters carry state)."""
        n = int(n)
        if n < 1:
            raise ConfigError("simulator: block length must be >= 1")
        c = self.config
        start = self._pos
        k = np.arange(start, start + n)
        t_s = k / self.fs
        t_ns = sample_times_ns(self.sample_time_ns(start), self.fs, n)
        end_ns = self.sample_time_ns(start + n)
        tb = self.t_bath_k(t_s)
        b = self.b_field_t(t_s)
        v = self._v_set * self._bias_factor_of_samples(k)[None, :]
        p_opt = self.optical_signal_w(t_s)
        if self._sigma_p_w > 0:
            noise = self._photon.take(start, n)
            if self._pink is not None:
                noise = noise + self._pink.next(n)
            p_opt = p_opt + self._sigma_p_w * noise
        op = solve_quasi_static(self._pa, p_opt, tb[None, :], b[None, :], v,
                                r_guess_ohm=self._guess_r(p_opt, tb, b, v), dropped0=self._dropped)
        self._dropped = op.dropped[:, -1]  # the latch carries into the next block
        self._r_prev = np.where(op.state[:, -1:] == model.STATE_TRANSITION, op.r_ohm[:, -1:], self._r_prev)
        i_meas = model.readout_current_a(self._pa, op.i_a, b[None, :])
        counts = i_meas / self._pa.gain_a_per_count
        ci, cq = counts.real, counts.imag
        if c.nei_a_rthz > 0:
            ci = ci + self._sigma_counts * self._read_i.take(start, n)
            cq = cq + self._sigma_counts * self._read_q.take(start, n)
        # Counts are int32 (the readout's word): round, and pin to the rails like an ADC.
        lim = float(np.iinfo(np.int32).max)
        ci = np.clip(np.rint(ci), -lim, lim).astype(np.int32)
        cq = np.clip(np.rint(cq), -lim, lim).astype(np.int32)
        hk = self._housekeeping(int(t_ns[0]), end_ns)
        self._pos += n
        return SimBlock(
            start_index=start, t_ns=t_ns, counts_i=ci, counts_q=cq, hk=hk,
            truth_p_opt_w=p_opt, truth_t_bath_k=tb, truth_b_field_t=b, truth_v_thev_v=v,
            truth_state=op.state,
        )

    def _guess_r(self, p_opt, tb, b, v):
        """Starting point for the forward solve: one Newton step from the last solution.

        Linearised at the previous block's last sample with this block's first
        environment; the bath term is exact (it enters only as ``K T_bath^n``).
        """
        pa = self._pa
        r0 = self._r_prev
        p0, s0 = _power_and_slope(pa, r0, tb[0], b[0], v[:, :1])
        excess = pa.k_w_per_k_n * (tb[None, :] ** pa.n - tb[0] ** pa.n)
        return r0 + (p_opt + excess - p0) / s0

    def blocks(self, block_samples: int, total_samples: int | None = None) -> Iterator[SimBlock]:
        """Blocks of ``block_samples`` until ``total_samples`` (forever if None)."""
        produced = 0
        while total_samples is None or produced < total_samples:
            n = block_samples if total_samples is None else min(block_samples, total_samples - produced)
            yield self.next_block(n)
            produced += n

    def _housekeeping(self, start_ns: int, end_ns: int) -> tuple:
        c = self.config
        out = []
        for sensor, rate, phase, fn, sigma, stream, unit in (
            ("t_bath", c.hk_t_bath_rate_hz, 0.37, self.t_bath_k, c.hk_t_bath_noise_k, self._hk_tb_noise, "K"),
            ("b_field", c.hk_b_field_rate_hz, 0.61, self.b_field_t, c.hk_b_field_noise_t, self._hk_b_noise, "T"),
        ):
            j, t = _readings_in(self.t0_ns, rate, phase, start_ns, end_ns)
            if j.size:
                value = fn((t - self.t0_ns) * 1e-9)
                if sigma > 0:
                    value = value + sigma * stream.take(int(j[0]), j.size)[0]
                out.append(HkReadings(sensor, t, np.asarray(value, dtype=float), unit))
        _, t_bias = _readings_in(self.t0_ns, c.hk_bias_rate_hz, 0.13, start_ns, end_ns)
        # A bias change is reported the moment it happens (old value 1 ns before, new at
        # the step), so interpolating housekeeping reproduces the step exactly.
        events = [t for s in self._step_ns for t in (s - 1, s) if start_ns <= t < end_ns]
        if events:
            t_bias = np.union1d(t_bias, np.array(events, dtype=np.int64))
        if t_bias.size:
            factor = self.bias_factor(t_bias)
            channels = np.arange(c.channels, dtype=np.int32)
            for b in range(c.boards):
                for m in range(c.modules):
                    rows = self.module_rows(b, m)
                    value = factor[:, None] * self._v_set[rows, 0][None, :]
                    out.append(HkReadings("bias", t_bias, value, "V", board=b, module=m, channels=channels))
        return tuple(out)
