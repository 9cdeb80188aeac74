"""Response tables for a whole detector array: one object, one identity hash.

Two table kinds, both behind :func:`mntes_stream.core.convert.make_converter`:

``"table"`` (structured; the default)
    The MNTES inverse is analytic except for the transition shape: from a
    measured current ``R = Re(sqrt(2) V / i - z)`` exactly, then
    ``P = K (T^n - T_bath^n) - V^2 R / |R + z|^2`` with
    ``T = T_s(R) + delta``, ``delta = c1 B + c2 B^2 - gamma |i|``. Only
    functions of R are tabulated: ``W = K T_s^n`` and ``U = 1 / T_s``, as
    cubic Hermite interpolants (exact values and slopes at the knots) on knots
    refined adaptively until W is within ``p_tol_w`` and T_s within
    ``p_tol_w / G_max``. Then ``K T^n = W (1 + delta U)^n`` (an 8-term
    binomial series, exact to 1e-14 relative for ``|delta U| <= 0.05``, with
    the exact power beyond), so bath temperature, bias and field stay exact
    and no logarithm is taken per sample. For a
    :class:`~mntes_stream.core.transition.TabulatedTransition` the measured
    resistances are knots, so no interval straddles a joint of its PCHIP pieces.

``"grid"`` (the paper's general route)
    Knots in R come from a forward (bracketed, Brent-type) solve of the power
    balance on a uniform grid of optical power at the nominal environment;
    on those knots (plus the measured points of a tabulated transition) the
    response ``P(R)`` and its slope are tabulated for each discrete bias state
    and each node of a uniform magnetic-field grid, cubic Hermite in R. A
    sample selects its bias state, is interpolated cubically (4-point
    Lagrange) across B, and corrected exactly for bath temperature
    (``+ K (T_ref^n - T_bath^n)``). Nothing but the bath-temperature term is
    assumed about the physics, so measured curves can be dropped in
    (:func:`grid_bank_from_curves`, slopes from a cubic spline if not given).

Both kinds cover the resistance range ``[r_lo, r_hi]`` that the
:class:`TableDomain` can reach (computed exactly, not sampled), so every
sample whose environment and power lie inside the domain is inside the table.

Layout (flat arrays, concatenated over detectors, for the compiled kernels)::

    knot_offset  (n_det + 1,) int64   detector d owns knots [o[d], o[d+1])
    r_knot_ohm   (n_knot,)    float64 increasing within a detector
    cell_offset  (n_det + 1,) int64   O(1) lookup cells of detector d
    cell_interval(n_cell,)    int32   first interval touching each cell
    cell_per_ohm (n_det,)     float64 cells per ohm
    "table":  coeffs (n_knot, 8)     W = K T_s^n and U = 1/T_s, each c0 + s (c1 + s (c2 + s c3)),
                                      s = R - r_knot (interval j uses row j)
    "grid":   p_w, dp_dr_w_per_ohm (n_knot, n_bias, n_b)
              bias_v (n_det, n_bias), b_nodes_t (n_b,), t_ref_k (n_det,)

The identity is the sha256 of the canonical contents (a JSON header with the
format version, detector parameters, domain and options, then every array's
name, dtype, shape and bytes in name order).
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

import numpy as np

from mntes_stream.core import model
from mntes_stream.core.params import DetectorParams, params_from_dict
from mntes_stream.core.transition import TabulatedTransition
from mntes_stream.errors import ConfigError, SchemaError

__all__ = [
    "TABLE_FORMAT",
    "TABLE_FORMAT_VERSION",
    "TABLE_KINDS",
    "TableDomain",
    "TableBank",
    "build_bank",
    "grid_bank_from_curves",
    "resistance_range_ohm",
    "transition_knots",
    "hermite_coefficients",
    "cell_floor",
    "lookup_cells",
    "params_identity",
]

TABLE_FORMAT = "mntes-tables"
TABLE_FORMAT_VERSION = 1
TABLE_KINDS = ("table", "grid")

_DEFAULT_P_TOL_W = 1e-20   # 10x below the 1e-19 W accuracy target
_MAX_REFINE = 60
_INITIAL_INTERVALS = 32


def _pair(name: str, value: Any) -> tuple[float, float]:
    try:
        lo, hi = (float(x) for x in value)
    except (TypeError, ValueError):
        raise ConfigError(f"table domain: {name} must be a pair (lo, hi), got {value!r}") from None
    if not (math.isfinite(lo) and math.isfinite(hi) and lo < hi):
        raise ConfigError(f"table domain: {name} needs finite lo < hi, got ({lo}, {hi})")
    return lo, hi


@dataclass(frozen=True)
class TableDomain:
    """The environment and loading a table bank must cover (inclusive ranges).

    Defaults are wider than the accuracy specification (P 0.05-1 pW,
    T_bath 95-105 mK, |B| <= 100 uT, bias +-5%) so its edges are interior.

    Attributes
    ----------
    p_opt_w : (lo, hi)
        Optical power at the TES, W.
    t_bath_k : (lo, hi)
    b_field_t : (lo, hi)
    v_frac : (lo, hi)
        Bias relative to each detector's nominal ``v_thev_v``.
    """

    p_opt_w: tuple[float, float] = (0.0, 1.2e-12)
    t_bath_k: tuple[float, float] = (0.090, 0.110)
    b_field_t: tuple[float, float] = (-2e-4, 2e-4)
    v_frac: tuple[float, float] = (0.9, 1.1)

    def __post_init__(self) -> None:
        for name in ("p_opt_w", "t_bath_k", "b_field_t", "v_frac"):
            object.__setattr__(self, name, _pair(name, getattr(self, name)))
        if self.t_bath_k[0] <= 0 or self.v_frac[0] <= 0:
            raise ConfigError("table domain: t_bath_k and v_frac must be > 0")

    def to_dict(self) -> dict:
        return {k: list(getattr(self, k)) for k in ("p_opt_w", "t_bath_k", "b_field_t", "v_frac")}

    @classmethod
    def from_dict(cls, d: Mapping) -> TableDomain:
        unknown = set(d) - {"p_opt_w", "t_bath_k", "b_field_t", "v_frac"}
        if unknown:
            raise ConfigError(f"table domain: unknown key(s) {sorted(unknown)}")
        return cls(**{k: tuple(v) for k, v in d.items()})


# --- exact resistance range -----------------------------------------------------------

def _b_candidates(p: DetectorParams, b_range: tuple[float, float]) -> np.ndarray:
    """Fields at which the T_c shift ``c1 B + c2 B^2`` takes its extremes."""
    cands = [b_range[0], b_range[1]]
    c1, c2 = p.t_c_shift_k_per_t, p.t_c_shift_k_per_t2
    if c2 != 0.0:
        b_star = -c1 / (2.0 * c2)
        if b_range[0] < b_star < b_range[1]:
            cands.append(b_star)
    return np.array(cands)


def resistance_range_ohm(p: DetectorParams, domain: TableDomain) -> tuple[float, float]:
    """Smallest R interval holding every sample of ``domain`` (exact, no sampling; +-1e-9 R_n).

    On the stable branch ``P(R)`` increases with R and decreases with bias and
    bath temperature; over B it follows the T_c shift. So the needed range is
    ``[R_a, R_b]`` with ``max_env P(R_a) = p_lo`` and ``min_env P(R_b) = p_hi``.
    """
    br_lo, br_hi = (float(x) for x in model.branch_bounds_ohm(p))
    v_lo, v_hi = (f * p.v_thev_v for f in domain.v_frac)
    b = _b_candidates(p, domain.b_field_t)

    def p_max(r: float) -> float:
        return float(np.max(model.power_of_resistance_w(p, r, domain.t_bath_k[0], b, v_lo)))

    def p_min(r: float) -> float:
        return float(np.min(model.power_of_resistance_w(p, r, domain.t_bath_k[1], b, v_hi)))

    # scipy imported where used: a converter restarted from its snapshot never builds a table, and
    # scipy.interpolate/optimize at module level cost its start ~0.25 s.
    from scipy.optimize import brentq

    p_lo, p_hi = domain.p_opt_w
    with np.errstate(over="ignore", invalid="ignore"):
        if p_max(br_lo) >= p_lo:
            r_a = br_lo
        elif p_max(br_hi) < p_lo:
            raise ConfigError(f"{p.detector_id}: the domain's lowest power is above saturation everywhere")
        else:
            r_a = brentq(lambda r: p_max(r) - p_lo, br_lo, br_hi, xtol=1e-15, rtol=1e-15)
        top = p_min(br_hi)
        if not np.isfinite(top) or top > p_hi:
            r_b = brentq(lambda r: p_min(r) - p_hi, br_lo, br_hi, xtol=1e-15, rtol=1e-15) if p_min(br_lo) < p_hi else br_lo
        else:
            r_b = br_hi
    if not r_b > r_a:
        raise ConfigError(f"{p.detector_id}: the table domain reaches no stable transition state")
    # A hair of margin so rounding in R never flags a sample on the domain's edge.
    pad = 1e-9 * p.r_normal_ohm
    return float(max(r_a - pad, br_lo)), float(min(r_b + pad, br_hi))


# --- the transition table ----------------------------------------------------------------

def hermite_coefficients(x: np.ndarray, y: np.ndarray, dy: np.ndarray) -> np.ndarray:
    """Local cubic coefficients from values and slopes at the knots.

    Returns ``c`` of shape ``(len(x), 4)`` with
    ``f(x_j + s) = c0 + s (c1 + s (c2 + s c3))`` on interval j; the last row is zero.
    """
    h = np.diff(x)
    slope = np.diff(y) / h
    c = np.zeros((x.size, 4))
    c[:-1, 0] = y[:-1]
    c[:-1, 1] = dy[:-1]
    c[:-1, 2] = (3.0 * slope - 2.0 * dy[:-1] - dy[1:]) / h
    c[:-1, 3] = (dy[:-1] + dy[1:] - 2.0 * slope) / (h * h)
    return c


def _eval_pieces(x: np.ndarray, c: np.ndarray, j: np.ndarray, xe: np.ndarray) -> np.ndarray:
    s = xe - x[j]
    return c[j, 0] + s * (c[j, 1] + s * (c[j, 2] + s * c[j, 3]))


def _breakpoints(transition_or_params, r_lo: float, r_hi: float) -> np.ndarray:
    """Resistances inside ``(r_lo, r_hi)`` where a tabulated transition's cubic pieces join."""
    tr = getattr(transition_or_params, "transition", transition_or_params)
    if not isinstance(tr, TabulatedTransition):
        return np.empty(0)
    pts = np.asarray(tr.r_ohm, dtype=float)
    return pts[(pts > r_lo) & (pts < r_hi)]


