"""Counts to optical power: every conversion kind behind one interface (pure, no I/O).

Kinds (:func:`make_converter`):

- ``"table"``: MNTES with structured response tables (:mod:`core.tables`):
  only the transition shape is tabulated; bath temperature, bias and field
  are exact. Compiled kernel (numba) by default, numpy fallback. Accuracy
  better than 1e-19 W against the exact inverse over the table domain.
- ``"grid"``: MNTES by the paper's general route: per-detector 1-D tables of
  P(R) for each discrete bias state and B node, cubic in B, exact in bath
  temperature. Accuracy documented in the README (looser).
- ``"exact"``: :func:`core.model.invert_current` per sample, the oracle.
- ``"linear"``: today's linear conversion, ``P = P0 + Re((i - i0) / S)`` with
  S (paper eq. 3) and i0 at the nominal operating point; ignores environment.
- ``"electrical"``: SPT-3G style, ``P = P_total,nominal - Re(V_tes conj(I))``
  with RMS quantities and the sample's bias; ignores bath temperature and field.

Every kind returns a :class:`PowerBlock` with the same flag semantics
(``core.flags``): input that cannot be converted is NaN and flagged, never a
silent number. Flag rules, per sample:

- ``INVALID_INPUT``: counts not finite or at/beyond the int32 rails
  (``|x| >= 2**31 - 1``: ADC saturation or sentinel), zero current after the
  pickup is removed, non-finite field, bath temperature or bias not > 0
  (not added where the housekeeping already says ``HK_MISSING``);
- thresholds on ``R = Re(sqrt(2) V / i - z)`` per detector from
  :func:`core.model.flag_thresholds` (the model, the readout noise
  ``readout_noise_a`` and the counts' quantisation, with 7 sigma margins):
- ``SATURATED``: R at or above the lowest of: the top of the model less the
  noise margin, the point where one count moves the power by more than
  ``model.P_RESOLUTION_W``, and loop gain < ``model.LOOP_GAIN_NORMAL``;
- ``SUPERCONDUCTING``: R not above ``|z|`` by the noise margin (loop gain
  <= 0: the detector dropped out of the transition), with ``LATCHED`` too where
  R is above the bottom of the transition by the margin (resistive, latched);
- ``PHASE_RESIDUAL``: the quadrature current the model does not explain,
  ``|Im(sqrt(2) V / i - z)| |i|^2 / (sqrt(2) V)``, above 7 sigma of readout
  noise and quantisation (the value is kept);
- ``OUT_OF_TABLE``: inside the branch but outside the table's R range (or, for
  ``"grid"``, a bias matching no tabulated bias state); for the baselines
  ``linear`` and ``electrical``, outside the R range their linearisation
  domain (``TableDomain``) reaches;
- ``NONLINEAR``: baselines only, a usable sample whose value differs from the
  exact inverse (:func:`core.model.invert_current`, same counts and
  environment) by more than ``tolerance_w`` (default ``BASELINE_TOLERANCE_W``),
  or where the exact inverse gives none; the value is kept. The exact inverse
  is known from a ``table`` bank built with the converter, and computed only
  near the tolerance (``nonlinear_check``; same flags, 40x faster on live
  chunks); the baselines' own arithmetic is one compiled pass
  (``core._baselines``), at numpy's ``a * x + b`` speed;
- ``ENV_OUT_OF_RANGE``: table kinds and baselines, environment outside the (bank's) domain
  (the value is still given; ``"table"`` stays exact there when R is covered);
- ``UNKNOWN_CHANNEL``: detector id without parameters/tables (whole row);
- housekeeping ``flags`` of the environment are OR-ed in.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from mntes_stream.core import _baselines, _kernels, model
from mntes_stream.core import flags as fl
from mntes_stream.core.params import DetectorParams
from mntes_stream.core.tables import TableBank, TableDomain, build_bank, params_identity, resistance_range_ohm
from mntes_stream.errors import ConfigError, SchemaError, TableDomainError

__all__ = [
    "CONVERTER_KINDS",
    "BASELINE_TOLERANCE_W",
    "COUNTS_RAIL",
    "EnvironmentBlock",
    "PowerBlock",
    "Converter",
    "make_converter",
    "BASELINE_KINDS",
    "baseline_can_take",
    "ExactConverter",
    "LinearConverter",
    "ElectricalConverter",
    "TableConverter",
    "numba_available",
]

CONVERTER_KINDS = ("table", "grid", "exact", "linear", "electrical")
COUNTS_RAIL = _kernels.RAIL
SQRT2 = model.SQRT2
# Photon noise per sample (issue 17): no unflagged baseline sample is further than this from the model.
BASELINE_TOLERANCE_W = 1e-17


@dataclass(frozen=True)
class EnvironmentBlock:
    """Environment aligned to every sample of a counts block.

    Attributes
    ----------
    t_bath_k : ndarray, shape (n_samp,) shared by all detectors, or (n_det, n_samp)
    b_field_t : ndarray, shape (n_samp,) or (n_det, n_samp)
    v_thev_v : ndarray, shape (n_det,) or (n_det, n_samp), optional
        RMS bias; None means each detector's nominal ``params.v_thev_v``.
    flags : ndarray of uint16, shape (n_samp,) or (n_det, n_samp), optional
        Housekeeping flags (``HK_STALE``, ``HK_MISSING``, ...) OR-ed into the output.
    """

    t_bath_k: np.ndarray
    b_field_t: np.ndarray
    v_thev_v: np.ndarray | None = None
    flags: np.ndarray | None = None


@dataclass(frozen=True)
class PowerBlock:
    """Converted power.

    Attributes
    ----------
    p_opt_w : ndarray of float64, shape (n_det, n_samp)
        NaN wherever ``flags & core.flags.UNUSABLE``.
    flags : ndarray of uint16, shape (n_det, n_samp)
    identity : str
        Identity (hash) of the parameters/tables that produced it.
    """

    p_opt_w: np.ndarray
    flags: np.ndarray
    identity: str = ""


@runtime_checkable
class Converter(Protocol):
    """What every conversion kind provides."""

    kind: str
    identity: str
    detector_ids: tuple[str, ...]

    def convert(self, detector_ids: Sequence[str], counts_i: np.ndarray, counts_q: np.ndarray,
                env: EnvironmentBlock) -> PowerBlock: ...


def numba_available() -> bool:
    """True when the compiled kernels can be used."""
    return _kernels.numba is not None


# --- input checking (shared by every kind) ------------------------------------------------

@dataclass(frozen=True)
class _Inputs:
    rows: np.ndarray          # (n_det,) int64 index into the converter's detectors, -1 unknown
    counts_i: np.ndarray      # (n_det, n_samp) int32 or float64
    counts_q: np.ndarray
    t_bath_k: np.ndarray      # (n_det, n_samp) float64 views (may have zero strides)
    b_field_t: np.ndarray
    v_thev_v: np.ndarray
    hk_flags: np.ndarray      # (n_det, n_samp) uint16 view
    log_t_bath: np.ndarray    # log(t_bath_k), computed before broadcasting


def _counts(name: str, a) -> np.ndarray:
    if not isinstance(a, np.ndarray):
        raise SchemaError(f"{name}: expected a numpy array, got {type(a).__name__}")
    if a.ndim != 2:
        raise SchemaError(f"{name}: expected shape (n_det, n_samp), got {a.shape}")
    if a.dtype == np.int32:
        return a
    if np.issubdtype(a.dtype, np.integer) or np.issubdtype(a.dtype, np.floating):
        return a.astype(np.float64)
    raise SchemaError(f"{name}: counts must be int32 (or another integer/float type), got {a.dtype}")


def _env_array(name: str, a, shape: tuple[int, int], per_det_1d: bool = False) -> np.ndarray:
    """Validate an environment array; return it reshaped to broadcast to ``shape`` (no copy)."""
    a = np.asarray(a)
    if a.dtype.kind not in "iuf":
        raise SchemaError(f"env.{name}: expected real numbers, got dtype {a.dtype}")
    a = a.astype(np.float64, copy=False)
    n_det, n_samp = shape
    if a.ndim == 0:
        return a.reshape(1, 1)
    if a.ndim == 1:
        if per_det_1d:
            if a.shape != (n_det,):
                raise SchemaError(f"env.{name}: 1-D must be (n_det,) = ({n_det},), got {a.shape}")
            return a[:, None]
        if a.shape != (n_samp,):
            raise SchemaError(f"env.{name}: 1-D must be (n_samp,) = ({n_samp},), got {a.shape}")
        return a[None, :]
    if a.shape != shape:
        raise SchemaError(f"env.{name}: expected {shape}, got {a.shape}")
    return a


def _hk_flags(f, shape: tuple[int, int]) -> np.ndarray:
    if f is None:
        return np.broadcast_to(np.zeros((), dtype=np.uint16), shape)
    f = np.asarray(f)
    if f.dtype.kind not in "iu":
        raise SchemaError(f"env.flags: expected uint16, got {f.dtype}")
    if f.dtype != np.uint16:
        if f.size and (f.min() < 0 or f.max() > 0xFFFF):
            raise SchemaError("env.flags: values do not fit in uint16")
        f = f.astype(np.uint16)
    n_det, n_samp = shape
    if f.shape == (n_samp,):
        return np.broadcast_to(f[None, :], shape)
    if f.shape != shape:
        raise SchemaError(f"env.flags: expected ({n_samp},) or {shape}, got {f.shape}")
    return f


def _prepare(rows_of, v_nominal: np.ndarray, detector_ids, counts_i, counts_q,
             env: EnvironmentBlock) -> _Inputs:
    ci = _counts("counts_i", counts_i)
    cq = _counts("counts_q", counts_q)
    if ci.shape != cq.shape:
        raise SchemaError(f"counts_i {ci.shape} and counts_q {cq.shape} differ in shape")
    if cq.dtype != ci.dtype:
        ci, cq = ci.astype(np.float64), cq.astype(np.float64)
    if isinstance(detector_ids, str) or len(detector_ids) != ci.shape[0]:
        raise SchemaError(f"need one detector id per counts row ({ci.shape[0]})")
    if not isinstance(env, EnvironmentBlock):
        raise SchemaError(f"env must be an EnvironmentBlock, got {type(env).__name__}")
    shape = ci.shape
    rows = rows_of(detector_ids)
    tb = _env_array("t_bath_k", env.t_bath_k, shape)
    with np.errstate(invalid="ignore", divide="ignore"):
        ltb = np.log(tb)  # before broadcasting: n_samp logs for a shared bath, not n_det * n_samp
    b = np.broadcast_to(_env_array("b_field_t", env.b_field_t, shape), shape)
    if env.v_thev_v is None:
        v_nom = np.where(rows >= 0, v_nominal[np.maximum(rows, 0)] if v_nominal.size else np.nan, np.nan)
        v = np.broadcast_to(v_nom[:, None], shape)
    else:
        v = np.broadcast_to(_env_array("v_thev_v", env.v_thev_v, shape, per_det_1d=True), shape)
    tb, ltb = np.broadcast_to(tb, shape), np.broadcast_to(ltb, shape)
    return _Inputs(rows, ci, cq, tb, b, v, _hk_flags(env.flags, shape), ltb)


_PHYS_COLUMNS = 21


def _phys(params: Sequence[DetectorParams], readout_noise_a: float) -> np.ndarray:
    """Per-detector scalars for the kernels, shape (n_det, 21) (see ``_kernels``).

    Columns 12, 13 and 15-20 are the flag thresholds of
    :func:`core.model.flag_thresholds`: resistances and their noise margins
    (Ohm V, divided by each sample's bias), and the phase-residual limit (A).
    """
    out = np.empty((len(params), _PHYS_COLUMNS))
    for k, p in enumerate(params):
        th = model.flag_thresholds(p, readout_noise_a)
        out[k] = (
            p.gain_a_per_count.real, p.gain_a_per_count.imag,
            p.pickup_a_per_t.real, p.pickup_a_per_t.imag,
            p.z_thev_ohm.real, p.z_thev_ohm.imag,
            p.k_w_per_k_n, p.n, p.t_c_shift_k_per_t, p.t_c_shift_k_per_t2,
            p.current_shift_k_per_a, p.v_thev_v, th.r_z_ohm, th.r_cap_ohm, p.t_bath_k,
            th.r_bottom_ohm, th.phase_limit_a, th.r_top_ohm, th.k_top_ohm_v, th.k_z_ohm_v, th.k_bottom_ohm_v,
        )
    return out


_NO_DOMAIN = np.array([-np.inf, np.inf] * 3)


def _front(inp: _Inputs, phys: np.ndarray, r0: int, r1: int):
    """Rows ``r0:r1`` through the shared front end (no environment domain)."""
    return _kernels.front_numpy(inp.counts_i[r0:r1], inp.counts_q[r0:r1], inp.t_bath_k[r0:r1], inp.b_field_t[r0:r1],
                       inp.v_thev_v[r0:r1], inp.hk_flags[r0:r1], inp.rows[r0:r1], phys, _NO_DOMAIN)


def _measured_current(phys: np.ndarray, rows: np.ndarray, inp: _Inputs, r0: int, r1: int) -> np.ndarray:
    """Gain times counts, pickup included (what the readout reports), shape (r1 - r0, n_samp)."""
    gain = (phys[rows, 0] + 1j * phys[rows, 1])[:, None]
    return gain * (np.asarray(inp.counts_i[r0:r1], float) + 1j * np.asarray(inp.counts_q[r0:r1], float))


def _finish(p: np.ndarray, flags: np.ndarray) -> None:
    np.copyto(p, np.nan, where=(flags & fl.UNUSABLE) != 0)


_CHUNK_ELEMENTS = 1 << 20


def _row_chunks(n_rows: int, n_samp: int):
    step = max(1, _CHUNK_ELEMENTS // max(n_samp, 1))
    for r0 in range(0, n_rows, step):
        yield r0, min(n_rows, r0 + step)


class _Base:
    kind: str = ""

    def __init__(self, params: Sequence[DetectorParams], identity: str,
                 readout_noise_a: float = model.DEFAULT_READOUT_NOISE_A) -> None:
        self.params = tuple(params)
        self.detector_ids = tuple(p.detector_id for p in self.params)
        self.identity = identity
        self._index = {d: k for k, d in enumerate(self.detector_ids)}
        self._rows_cache: dict[tuple, np.ndarray] = {}
        self.readout_noise_a = float(readout_noise_a)
        self._phys = _phys(self.params, self.readout_noise_a)
        self._v_nominal = self._phys[:, 11].copy() if self.params else np.empty(0)

    def __setstate__(self, state: dict) -> None:
        # A converter pickled by an older version (a restart snapshot) may carry the kernels'
        # per-detector scalars in an older layout: the compiled kernel does not bounds-check,
        # so rebuild them from the parameters rather than read past the end.
        self.__dict__.update(state)
        if self._phys.shape[1] != _PHYS_COLUMNS:
            self.readout_noise_a = float(state.get("readout_noise_a", model.DEFAULT_READOUT_NOISE_A))
            self._phys = _phys(self.params, self.readout_noise_a)

    def _rows(self, detector_ids) -> np.ndarray:
        """Index of each id in this converter (-1 unknown); cached per id list (a stream repeats it)."""
        key = tuple(detector_ids)
        try:
            rows = self._rows_cache.get(key)
        except TypeError:  # unhashable entries: not ids, so unknown channels
            key, rows = None, None
        if rows is None:
            rows = np.array([self._index.get(d, -1) if isinstance(d, str) else -1 for d in detector_ids], dtype=np.int64)
            rows.flags.writeable = False
            if key is not None:
                if len(self._rows_cache) >= 256:
                    self._rows_cache.clear()
                self._rows_cache[key] = rows
        return rows

    def __repr__(self) -> str:
        return f"<{type(self).__name__} kind={self.kind!r} detectors={len(self.detector_ids)} identity={self.identity[:12]}>"

    def convert(self, detector_ids: Sequence[str], counts_i: np.ndarray, counts_q: np.ndarray,
                env: EnvironmentBlock, low_responsivity: np.ndarray | None = None) -> PowerBlock:
        """Convert a block of counts to optical power.

        Parameters
        ----------
        detector_ids : sequence of str, length n_det
        counts_i, counts_q : ndarray, shape (n_det, n_samp)
            int32 (other integer or float types are accepted; floats may be NaN).
        env : EnvironmentBlock
        low_responsivity : ndarray, shape (n_bank, ``_kernels.LOW_COLS``), optional
            Only where :attr:`fuses_low_responsivity`: flag LOW_RESPONSIVITY in the
            conversion itself (``core.uncertainty.NoiseModel.low_record``).

        Returns
        -------
        PowerBlock with arrays of shape (n_det, n_samp)

        Raises
        ------
        SchemaError
            Only for arrays of the wrong shape or dtype.
        ConfigError
            ``low_responsivity`` given to a converter that does not fuse it, or of the wrong shape.
        """
        if low_responsivity is not None:
            if not self.fuses_low_responsivity:
                raise ConfigError(f"a {self.kind!r} converter ({getattr(self, 'backend', 'numpy')}) does not flag "
                                  "LOW_RESPONSIVITY itself: use core.uncertainty.sigma_p_block")
            if np.shape(low_responsivity) != (len(self.detector_ids), _kernels.LOW_COLS):
                raise ConfigError(f"low_responsivity: expected shape ({len(self.detector_ids)}, {_kernels.LOW_COLS}), "
                                  f"got {np.shape(low_responsivity)}")
        inp = _prepare(self._rows, self._v_nominal, detector_ids, counts_i, counts_q, env)
        n_det, n_samp = inp.counts_i.shape
        p = np.empty((n_det, n_samp))
        f = np.empty((n_det, n_samp), dtype=np.uint16)
        if low_responsivity is None:
            self._convert(inp, p, f)
        else:
            self._convert(inp, p, f, low=low_responsivity)
        return PowerBlock(p_opt_w=p, flags=f, identity=self.identity)

    def _convert(self, inp: _Inputs, p: np.ndarray, f: np.ndarray) -> None:
        raise NotImplementedError

    @property
    def fuses_low_responsivity(self) -> bool:
        """True when :meth:`convert` can flag LOW_RESPONSIVITY in its own pass (the compiled "table" kernel)."""
        return False

    # What core.uncertainty needs to follow a conversion sample by sample, without reaching into privates.
    @property
    def kernel_constants(self) -> np.ndarray:
        """Per-detector constants the kernels read, one row per detector (shared: never modify)."""
        return self._phys

    def inputs(self, detector_ids: Sequence[str], counts_i: np.ndarray, counts_q: np.ndarray,
               env: EnvironmentBlock) -> _Inputs:
        """The arguments of :meth:`convert` as it works on them: checked, rows looked up, environment broadcast."""
        return _prepare(self._rows, self._v_nominal, detector_ids, counts_i, counts_q, env)

    def measured_current(self, inp: _Inputs, rows: np.ndarray) -> np.ndarray:
        """Gain times counts (what the readout reports) of every row of ``inp``; ``rows``: each row's detector."""
        return _measured_current(self._phys, rows, inp, 0, inp.counts_i.shape[0])


class ExactConverter(_Base):
    """Per-sample exact inverse (:func:`core.model.invert_current`): the oracle."""

    kind = "exact"

    def __init__(self, params: Sequence[DetectorParams], readout_noise_a: float = model.DEFAULT_READOUT_NOISE_A) -> None:
        super().__init__(params, params_identity(params, {"kind": "exact"}), readout_noise_a)

    def _convert(self, inp, p, f):
        n_det, n_samp = p.shape
        for r0, r1 in _row_chunks(n_det, n_samp):
            # The flags are the shared front end's thresholds; the oracle gives the value.
            _, _, flags, _, _ = _front(inp, self._phys, r0, r1)
            i = _measured_current(self._phys, np.maximum(inp.rows[r0:r1], 0), inp, r0, r1)
            for k in range(r0, r1):
                row = inp.rows[k]
                if row < 0:
                    continue
                with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                    inv = model.invert_current(self.params[row], i[k - r0], inp.t_bath_k[k],
                                               inp.b_field_t[k], inp.v_thev_v[k])
                p[k] = inv.p_opt_w
            f[r0:r1] = flags
        _finish(p, f)


# The table kind is within 1e-19 W of the exact inverse; where a baseline's distance from the
# table's power is within this of ``tolerance_w``, the exact inverse decides NONLINEAR instead.
NONLINEAR_MARGIN_W = 1e-18
NONLINEAR_CHECKS = ("table", "exact")


BASELINE_KINDS = ("linear", "electrical")


def _nominal_in_transition(q: DetectorParams):
    """The nominal operating point (``p_opt_w``, ``t_bath_k``, no field, ``v_thev_v``) if in the transition, else None."""
    op = model.solve_operating_point(q, q.p_opt_w, q.t_bath_k, 0.0, q.v_thev_v)
    return op if int(op.state) == model.STATE_TRANSITION else None


def baseline_can_take(q: DetectorParams) -> bool:
    """Whether a baseline (linear, electrical) can linearise this detector: its nominal operating point is
    in the transition (not latched, not normal)."""
    return _nominal_in_transition(q) is not None


class _Baseline(_Base):
    """Linear baselines: built at each detector's nominal operating point, env ignored.

    ``tolerance_w``: samples whose value differs from the exact inverse by more
    get ``NONLINEAR`` (value kept); None or 0 disables the check.
    ``nonlinear_check``: how the exact inverse is known. ``"table"`` (default):
    from a ``table`` bank of the same detectors and domain, built with the
    converter (about 1.5 s per 1,000 detectors), at the table kernel's speed;
    samples whose distance from the table's power is within
    ``NONLINEAR_MARGIN_W`` of the tolerance, that the table gives no value
    for, or flagged ``PHASE_RESIDUAL`` or ``ENV_OUT_OF_RANGE`` (where the
    table's 1e-19 W is not promised), get the exact inverse, so the flags are
    those of ``"exact"``.
    ``"exact"``: :func:`core.model.invert_current` for every usable sample
    (0.4 M samples per CPU second on live 128 x 20 chunks, where ``"table"``
    does 8-16). The attribute ``nonlinear_check`` says which is in use
    (``"exact"`` too when no bank could be built; ``"off"`` without a tolerance).
    """

    def __init__(self, params: Sequence[DetectorParams], readout_noise_a: float = model.DEFAULT_READOUT_NOISE_A,
                 domain: TableDomain | None = None, tolerance_w: float | None = BASELINE_TOLERANCE_W,
                 nonlinear_check: str = "table") -> None:
        domain = domain or TableDomain()
        tol = 0.0 if tolerance_w is None else tolerance_w
        if not isinstance(tol, (int, float)) or not (np.isfinite(tol) and tol >= 0):
            raise ConfigError(f"tolerance_w must be None or a finite number >= 0 (W), got {tolerance_w!r}")
        if nonlinear_check not in NONLINEAR_CHECKS:
            raise ConfigError(f"nonlinear_check must be one of {', '.join(NONLINEAR_CHECKS)}, got {nonlinear_check!r}")
        self.tolerance_w = float(tol)
        # The default keeps the identity older runs recorded; another tolerance flags differently.
        extra = {"kind": self.kind} if self.tolerance_w == BASELINE_TOLERANCE_W else {
            "kind": self.kind, "tolerance_w": self.tolerance_w}
        super().__init__(params, params_identity(params, extra), readout_noise_a)
        self._nominal = []
        for q in self.params:
            op = _nominal_in_transition(q)
            if op is None:
                raise ConfigError(f"{q.detector_id}: nominal operating point is not in the transition")
            self._nominal.append(op)
        # The linearisation's domain: the environment of ``domain`` and the R range its states reach.
        self.domain = domain
        self._dom = np.array([*domain.t_bath_k, *domain.b_field_t, *domain.v_frac], dtype=float)
        self._r_range = np.array([resistance_range_ohm(q, domain) for q in self.params]).reshape(-1, 2)
        # The flags do not depend on how the exact inverse is known: not part of the identity.
        self._check = None
        if self.tolerance_w and nonlinear_check == "table":
            try:
                check = TableConverter(build_bank(self.params, kind="table", domain=domain),
                                       readout_noise_a=self.readout_noise_a)
            except (ConfigError, TableDomainError):  # no table for these: the exact route, same flags, slower
                check = None
            if check is not None and check.detector_ids == self.detector_ids:  # its rows must be ours
                self._check = check
        self.nonlinear_check = "table" if self._check is not None else "exact" if self.tolerance_w else "off"

    def _constants(self) -> np.ndarray:
        """The compiled kernel's per-detector constants (``_baselines.constants``), made once."""
        cst = self.__dict__.get("_cst")  # absent from converters pickled by older versions
        if cst is None:
            cst = self._cst = _baselines.constants(self._phys, self._dom, self._r_range, self._power_constants())
        return cst

    def _power_constants(self) -> np.ndarray:
        raise NotImplementedError

    def _convert(self, inp, p, f):
        if _baselines.available():
            # One compiled pass for flags and values; the numpy route below is its reference.
            _baselines.baseline_numba(inp.counts_i, inp.counts_q, inp.t_bath_k, inp.b_field_t, inp.v_thev_v,
                                      inp.hk_flags, inp.rows, self._constants(), self._dom, self._kernel_kind, p, f)
            if self.__dict__.get("_check") is not None:
                self._flag_nonlinear_from_table(inp, p, f)
            elif self.__dict__.get("tolerance_w", BASELINE_TOLERANCE_W):
                n_det, n_samp = p.shape
                for r0, r1 in _row_chunks(n_det, n_samp):
                    i_meas = _measured_current(self._phys, np.maximum(inp.rows[r0:r1], 0), inp, r0, r1)
                    self._flag_nonlinear(inp, r0, r1, i_meas, p, f)
            return
        self._convert_numpy(inp, p, f)

    def _flag_nonlinear_from_table(self, inp: _Inputs, p: np.ndarray, f: np.ndarray) -> None:
        """``NONLINEAR`` as :meth:`_flag_nonlinear` gives it, the table's power standing in for
        the exact inverse wherever it decides by more than ``NONLINEAR_MARGIN_W``."""
        tol = self.tolerance_w
        p_tab = np.empty_like(p)
        f_tab = np.empty_like(f)
        self._check._convert(inp, p_tab, f_tab)  # same detectors, same order: the same rows
        checked = ((f & fl.UNUSABLE) == 0) & np.isfinite(p) & (inp.rows >= 0)[:, None]
        # The table's accuracy holds where the model explains the sample and its environment is
        # inside the bank's: elsewhere (quadrature left over, environment outside) the exact inverse.
        vouched = (f & (fl.PHASE_RESIDUAL | fl.ENV_OUT_OF_RANGE)) == 0
        with np.errstate(invalid="ignore"):
            dist = np.abs(p - p_tab)
            far = checked & vouched & (dist > tol + NONLINEAR_MARGIN_W)
            near = checked & ~far & ~(vouched & (dist <= tol - NONLINEAR_MARGIN_W))  # NaN table power: near
        f[far] |= fl.NONLINEAR
        for k in np.flatnonzero(near.any(axis=1)):
            idx = np.flatnonzero(near[k])
            d = inp.rows[k]
            gain = complex(self._phys[d, 0], self._phys[d, 1])
            i_meas = gain * (np.asarray(inp.counts_i[k, idx], float) + 1j * np.asarray(inp.counts_q[k, idx], float))
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                exact = model.invert_current(self.params[d], i_meas, inp.t_bath_k[k, idx], inp.b_field_t[k, idx],
                                             inp.v_thev_v[k, idx]).p_opt_w
            f[k, idx[~(np.abs(p[k, idx] - exact) <= tol)]] |= fl.NONLINEAR

    def _convert_numpy(self, inp, p, f):
        n_det, n_samp = p.shape
        for r0, r1 in _row_chunks(n_det, n_samp):
            rows = np.maximum(inp.rows[r0:r1], 0)
            r, _, f[r0:r1], _, ok = _kernels.front_numpy(
                inp.counts_i[r0:r1], inp.counts_q[r0:r1], inp.t_bath_k[r0:r1], inp.b_field_t[r0:r1],
                inp.v_thev_v[r0:r1], inp.hk_flags[r0:r1], inp.rows[r0:r1], self._phys, self._dom)
            rr = self._r_range[rows]
            with np.errstate(invalid="ignore"):
                outside = ok & ~((r >= rr[:, :1]) & (r <= rr[:, 1:]))
            f[r0:r1][outside] |= fl.OUT_OF_TABLE
            i_meas = _measured_current(self._phys, rows, inp, r0, r1)
            with np.errstate(invalid="ignore", over="ignore"):
                p[r0:r1] = self._power(rows, i_meas, inp.v_thev_v[r0:r1])
            if self.__dict__.get("_check") is None and self.__dict__.get("tolerance_w", BASELINE_TOLERANCE_W):
                self._flag_nonlinear(inp, r0, r1, i_meas, p, f)  # tolerance_w absent in converters pickled before it
        if self.__dict__.get("_check") is not None:
            self._flag_nonlinear_from_table(inp, p, f)
        _finish(p, f)

    def _flag_nonlinear(self, inp: _Inputs, r0: int, r1: int, i_meas: np.ndarray, p: np.ndarray,
                        f: np.ndarray) -> None:
        """Set ``NONLINEAR`` on rows ``r0:r1`` where the value is not within tolerance of the exact inverse."""
        tol = self.__dict__.get("tolerance_w", BASELINE_TOLERANCE_W)
        for k in range(r0, r1):
            row = inp.rows[k]
            if row < 0:
                continue
            idx = np.flatnonzero(((f[k] & fl.UNUSABLE) == 0) & np.isfinite(p[k]))
            if not idx.size:
                continue
            with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
                exact = model.invert_current(self.params[row], i_meas[k - r0, idx], inp.t_bath_k[k, idx],
                                             inp.b_field_t[k, idx], inp.v_thev_v[k, idx]).p_opt_w
            # Not "> tol": an exact inverse that gives no value cannot vouch for the baseline's.
            bad = ~(np.abs(p[k, idx] - exact) <= tol)
            f[k, idx[bad]] |= fl.NONLINEAR

    def _power(self, rows: np.ndarray, i_meas_a: np.ndarray, v_thev_v: np.ndarray) -> np.ndarray:
        raise NotImplementedError


class LinearConverter(_Baseline):
    """``P = P0 + Re((i - i0) / S)`` at each detector's nominal operating point.

    S is the complex responsivity of paper eq. 3 and i0 the TES current at the
    nominal loading, bath temperature, bias and zero field; the measured
    current is projected onto the phase of S. Environment is ignored (that is
    the point of the baseline); flags are as for every kind.
    """

    kind = "linear"
    _kernel_kind = _baselines.LINEAR

    def __init__(self, params: Sequence[DetectorParams], **options) -> None:
        super().__init__(params, **options)
        self.i0_a = np.array([complex(op.i_a) for op in self._nominal])
        self.responsivity_a_per_w = np.array(
            [complex(model.small_signal(q, op.r_ohm).responsivity_a_per_w) for q, op in zip(self.params, self._nominal)]
        )
        self.p0_w = np.array([q.p_opt_w for q in self.params])

    def _power_constants(self):
        return _baselines.linear_power(self.p0_w, self.i0_a, self.responsivity_a_per_w)

    def _power(self, rows, i_meas_a, v_thev_v):
        return self.p0_w[rows, None] + np.real((i_meas_a - self.i0_a[rows, None]) / self.responsivity_a_per_w[rows, None])


class ElectricalConverter(_Baseline):
    """SPT-3G style: optical power = nominal total power - electrical power.

    ``P_el = Re(V_tes conj(I))`` with RMS ``I = i / sqrt(2)`` and
    ``V_tes = V - z I`` (the sample's bias), and ``P_total`` the optical plus
    Joule power at the nominal operating point. Assumes the total power is
    constant (infinite loop gain): ignores bath temperature, field and the
    temperature change across the transition.
    """

    kind = "electrical"
    _kernel_kind = _baselines.ELECTRICAL

    def __init__(self, params: Sequence[DetectorParams], **options) -> None:
        super().__init__(params, **options)
        self.p_total_w = np.array([
            q.p_opt_w + float(model.joule_power_w(q, op.r_ohm, q.v_thev_v)) for q, op in zip(self.params, self._nominal)
        ])

    def _power_constants(self):
        return _baselines.electrical_power(self.p_total_w)

    def _power(self, rows, i_meas_a, v_thev_v):
        z = (self._phys[rows, 4] + 1j * self._phys[rows, 5])[:, None]
        i_rms = i_meas_a / SQRT2
        return self.p_total_w[rows, None] - np.real((v_thev_v - z * i_rms) * np.conj(i_rms))


class TableConverter(_Base):
    """MNTES with a :class:`~mntes_stream.core.tables.TableBank` (kinds "table" and "grid").

    Parameters
    ----------
    bank : TableBank
    backend : {"auto", "numba", "numpy"}
        ``"auto"`` uses the compiled kernel when numba is installed.
    bias_rtol : float
        ``"grid"`` only: a sample's bias selects a tabulated bias state when
        within this relative tolerance.
    """

    def __init__(self, bank: TableBank, backend: str = "auto", bias_rtol: float = 1e-6,
                 readout_noise_a: float = model.DEFAULT_READOUT_NOISE_A) -> None:
        super().__init__(bank.params, bank.identity, readout_noise_a)
        if backend not in ("auto", "numba", "numpy"):
            raise ConfigError(f"backend must be auto, numba or numpy, got {backend!r}")
        if backend == "auto":
            backend = "numba" if numba_available() else "numpy"
        elif backend == "numba" and not numba_available():
            raise ConfigError("backend 'numba' requested but numba is not installed")
        if not (0 <= bias_rtol < 0.5):
            raise ConfigError("bias_rtol must be in [0, 0.5)")
        self.kind = bank.kind
        self.bank = bank
        self.backend = backend
        self.bias_rtol = float(bias_rtol)
        d = bank.domain
        self._domain = np.array([*d.t_bath_k, *d.b_field_t, *d.v_frac], dtype=float)

    def _row_constants(self) -> np.ndarray:
        """The compiled kernels' per-detector record (``_kernels.row_constants``), made once."""
        rec = self.__dict__.get("_rec")  # absent from converters pickled by older versions
        if rec is None:
            a = self.bank.arrays
            t0 = a["t_ref_k"] if self.kind == "grid" else self._phys[:, 14]
            rec = self._rec = _kernels.row_constants(self._phys, t0, self._domain, a["knot_offset"], a["r_knot_ohm"],
                                                     a["cell_offset"], a["cell_per_ohm"])
        return rec

    @property
    def fuses_low_responsivity(self) -> bool:
        return self.kind == "table" and self.backend == "numba"

    def _convert(self, inp, p, f, low=None):
        a = self.bank.arrays
        numba = self.backend == "numba"
        common = (inp.counts_i, inp.counts_q, inp.t_bath_k, inp.log_t_bath, inp.b_field_t, inp.v_thev_v, inp.hk_flags,
                  inp.rows, self._phys, *((self._row_constants(),) if numba else ()), self._domain, a["knot_offset"],
                  a["r_knot_ohm"], a["cell_offset"], a["cell_interval"], a["cell_per_ohm"])
        if self.kind == "table":
            if low is not None:
                _kernels.table_numba(*common, a["coeffs"], p, f, low=low)
            else:
                kernel = _kernels.table_numba if numba else _kernels.table_numpy
                kernel(*common, a["coeffs"], p, f)
        else:
            kernel = _kernels.grid_numba if numba else _kernels.grid_numpy
            kernel(*common, a["p_w"], a["dp_dr_w_per_ohm"], a["bias_v"], a["b_nodes_t"], a["t_ref_k"],
                   self.bias_rtol, p, f)


def make_converter(kind: str, params: Mapping[str, DetectorParams] | None,
                   bank: TableBank | None = None, **options) -> Converter:
    """A converter of the given kind.

    Parameters
    ----------
    kind : {"table", "grid", "exact", "linear", "electrical"}
    params : mapping detector id -> DetectorParams
        May be None for table kinds when ``bank`` is given (the bank carries
        its parameters). With a bank, every given detector must match the
        bank's parameters exactly.
    bank : TableBank, optional
        Table kinds only; built from ``params`` when absent.
    **options
        Every kind: ``readout_noise_a`` (readout noise per quadrature and
        sample, peak A rms; sets the flag thresholds' margins and the
        phase-residual limit, default ``model.DEFAULT_READOUT_NOISE_A``).
        Table kinds: ``domain`` (TableDomain), ``backend``, ``bias_rtol``,
        ``progress`` and the build options of :func:`core.tables.build_bank`.
        Baselines: ``domain``, the linearisation domain they flag outside
        (``OUT_OF_TABLE``), ``tolerance_w`` (W, default
        ``BASELINE_TOLERANCE_W``; None or 0 disables): ``NONLINEAR`` where the
        value differs from the exact inverse by more, and ``nonlinear_check``
        (``"table"``, default, or ``"exact"``: how that inverse is known; the
        flags are the same, ``"table"`` builds a bank and is far faster).

    Raises
    ------
    ConfigError
        Unknown kind or option, or parameters that disagree with the bank.
    """
    if kind not in CONVERTER_KINDS:
        raise ConfigError(f"unknown converter kind {kind!r} (known: {', '.join(CONVERTER_KINDS)})")
    if params is not None and not isinstance(params, Mapping):
        raise ConfigError("params must be a mapping detector id -> DetectorParams")
    if kind in ("table", "grid"):
        run_opts = {k: options.pop(k) for k in ("backend", "bias_rtol", "readout_noise_a") if k in options}
        if bank is None:
            if not params:
                raise ConfigError(f"kind {kind!r} needs params or a bank")
            bank = build_bank(params, kind=kind, **options)
        else:
            if options:
                raise ConfigError(f"build options {sorted(options)} given with a ready bank")
            if bank.kind != kind:
                raise ConfigError(f"bank is of kind {bank.kind!r}, not {kind!r}")
            have = bank.params_by_id()
            for det_id, q in (params or {}).items():
                if det_id not in have:
                    raise ConfigError(f"bank {bank.identity[:12]} has no table for detector {det_id!r}")
                if have[det_id].to_dict() != q.to_dict():
                    raise ConfigError(f"bank {bank.identity[:12]} was built from other parameters for {det_id!r}")
        return TableConverter(bank, **run_opts)
    if bank is not None:
        raise ConfigError(f"kind {kind!r} takes no table bank")
    allowed = {"readout_noise_a"} | (
        {"domain", "tolerance_w", "nonlinear_check"} if kind in ("linear", "electrical") else set())
    if set(options) - allowed:
        raise ConfigError(f"kind {kind!r} takes only {sorted(allowed)} as options, got {sorted(options)}")
    if not params:
        raise ConfigError(f"kind {kind!r} needs params")
    plist = list(params.values())
    for key, q in params.items():
        if key != q.detector_id:
            raise ConfigError(f"params key {key!r} != detector_id {q.detector_id!r}")
    cls = {"exact": ExactConverter, "linear": LinearConverter, "electrical": ElectricalConverter}[kind]
    return cls(plist, **options)
