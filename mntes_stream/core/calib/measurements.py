"""The six ground-calibration measurements of paper section 4, as data.

Each measurement is a *sweep*: one condition varied, the others held fixed
(``I_DAN(P_opt, B, V, T_bath, omega)``, one argument at a time). What a sweep
records, per point: the mean complex DAN output in **counts** (``I + 1j Q``)
and its per-component standard deviation (the known measurement noise).

Conditions (all five are known for every point):

- ``p_opt_w``: absolute optical power at the TES, W (calibrated source);
- ``b_field_t``: magnetic field, T;
- ``bias_ratio``: commanded carrier amplitude relative to the operating bias,
  so the Thevenin voltage is ``V = bias_ratio * V0`` (``V0`` is fitted; the
  Thevenin transfer of the bias network is what is unknown, the DAC ratio is exact);
- ``t_bath_k``: bath temperature, K;
- ``freq_hz``: carrier frequency, Hz (the bias frequency except in the network analyses).

============================  ==============  ==========================================
kind                          swept           paper
============================  ==============  ==========================================
``optical_response``          ``p_opt_w``     I(P) at B0, V0, T0, omega0
``field_sensitivity``         ``b_field_t``   I(B) at P0, V, T0, omega0 (one or more biases)
``iv_curve``                  ``bias_ratio``  I(V) at P0, B0, omega0, one or more T_bath
``impedance_temperature``     ``t_bath_k``    R(T) + z = V/I at a small probe bias
``network_normal``            ``freq_hz``     Y(omega) with the TES normal (T > T_c), probe bias
``network_super``             ``freq_hz``     Y(omega) with the TES superconducting, probe bias
============================  ==============  ==========================================
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import numpy as np

from mntes_stream.core.checks import finite_float
from mntes_stream.errors import ConfigError

__all__ = [
    "KINDS",
    "SWEPT_AXIS",
    "CONDITIONS",
    "PROBE_KINDS",
    "Sweep",
    "DetectorCalibration",
    "Campaign",
    "assemble_campaign",
]

KINDS = (
    "optical_response",
    "field_sensitivity",
    "iv_curve",
    "impedance_temperature",
    "network_normal",
    "network_super",
)
SWEPT_AXIS = {
    "optical_response": "p_opt_w",
    "field_sensitivity": "b_field_t",
    "iv_curve": "bias_ratio",
    "impedance_temperature": "t_bath_k",
    "network_normal": "freq_hz",
    "network_super": "freq_hz",
}
CONDITIONS = ("p_opt_w", "b_field_t", "bias_ratio", "t_bath_k", "freq_hz")
# Taken at a small probe bias: no electrothermal latching, the TES sits on R(T).
PROBE_KINDS = frozenset({"impedance_temperature", "network_normal", "network_super"})

_POSITIVE = {"bias_ratio", "t_bath_k", "freq_hz"}


@dataclass(frozen=True, eq=False)
class Sweep:
    """One measurement of one detector: a swept condition and the DAN output.

    Attributes
    ----------
    kind : str
        One of :data:`KINDS`; fixes which condition is swept.
    detector_id : str
    swept : ndarray of float, shape (n,)
        Values of ``SWEPT_AXIS[kind]``.
    fixed : mapping of str to float
        The four other conditions.
    counts : ndarray of complex128, shape (n,)
        Mean DAN output ``I + 1j Q`` per point (may hold NaN for failed points).
    sigma_counts : ndarray of float, shape (n,)
        Standard deviation of each of ``I`` and ``Q`` of the mean, > 0.
    """

    kind: str
    detector_id: str
    swept: np.ndarray
    fixed: Mapping[str, float]
    counts: np.ndarray
    sigma_counts: np.ndarray

    def __post_init__(self) -> None:
        if self.kind not in KINDS:
            raise ConfigError(f"unknown calibration measurement kind {self.kind!r} (known: {', '.join(KINDS)})")
        if not isinstance(self.detector_id, str) or not self.detector_id:
            raise ConfigError(f"{self.kind}: detector_id must be a non-empty string")
        where = f"{self.detector_id} {self.kind}"
        swept = np.array(self.swept, dtype=float).reshape(-1) if np.ndim(self.swept) else None
        counts = np.array(self.counts, dtype=complex)
        sigma = np.array(self.sigma_counts, dtype=float)
        if swept is None or counts.ndim != 1 or counts.shape != swept.shape:
            raise ConfigError(f"{where}: swept values and counts must be 1-D of equal length")
        if sigma.ndim == 0:
            sigma = np.full(swept.shape, float(sigma))
        if sigma.shape != swept.shape:
            raise ConfigError(f"{where}: sigma_counts must be a scalar or match the sweep length")
        if np.any(~(sigma > 0) & np.isfinite(sigma)):
            raise ConfigError(f"{where}: sigma_counts must be > 0")
        expected = set(CONDITIONS) - {SWEPT_AXIS[self.kind]}
        fixed = dict(self.fixed)
        if set(fixed) != expected:
            raise ConfigError(
                f"{where}: fixed conditions must be exactly {sorted(expected)}, got {sorted(fixed)}"
            )
        for name, value in fixed.items():
            try:
                value = float(value)
            except (TypeError, ValueError):
                raise ConfigError(f"{where}: {name} must be a number, got {value!r}") from None
            if not math.isfinite(value) or (name in _POSITIVE and value <= 0):
                raise ConfigError(f"{where}: {name} = {value} is not a valid fixed condition")
            fixed[name] = value
        for name, arr in (("swept", swept), ("counts", counts), ("sigma_counts", sigma)):
            arr.setflags(write=False)
            object.__setattr__(self, name, arr)
        object.__setattr__(self, "fixed", fixed)

    @property
    def axis(self) -> str:
        return SWEPT_AXIS[self.kind]

    def __len__(self) -> int:
        return int(self.swept.size)

    def condition(self, name: str) -> np.ndarray:
        """Condition ``name`` at every point, shape (n,)."""
        if name == self.axis:
            return self.swept
        return np.full(self.swept.shape, self.fixed[name])

    def finite_mask(self) -> np.ndarray:
        """Points with finite swept value, counts and noise (and valid positive conditions)."""
        ok = np.isfinite(self.swept) & np.isfinite(self.counts.real) & np.isfinite(self.counts.imag)
        ok &= np.isfinite(self.sigma_counts) & (self.sigma_counts > 0)
        if self.axis in _POSITIVE:
            ok &= self.swept > 0
        return ok

    def select(self, mask: np.ndarray) -> Sweep:
        """The sweep restricted to the points where ``mask`` is True."""
        return Sweep(self.kind, self.detector_id, self.swept[mask], self.fixed, self.counts[mask], self.sigma_counts[mask])


@dataclass(frozen=True, eq=False)
class DetectorCalibration:
    """Everything measured on one detector, plus the few numbers known a priori.

    Attributes
    ----------
    detector_id : str
    bias_freq_hz : float
        Carrier (bias) frequency of the channel in operation, ``omega0 / 2 pi``.
    gain_abs_a_per_count : float
        Magnitude of the DAN gain (A per count) from the electronics' transfer
        function. The six measurements in counts are invariant under
        ``(R, z, V, g, m) -> (s R, s z, sqrt(s) V, g/sqrt(s), m/sqrt(s))``, so
        one absolute scale must come from outside; the conversion counts ->
        watts does not depend on it (see README "Ground calibration").
    p_opt_w, t_bath_k, b_field_t : float
        Fiducial operating conditions (written to the parameter file).
    sweeps : tuple of Sweep
    """

    detector_id: str
    bias_freq_hz: float
    gain_abs_a_per_count: float
    p_opt_w: float
    t_bath_k: float
    b_field_t: float = 0.0
    sweeps: tuple = field(default=())

    def __post_init__(self) -> None:
        if not isinstance(self.detector_id, str) or not self.detector_id:
            raise ConfigError("detector_id must be a non-empty string")
        for name in ("bias_freq_hz", "gain_abs_a_per_count", "p_opt_w", "t_bath_k", "b_field_t"):
            object.__setattr__(self, name, finite_float(self.detector_id, name, getattr(self, name)))
        for name in ("bias_freq_hz", "gain_abs_a_per_count", "t_bath_k"):
            if getattr(self, name) <= 0:
                raise ConfigError(f"{self.detector_id}: {name} must be > 0")
        if self.p_opt_w < 0:
            raise ConfigError(f"{self.detector_id}: p_opt_w must be >= 0")
        sweeps = tuple(self.sweeps)
        for s in sweeps:
            if not isinstance(s, Sweep):
                raise ConfigError(f"{self.detector_id}: sweeps must be Sweep objects")
            if s.detector_id != self.detector_id:
                raise ConfigError(
                    f"mismatched detector id: a {s.kind} sweep of {s.detector_id!r} given to {self.detector_id!r}"
                )
        object.__setattr__(self, "sweeps", sweeps)

    def by_kind(self, kind: str) -> list[Sweep]:
        return [s for s in self.sweeps if s.kind == kind]

    def kinds(self) -> set[str]:
        return {s.kind for s in self.sweeps}

    def replace_sweeps(self, sweeps: Iterable[Sweep]) -> DetectorCalibration:
        return DetectorCalibration(
            self.detector_id, self.bias_freq_hz, self.gain_abs_a_per_count,
            self.p_opt_w, self.t_bath_k, self.b_field_t, tuple(sweeps),
        )


@dataclass(frozen=True, eq=False)
class Campaign:
    """A calibration campaign: detectors in file order, plus what could not be attributed.

    Attributes
    ----------
    detectors : dict of str to DetectorCalibration
    orphans : dict of str to str
        Detector ids that have sweeps but no header (so no gain or bias
        frequency), mapped to the reason; the fit lists them as flagged.
    metadata : dict of str to str
    """

    detectors: dict
    orphans: dict = field(default_factory=dict)
    metadata: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.detectors)


def assemble_campaign(headers: Iterable[DetectorCalibration], sweeps: Iterable[Sweep],
                      metadata: Mapping[str, str] | None = None) -> Campaign:
    """Group sweeps under their detectors' headers.

    A header given twice is an error (ambiguous gain); sweeps whose detector
    has no header become :attr:`Campaign.orphans` (reported, never fitted).
    """
    dets: dict[str, DetectorCalibration] = {}
    for h in headers:
        if h.detector_id in dets:
            raise ConfigError(f"detector {h.detector_id!r} has two calibration headers")
        dets[h.detector_id] = h
    grouped: dict[str, list[Sweep]] = {d: list(h.sweeps) for d, h in dets.items()}
    orphans: dict[str, str] = {}
    orphan_kinds: dict[str, list[str]] = {}
    for s in sweeps:
        if s.detector_id in grouped:
            grouped[s.detector_id].append(s)
        else:
            orphan_kinds.setdefault(s.detector_id, []).append(s.kind)
    for det_id, kinds in orphan_kinds.items():
        orphans[det_id] = (
            f"{len(kinds)} sweep(s) ({', '.join(sorted(set(kinds)))}) but no detector header "
            "(gain and bias frequency unknown): mismatched detector id?"
        )
    out = {d: dets[d].replace_sweeps(grouped[d]) for d in dets}
    return Campaign(detectors=out, orphans=orphans, metadata=dict(metadata or {}))