def transition_knots(
    p: DetectorParams, r_lo: float, r_hi: float, p_tol_w: float, t_tol_k: float, max_knots: int = 20000
) -> tuple[np.ndarray, np.ndarray]:
    """Knots and cubic coefficients of ``W = K T_s(R)^n`` and ``U = 1 / T_s(R)`` on ``[r_lo, r_hi]``.

    The conversion needs ``K T^n`` with ``T = T_s + delta`` (field shift and
    current term): ``K T^n = W (1 + delta U)^n``, a short binomial series, so
    no logarithm or power is evaluated per sample. Knots start from a uniform
    grid plus the measured resistances of a tabulated transition (where its
    PCHIP pieces join); every interval whose Hermite interpolants miss W by
    more than ``p_tol_w`` or T_s (through U) by more than ``t_tol_k`` at
    s = 1/4, 1/2, 3/4 is bisected.

    Returns
    -------
    r_knot_ohm : ndarray, shape (m + 1,)
    coeffs : ndarray, shape (m + 1, 8)
        ``[W c0..c3, U c0..c3]`` of interval j in ``s = R - r_knot[j]``; last row zero.
    """
    tr, k, n = p.transition, p.k_w_per_k_n, p.n

    def w_u(r):
        t = np.asarray(tr.temperature_k(r), dtype=float)
        dt = np.asarray(tr.dtemperature_dr(r)[0], dtype=float)
        w = k * t**n
        return t, w, n * w / t * dt, 1.0 / t, -dt / (t * t)

    # Knots at fractions t = k / 2^L of the range, placed where the lookup cells of any power-of-two count
    # begin (cell_floor): a sample's cell then lies in one interval, with no step to the next
    # (lookup_cells). A tabulated transition's joints stay where they are, with their own fraction NaN.
    span = r_hi - r_lo
    brk = _breakpoints(tr, r_lo, r_hi)
    frac_k = np.arange(_INITIAL_INTERVALS + 1) / _INITIAL_INTERVALS
    x = cell_floor(r_lo, span, frac_k)
    x[0], x[-1] = r_lo, r_hi
    if brk.size:  # a joint within a hair of a lattice knot replaces it (no interval of a few ulps)
        near = np.abs(x[:, None] - brk[None, :]).min(axis=1) < 1e-9 * span
        near[[0, -1]] = False
        x, frac_k = x[~near], frac_k[~near]
        x = np.concatenate([x, brk])
        frac_k = np.concatenate([frac_k, np.full(brk.size, np.nan)])
        order = np.argsort(x, kind="stable")
        x, frac_k = x[order], frac_k[order]
    frac = np.array([0.25, 0.5, 0.75])
    for _ in range(_MAX_REFINE):
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            t, w, dw, u, du = w_u(x)
        if not (np.all(np.isfinite([w, dw, u, du])) and np.all(t > 0)):
            raise ConfigError(f"{p.detector_id}: transition is not finite and positive on the table range")
        c = np.concatenate([hermite_coefficients(x, w, dw), hermite_coefficients(x, u, du)], axis=1)
        h = np.diff(x)
        xe = (x[:-1, None] + frac[None, :] * h[:, None]).ravel()
        j = np.repeat(np.arange(h.size), frac.size)
        te, we, _, ue, _ = w_u(xe)
        err_w = np.abs(_eval_pieces(x, c[:, :4], j, xe) - we)
        err_t = np.abs(_eval_pieces(x, c[:, 4:], j, xe) - ue) * te * te
        bad = ((err_w > p_tol_w) | (err_t > t_tol_k)).reshape(h.size, frac.size).any(axis=1)
        if not np.any(bad):
            return x, c
        if x.size + np.count_nonzero(bad) > max_knots or np.min(h[bad]) < 1e-12 * (r_hi - r_lo):
            break
        f_mid = 0.5 * (frac_k[:-1][bad] + frac_k[1:][bad])
        # Next to a joint: the point nearest the middle on a lattice of at most half the interval, so within a
        # quarter of it from the middle, and no finer than the cells its smaller part calls for (lookup_cells).
        joint = np.isnan(f_mid)
        if joint.any():
            hj = h[bad][joint]
            per = 2.0 ** np.ceil(np.log2(span / hj) + 1.0)
            f_mid[joint] = np.round((x[:-1][bad][joint] + 0.5 * hj - r_lo) / span * per) / per
        x_mid = cell_floor(r_lo, span, f_mid)
        x, frac_k = np.concatenate([x, x_mid]), np.concatenate([frac_k, f_mid])
        order = np.argsort(x, kind="stable")
        x, frac_k = x[order], frac_k[order]
    raise ConfigError(
        f"{p.detector_id}: response table did not reach {p_tol_w:.2g} W within {max_knots} knots on "
        f"R = [{r_lo:.6g}, {r_hi:.6g}] Ohm (is T_s(R) smooth there? narrow the domain?)"
    )


def cell_floor(x0: float, span: float, t) -> np.ndarray:
    """The smallest floats ``r`` with ``fl(fl(r - x0) * fl(1 / span)) >= t`` (``t`` >= 0, any shape).

    A kernel's lookup cell of ``r`` is ``int((r - x0) * cells_per_ohm)``; with
    ``2^P`` cells, ``cells_per_ohm = fl(2^P / span)`` is ``fl(1 / span)`` scaled
    exactly by ``2^P``, so the cells of every power-of-two count begin at
    ``cell_floor(x0, span, k / 2^P)``, in floating point and not only on paper.
    """
    t = np.asarray(t, dtype=float)
    x0, span = float(x0), float(span)
    u0 = 1.0 / span

    def reaches(r):
        return (r - x0) * u0 >= t

    # fl(fl(r - x0) * u0) never falls as r rises, so its first float reaching t is found by bisection over
    # the floats in order (their bits, the negative ones' reversed). Stepping one float at a time from
    # x0 + t span is not enough: where |r| << |x0| a step of r's ulp may leave fl(r - x0) unchanged.
    guess = x0 + t * span
    pad = 8 * np.finfo(float).eps * (abs(x0) + span) + np.finfo(float).tiny
    lo, hi = guess - pad, guess + pad
    for _ in range(64):
        low_ok = reaches(lo)
        high_bad = ~reaches(hi)
        if not (low_ok.any() or high_bad.any()):
            break
        pad *= 2
        lo = np.where(low_ok, lo - pad, lo)
        hi = np.where(high_bad, hi + pad, hi)
    else:
        raise ConfigError(f"lookup cells: no cell edge found on [{x0}, {x0 + span}] (span too small?)")
    a, b = _ordered(lo), _ordered(hi)  # reaches(lo) false, reaches(hi) true
    while np.any(b - a > 1):
        mid = a + (b - a) // 2
        ok = reaches(_unordered(mid))
        a, b = np.where(ok, a, mid), np.where(ok, mid, b)
    return _unordered(b)


def _ordered(r: np.ndarray) -> np.ndarray:
    """Floats as int64 keys in the floats' order (-0.0 and 0.0 alike)."""
    i = np.asarray(r, dtype=np.float64).view(np.int64)
    return np.where(i < 0, -(i & np.int64(0x7FFFFFFFFFFFFFFF)), i)


def _unordered(k: np.ndarray) -> np.ndarray:
    """The floats of :func:`_ordered`'s keys."""
    k = np.asarray(k, dtype=np.int64)
    return np.where(k < 0, (-k) | np.int64(-0x8000000000000000), k).view(np.float64)


def lookup_cells(x: np.ndarray, max_cells_per_interval: int = 16) -> tuple[np.ndarray, float]:
    """Uniform lookup cells over nonuniform knots: O(1) interval search.

    A power-of-two count of cells, cell k holding the R whose
    ``int((R - x0) * cells_per_ohm)`` is k; ``cell_interval[k]`` is the
    interval containing its smallest R (:func:`cell_floor`), so the interval
    of any R in the cell is that one or a few steps to the right. None at all
    where the knots begin cells, as :func:`transition_knots` places them, and
    the cells are no wider than the narrowest interval (unless that would
    exceed ``max_cells_per_interval`` cells per interval).

    Returns
    -------
    cell_interval : ndarray of int32, shape (n_cells,)
    cells_per_ohm : float
    """
    span = float(x[-1] - x[0])
    m = x.size - 1
    need = span / float(np.min(np.diff(x)))
    p = min(math.ceil(math.log2(max(need, 1.0))), int(math.floor(math.log2(max(max_cells_per_interval * m, 1)))))
    n_cells = 2 ** max(p, 0)
    left = cell_floor(float(x[0]), span, np.arange(n_cells) / n_cells)
    j = np.clip(np.searchsorted(x, left, side="right") - 1, 0, m - 1)
    return j.astype(np.int32), n_cells / span


# --- identity -------------------------------------------------------------------------

def _canonical_json(obj: Any) -> bytes:
    return json.dumps(obj, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def params_identity(params: Sequence[DetectorParams], extra: Mapping | None = None) -> str:
    """sha256 (hex) of detector parameters (in the given order) plus ``extra``."""
    doc = {"params": [p.to_dict() for p in params], "extra": dict(extra or {})}
    return hashlib.sha256(_canonical_json(doc)).hexdigest()


def content_identity(header: Mapping, arrays: Mapping[str, np.ndarray]) -> str:
    """sha256 (hex) of a header and arrays in canonical form."""
    h = hashlib.sha256(_canonical_json(dict(header)))
    for name in sorted(arrays):
        a = np.ascontiguousarray(arrays[name])
        dt = a.dtype.newbyteorder("<") if a.dtype.byteorder == ">" else a.dtype
        a = a.astype(dt, copy=False)
        h.update(_canonical_json([name, dt.str, list(a.shape)]))
        h.update(a.tobytes())
    return h.hexdigest()


# --- the bank -------------------------------------------------------------------------

_COMMON_ARRAYS = {
    "knot_offset": ("<i8", 1),
    "r_knot_ohm": ("<f8", 1),
    "cell_offset": ("<i8", 1),
    "cell_interval": ("<i4", 1),
    "cell_per_ohm": ("<f8", 1),
}
_KIND_ARRAYS = {
    "table": {"coeffs": ("<f8", 2)},
    "grid": {
        "p_w": ("<f8", 3),
        "dp_dr_w_per_ohm": ("<f8", 3),
        "bias_v": ("<f8", 2),
        "b_nodes_t": ("<f8", 1),
        "t_ref_k": ("<f8", 1),
    },
}
# The table kernel reads these a few lines a row at places it cannot predict: starting them on a
# cache line puts a knot's eight coefficients (64 bytes) in one line instead of two (numpy's own
# arrays start 16 bytes in), about 7% of the kernel's time on 20-sample rows. The grid's large
# arrays are left as they come: aligning is a copy.
_LINE_BYTES = 64
_LINE_ALIGNED = ("r_knot_ohm", "cell_interval", "coeffs")


def _line_aligned(a: np.ndarray) -> np.ndarray:
    """``a`` C-contiguous and starting on a cache line: itself when it already is, else a copy."""
    a = np.ascontiguousarray(a)
    if a.ctypes.data % _LINE_BYTES == 0:
        return a
    buf = np.empty(a.nbytes + _LINE_BYTES, dtype=np.uint8)
    start = -buf.ctypes.data % _LINE_BYTES
    out = buf[start:start + a.nbytes].view(a.dtype).reshape(a.shape)
    out[...] = a
    return out


@dataclass(frozen=True)
class TableBank:
    """Response tables of a whole array: one object, identified by ``identity``.

    Build with :func:`build_bank`; save/load with
    :mod:`mntes_stream.io.tablefile`. Arrays are read-only and C-contiguous,
    the knots, cells and coefficients on a 64-byte cache line (layout in the
    module docstring).

    Attributes
    ----------
    kind : {"table", "grid"}
    detector_ids : tuple of str
    params : tuple of DetectorParams, same order
    domain : TableDomain
    options : mapping (build options, part of the identity)
    arrays : mapping name -> ndarray
    identity : str
        sha256 hex of the canonical contents (computed, never passed in).
    """

    kind: str
    detector_ids: tuple
    params: tuple
    domain: TableDomain
    options: Mapping
    arrays: Mapping
    identity: str = field(init=False)

    def __post_init__(self) -> None:
        if self.kind not in TABLE_KINDS:
            raise SchemaError(f"table bank: unknown kind {self.kind!r} (known: {', '.join(TABLE_KINDS)})")
        ids = tuple(self.detector_ids)
        if len(set(ids)) != len(ids):
            raise SchemaError("table bank: duplicate detector ids")
        if tuple(p.detector_id for p in self.params) != ids:
            raise SchemaError("table bank: params do not match detector_ids")
        expected = dict(_COMMON_ARRAYS, **_KIND_ARRAYS[self.kind])
        if set(self.arrays) != set(expected):
            raise SchemaError(
                f"table bank ({self.kind}): arrays {sorted(self.arrays)} != expected {sorted(expected)}"
            )
        arrays = {}
        for name, (dt, ndim) in expected.items():
            a = np.asarray(self.arrays[name])
            if a.dtype.str != dt or a.ndim != ndim:
                raise SchemaError(f"table bank: {name} must be {dt} with {ndim} dims, got {a.dtype.str} {a.shape}")
            a = _line_aligned(a) if name in _LINE_ALIGNED else np.ascontiguousarray(a)
            a.flags.writeable = False
            arrays[name] = a
        self._check_layout(arrays, len(ids))
        object.__setattr__(self, "detector_ids", ids)
        object.__setattr__(self, "params", tuple(self.params))
        object.__setattr__(self, "options", MappingProxyType(dict(self.options)))
        object.__setattr__(self, "arrays", MappingProxyType(arrays))
        object.__setattr__(self, "identity", content_identity(self.header(), arrays))

    def _check_layout(self, a: dict, n_det: int) -> None:
        ko, co = a["knot_offset"], a["cell_offset"]
        n_knot, n_cell = a["r_knot_ohm"].size, a["cell_interval"].size
        ok = (
            ko.shape == (n_det + 1,) and co.shape == (n_det + 1,) and a["cell_per_ohm"].shape == (n_det,)
            and ko[0] == 0 and ko[-1] == n_knot and co[0] == 0 and co[-1] == n_cell
            and np.all(np.diff(ko) >= 2) and np.all(np.diff(co) >= 1)
        )
        if not ok:
            raise SchemaError("table bank: inconsistent knot/cell offsets")
        nk_per_det = np.diff(ko)
        owner = np.repeat(np.arange(n_det), np.diff(co))
        if np.any(a["cell_interval"] < 0) or np.any(a["cell_interval"] > nk_per_det[owner] - 2):
            raise SchemaError("table bank: lookup cell points outside its detector's knots")
        x = a["r_knot_ohm"]
        inside = np.ones(n_knot - 1, dtype=bool)
        inside[ko[1:-1] - 1] = False  # no ordering across detector boundaries
        if not (np.all(np.isfinite(x)) and np.all(np.diff(x)[inside] > 0)):
            raise SchemaError("table bank: knots must be finite and increasing")
        if self.kind == "table":
            if a["coeffs"].shape != (n_knot, 8):
                raise SchemaError("table bank: coeffs must have shape (n_knot, 8)")
        else:
            nb = a["b_nodes_t"].size
            n_bias = a["bias_v"].shape[1] if a["bias_v"].ndim == 2 else -1
            shape = (n_knot, n_bias, nb)
            if a["p_w"].shape != shape or a["dp_dr_w_per_ohm"].shape != shape or a["bias_v"].shape[0] != n_det:
                raise SchemaError("table bank: grid arrays have inconsistent shapes")
            if nb < 4 or np.any(np.diff(a["b_nodes_t"]) <= 0) or a["t_ref_k"].shape != (n_det,):
                raise SchemaError("table bank: grid needs >= 4 increasing B nodes and one t_ref per detector")

    def header(self) -> dict:
        """Everything but the arrays, JSON-ready (what the identity hashes first)."""
        return {
            "format": TABLE_FORMAT,
            "version": TABLE_FORMAT_VERSION,
            "kind": self.kind,
            "detector_ids": list(self.detector_ids),
            "params": [p.to_dict() for p in self.params],
            "domain": self.domain.to_dict(),
            "options": dict(self.options),
        }

    @classmethod
    def from_header(cls, header: Mapping, arrays: Mapping[str, np.ndarray]) -> TableBank:
        """Inverse of :meth:`header` (raises SchemaError/ConfigError on anything wrong)."""
        if header.get("format") != TABLE_FORMAT:
            raise SchemaError(f"not a table bank (format {header.get('format')!r}, expected {TABLE_FORMAT!r})")
        if header.get("version") != TABLE_FORMAT_VERSION:
            raise SchemaError(
                f"table bank format version {header.get('version')!r} is not supported "
                f"(this build reads version {TABLE_FORMAT_VERSION}); rebuild the tables"
            )
        try:
            params = tuple(params_from_dict(dict(d)) for d in header["params"])
            return cls(
                kind=header["kind"],
                detector_ids=tuple(header["detector_ids"]),
                params=params,
                domain=TableDomain.from_dict(header["domain"]),
                options=dict(header["options"]),
                arrays=dict(arrays),
            )
        except (KeyError, TypeError) as exc:
            raise SchemaError(f"table bank header is malformed: {type(exc).__name__}: {exc}") from None

    @property
    def nbytes(self) -> int:
        """Memory held by the arrays (bytes)."""
        return int(sum(a.nbytes for a in self.arrays.values()))

    def __len__(self) -> int:
        return len(self.detector_ids)

    def params_by_id(self) -> dict[str, DetectorParams]:
        return dict(zip(self.detector_ids, self.params))

    def r_range_ohm(self) -> np.ndarray:
        """``(n_det, 2)`` resistance range each detector's table covers."""
        ko = self.arrays["knot_offset"]
        x = self.arrays["r_knot_ohm"]
        return np.stack([x[ko[:-1]], x[ko[1:] - 1]], axis=1)

    def summary(self) -> dict:
        """Short, JSON-ready description (``mntes-stream tables info``)."""
        ko = self.arrays["knot_offset"]
        knots = np.diff(ko)
        rr = self.r_range_ohm()
        r_n = np.array([p.r_normal_ohm for p in self.params])
        out = {
            "format": TABLE_FORMAT,
            "version": TABLE_FORMAT_VERSION,
            "kind": self.kind,
            "identity": self.identity,
            "detectors": len(self),
            "knots_per_detector": {"min": int(knots.min()), "median": float(np.median(knots)), "max": int(knots.max())},
            "r_frac_range": [float(np.min(rr[:, 0] / r_n)), float(np.max(rr[:, 1] / r_n))],
            "bytes": self.nbytes,
            "domain": self.domain.to_dict(),
            "options": dict(self.options),
        }
        if self.kind == "grid":
            out["bias_states"] = int(self.arrays["bias_v"].shape[1])
            out["b_nodes_t"] = [float(b) for b in self.arrays["b_nodes_t"]]
        return out


def _assemble(kind: str, params: list[DetectorParams], domain: TableDomain, options: dict,
              knots: list[np.ndarray], per_knot: dict[str, list[np.ndarray]], extra: dict) -> TableBank:
    ko = np.zeros(len(knots) + 1, dtype=np.int64)
    ko[1:] = np.cumsum([k.size for k in knots])
    cells, per_ohm = zip(*(lookup_cells(k) for k in knots))
    co = np.zeros(len(knots) + 1, dtype=np.int64)
    co[1:] = np.cumsum([c.size for c in cells])
    arrays = {
        "knot_offset": ko,
        "r_knot_ohm": np.concatenate(knots),
        "cell_offset": co,
        "cell_interval": np.concatenate(cells).astype(np.int32),
        "cell_per_ohm": np.array(per_ohm, dtype=float),
    }
    arrays.update({name: np.concatenate(parts) for name, parts in per_knot.items()})
    arrays.update(extra)
    return TableBank(kind=kind, detector_ids=tuple(p.detector_id for p in params), params=tuple(params),
                     domain=domain, options=options, arrays=arrays)


def _check_params(params: Mapping[str, DetectorParams] | Sequence[DetectorParams]) -> list[DetectorParams]:
    plist = list(params.values()) if isinstance(params, Mapping) else list(params)
    if not plist:
        raise ConfigError("a table bank needs at least one detector")
    for p in plist:
        if not isinstance(p, DetectorParams):
            raise ConfigError(f"expected DetectorParams, got {type(p).__name__}")
    if isinstance(params, Mapping):
        for key, p in params.items():
            if key != p.detector_id:
                raise ConfigError(f"params key {key!r} != detector_id {p.detector_id!r}")
    return plist


def _g_max(p: DetectorParams, domain: TableDomain, r_hi: float) -> float:
    """Largest thermal conductance ``n K T^(n-1)`` over the table (sets the T tolerance)."""
    b = _b_candidates(p, domain.b_field_t)
    shift = np.max(p.t_c_shift_k_per_t * b + p.t_c_shift_k_per_t2 * b * b)
    t = float(p.transition.temperature_k(r_hi)) + float(shift)
    return p.n * p.k_w_per_k_n * max(t, 1e-300) ** (p.n - 1)


def build_bank(
    params: Mapping[str, DetectorParams] | Sequence[DetectorParams],
    kind: str = "table",
    domain: TableDomain | None = None,
    *,
    p_tol_w: float = _DEFAULT_P_TOL_W,
    bias_frac: Sequence[float] = (0.95, 1.0, 1.05),
    n_b_nodes: int = 7,
    n_power: int = 256,
    progress: Callable[[int], None] | None = None,
) -> TableBank:
    """Build the response tables of an array.

    Parameters
    ----------
    params : mapping id -> DetectorParams, or a sequence
    kind : {"table", "grid"}
    domain : TableDomain, optional
    p_tol_w : float
        ``"table"`` only: interpolation tolerance on power (W), turned into a
        temperature tolerance with the largest G on the table.
    bias_frac, n_b_nodes, n_power : ``"grid"`` only
        Discrete bias states relative to nominal, number of uniform B nodes
        across ``domain.b_field_t`` (>= 4), knots per detector.
    progress : callable(int), optional
        Called with 1 after each detector (e.g. ``tqdm.update``).
    """
    plist = _check_params(params)
    domain = domain or TableDomain()
    if kind == "table":
        if not (p_tol_w > 0 and math.isfinite(p_tol_w)):
            raise ConfigError("p_tol_w must be > 0")
        knots, coeffs = [], []
        for p in plist:
            r_lo, r_hi = resistance_range_ohm(p, domain)
            x, c = transition_knots(p, r_lo, r_hi, p_tol_w, p_tol_w / _g_max(p, domain, r_hi))
            knots.append(x)
            coeffs.append(c)
            if progress is not None:
                progress(1)
        return _assemble("table", plist, domain, {"p_tol_w": float(p_tol_w)}, knots, {"coeffs": coeffs}, {})
    if kind == "grid":
        return _build_grid(plist, domain, bias_frac, n_b_nodes, n_power, progress)
    raise ConfigError(f"unknown table kind {kind!r} (known: {', '.join(TABLE_KINDS)})")


def _build_grid(plist, domain, bias_frac, n_b_nodes, n_power, progress) -> TableBank:
    bias_frac = np.asarray(bias_frac, dtype=float)
    if bias_frac.ndim != 1 or bias_frac.size < 1 or np.any(bias_frac <= 0) or np.any(np.diff(bias_frac) <= 0):
        raise ConfigError("bias_frac must be increasing positive fractions of the nominal bias")
    if int(n_b_nodes) < 4 or int(n_power) < 8:
        raise ConfigError("grid tables need n_b_nodes >= 4 and n_power >= 8")
    b_nodes = np.linspace(domain.b_field_t[0], domain.b_field_t[1], int(n_b_nodes))
    knots, values, slopes, bias_v, t_ref = [], [], [], [], []
    for p in plist:
        r_lo, r_hi = resistance_range_ohm(p, domain)
        # Knots: the paper's route, a forward solve on a uniform power grid at
        # the nominal environment (equidistributed in P, so dense where T_s is steep).
        p_ends = model.power_of_resistance_w(p, np.array([r_lo, r_hi]), p.t_bath_k, 0.0, p.v_thev_v)
        p_grid = np.linspace(p_ends[0], p_ends[1], int(n_power))[1:-1]
        op = model.solve_operating_point(p, p_grid, p.t_bath_k, 0.0, p.v_thev_v)
        x = np.concatenate([[r_lo], op.r_ohm[op.state == model.STATE_TRANSITION], [r_hi], _breakpoints(p, r_lo, r_hi)])
        x = np.unique(x)
        v_states = bias_frac * p.v_thev_v
        # P(R) at every (bias state, B node), bath at the reference temperature,
        # with the exact slope dP/dR = (dI/dR) / (dI/dP) from the small-signal model.
        xr, vs, bn = x[:, None, None], v_states[None, :, None], b_nodes[None, None, :]
        pw = model.power_of_resistance_w(p, xr, p.t_bath_k, bn, vs)
        di_dr = -model.SQRT2 * vs / (xr + p.z_thev_ohm) ** 2
        slope = np.real(di_dr / model.small_signal(p, xr, p.t_bath_k, bn, vs).di_dp_a_per_w)
        knots.append(x)
        values.append(np.ascontiguousarray(pw))
        slopes.append(np.ascontiguousarray(slope))
        bias_v.append(v_states)
        t_ref.append(p.t_bath_k)
        if progress is not None:
            progress(1)
    options = {"bias_frac": [float(f) for f in bias_frac], "n_b_nodes": int(n_b_nodes), "n_power": int(n_power)}
    extra = {"bias_v": np.array(bias_v), "b_nodes_t": b_nodes, "t_ref_k": np.array(t_ref, dtype=float)}
    return _assemble("grid", plist, domain, options, knots, {"p_w": values, "dp_dr_w_per_ohm": slopes}, extra)


def grid_bank_from_curves(
    params: Sequence[DetectorParams],
    r_knot_ohm: Sequence[np.ndarray],
    p_w: Sequence[np.ndarray],
    bias_v: np.ndarray,
    b_nodes_t: np.ndarray,
    t_ref_k: np.ndarray,
    domain: TableDomain | None = None,
    options: Mapping | None = None,
    dp_dr_w_per_ohm: Sequence[np.ndarray] | None = None,
) -> TableBank:
    """A ``"grid"`` bank from response curves measured or computed elsewhere.

    Parameters
    ----------
    params : detectors (K, n, z and gain are used by the conversion)
    r_knot_ohm : per detector, shape (m_d,), increasing
    p_w : per detector, shape (m_d, n_bias, n_b): optical power at each knot,
        bias state and B node with the bath at ``t_ref_k``
    bias_v : (n_det, n_bias) bias state voltages (RMS)
    b_nodes_t : (n_b,) uniform B nodes
    t_ref_k : (n_det,) bath temperature of the curves
    dp_dr_w_per_ohm : per detector, like ``p_w``, optional
        Slopes at the knots; by default those of a not-a-knot cubic spline
        through the values (right for curves smooth between the knots).
    """
    plist = _check_params(list(params))
    knots = [np.asarray(x, dtype=float) for x in r_knot_ohm]
    values = [np.asarray(v, dtype=float) for v in p_w]
    if len(knots) != len(plist) or len(values) != len(plist):
        raise ConfigError("need one knot array and one curve array per detector")
    b_nodes_t = np.asarray(b_nodes_t, dtype=float)
    if b_nodes_t.size >= 2 and not np.allclose(np.diff(b_nodes_t), b_nodes_t[1] - b_nodes_t[0], rtol=1e-9, atol=0):
        raise ConfigError("B nodes must be uniformly spaced")
    if dp_dr_w_per_ohm is None:
        from scipy.interpolate import CubicSpline

        slopes = [np.ascontiguousarray(CubicSpline(x, v, axis=0)(x, 1)) for x, v in zip(knots, values)]
    else:
        slopes = [np.asarray(d, dtype=float) for d in dp_dr_w_per_ohm]
    extra = {
        "bias_v": np.asarray(bias_v, dtype=float),
        "b_nodes_t": b_nodes_t,
        "t_ref_k": np.asarray(t_ref_k, dtype=float),
    }
    return _assemble("grid", plist, domain or TableDomain(), dict(options or {"source": "curves"}), knots,
                     {"p_w": values, "dp_dr_w_per_ohm": slopes}, extra)
