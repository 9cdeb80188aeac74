"""Table conversion kernels: compiled (numba, one core, no GIL) and numpy twins.

Both backends implement the same arithmetic and flag rules as
``core.convert`` (documented there); the tests run both against the exact
inverse. The compiled kernel does one pass over the samples with no
transcendental call per sample in normal operation: ``K T^n`` comes from
the table and a short binomial series (see ``core.tables``), and so does
``K T_bath^n`` around each detector's nominal bath (within 5%; beyond, the
exact power). See ``benchmarks/README.md`` for its speed.

The "table" kind's sample loop vectorises (``_table_kernel``; 8 doubles
to a register on AVX-512): a detector's samples run as vector lanes with no
branch (flags as bit arithmetic, the interval from an O(1) lookup cell and
one branch-free step, tables read by gathers); a lane that needs a branch
(the exact power beyond the series, a second lookup step: 0.03% of the
bench's samples) is done again by the scalar reference, so the values are
the reference's bit for bit. The previous sample's interval is not reused:
that would chain each lane to the one before and stop the vectorising;
close samples find their table lines in cache anyway.

Per-detector scalars ``phys`` (n_bank, 21): gain re/im, pickup re/im, z re/im,
K, n, c1, c2, gamma, nominal bias, R at |z| and the saturation cap, nominal
bath, R at the bottom, the phase-residual limit (A), R at the top, and the
noise margins (Ohm V) at the top, at |z| and at the bottom; see
``core.model.FlagThresholds``.
``dom``: bath temperature lo/hi, field lo/hi, bias fraction lo/hi.
The compiled kernels read a compact per-detector record ``rec`` (n_bank,
``REC_COLS``), from :func:`row_constants`, computed once per converter: the
front end's constants, K, n, field and current coefficients, the binomials
``C(n, 1..8)``, ``1 / T0`` and ``K T0^n`` (``T0`` the bath the table refers
to) and the detector's table window (R range, knot and cell offsets). One
320-byte row per detector instead of some forty values from seven arrays,
so a short row (a live chunk holds about 20 samples) is cheap to start.
What still made it dear was waiting: a row's record, lookup cell, knots and
coefficients are cache misses in a bank far larger than the cache, each
address known only once the line before has come. The table kernel asks
for them (``llvm.prefetch``) a block of rows ahead, so the misses of many
rows overlap (:func:`_prefetch_block`); the arithmetic is untouched.
"""

from __future__ import annotations

import math

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core import model
from mntes_stream.core._numba import numba  # None: the numpy twins above still work

__all__ = ["table_numba", "grid_numba", "table_numpy", "grid_numpy", "front_numpy", "lookup_numpy",
           "row_constants", "compile_kernels", "REC_COLS", "LOW_COLS", "w1_screenable"]

SQRT2 = model.SQRT2
# Counts at or beyond the int32 rails are ADC saturation or "no data" sentinels.
RAIL = float(2**31 - 1)
# |delta / T_s| up to which the 8-term binomial series is used: its remainder
# |C(n, 9)| 0.05^9 / 0.95 < 2e-14 relative for 1 < n < 6; beyond, the exact power.
SERIES_LIMIT = 0.05
_INVALID = int(fl.INVALID_INPUT)
_SAT = int(fl.SATURATED)
_SC = int(fl.SUPERCONDUCTING)
_LAT = int(fl.LATCHED)
_PHASE = int(fl.PHASE_RESIDUAL)
_OOT = int(fl.OUT_OF_TABLE)
_ENV = int(fl.ENV_OUT_OF_RANGE)
_UNKNOWN = int(fl.UNKNOWN_CHANNEL)
_HK_MISSING = int(fl.HK_MISSING)
_UNUSABLE = int(fl.UNUSABLE)
_LOW = int(fl.LOW_RESPONSIVITY)
# Columns of the record ``rec`` (:func:`row_constants`). 0-15 are the front end's
# constants in the order of ``_front``'s ``det``.
_R_K, _R_N, _R_C1, _R_C2, _R_GAMMA = 16, 17, 18, 19, 20
_R_A = 21                                     # 21-28: C(n, 1..8)
_R_INV_T0, _R_K_T0_N = 29, 30
_R_X_LO, _R_X_HI, _R_CPO = 31, 32, 33         # the table's R range, lookup cells per ohm
_R_K0, _R_LAST, _R_C0, _R_NCELL = 34, 35, 36, 37  # first and last knot, first cell, cells (exact in float64)
REC_COLS = 40                                 # padded to 320 bytes, five cache lines
# Columns of the LOW_RESPONSIVITY record (``core.uncertainty.NoiseModel.low_record``): noise per
# quadrature (A), tolerance (W), C(n - 1, 1..8), 1 where the screen may decide (:func:`w1_screenable`).
LOW_COLS = 11
# The largest ratio of W''s terms to W' (:func:`w1_screenable`) for which the screen's W' is near enough to
# the reference's: 1e4 x ~10 eps is ~2e-11 relative, far below the screen's margin (1e-9).
W1_CONDITION_LIMIT = 1e4


# --- numpy twins -------------------------------------------------------------------------

def lookup_numpy(rows, r, ko, x, co, ci, cpo):
    """Global knot index of the interval holding ``r`` (rows broadcast over samples).

    Returns ``j`` (int64, shape of ``r``) and ``inside`` (r within the table).
    """
    d = np.broadcast_to(rows[:, None], r.shape)
    k0 = ko[d]
    last = ko[d + 1] - 1
    with np.errstate(invalid="ignore"):
        inside = (r >= x[k0]) & (r <= x[last])
    rr = np.where(inside, r, x[k0])
    nc = co[d + 1] - co[d]
    cell = np.minimum(((rr - x[k0]) * cpo[d]).astype(np.int64), nc - 1)
    j = k0 + ci[co[d] + np.maximum(cell, 0)]
    while True:
        step = (j + 1 < last) & (rr >= x[np.minimum(j + 1, last)])
        if not np.any(step):
            return j, inside
        j = j + step


def binomials(n):
    """``C(n, k)`` for k = 1..8 (the series ``(1 + x)^n = 1 + sum C(n, k) x^k``).

    Plain arithmetic so the compiled kernel uses this very function.
    """
    a1 = n
    a2 = a1 * (n - 1.0) / 2.0
    a3 = a2 * (n - 2.0) / 3.0
    a4 = a3 * (n - 3.0) / 4.0
    a5 = a4 * (n - 4.0) / 5.0
    a6 = a5 * (n - 5.0) / 6.0
    a7 = a6 * (n - 6.0) / 7.0
    a8 = a7 * (n - 7.0) / 8.0
    return a1, a2, a3, a4, a5, a6, a7, a8


def binomial_series(x, a):
    """``(1 + x)^n`` as ``1 + sum_k a[k-1] x^k``, ``a = binomials(n)``.

    Estrin's scheme: pairs of terms, then x^2 and x^4, three levels of
    multiply-adds instead of Horner's chain of eight (the kernel evaluates
    two of these per sample, each otherwise a long serial dependency).
    """
    x2 = x * x
    x4 = x2 * x2
    lo = (a[0] + a[1] * x) + x2 * (a[2] + a[3] * x)
    hi = (a[4] + a[5] * x) + x2 * (a[6] + a[7] * x)
    return 1.0 + x * (lo + x4 * hi)


def row_constants(phys, t0_k, dom, ko, x, co, cpo):
    """The compiled kernels' per-detector record ``rec`` (n_det, ``REC_COLS``), C-contiguous float64.

    Parameters
    ----------
    phys : ndarray, shape (n_det, 21)
        The kernels' per-detector scalars.
    t0_k : ndarray, shape (n_det,)
        The bath temperature the detector's table refers to (nominal bath for
        "table", ``t_ref_k`` for "grid").
    dom : ndarray, shape (6,)
        The bank's domain (bias bounds become volts here, as the kernel formed them).
    ko, x, co, cpo : the bank's ``knot_offset``, ``r_knot_ohm``, ``cell_offset``, ``cell_per_ohm``
    """
    phys = np.asarray(phys, dtype=np.float64)
    t0 = np.asarray(t0_k, dtype=np.float64)
    rec = np.zeros((len(t0), REC_COLS))
    if not len(t0):
        return rec
    ko, co = np.asarray(ko), np.asarray(co)
    v_nom = phys[:, 11]
    front = (0, 1, 2, 3, 4, None, 12, 13, None, 5, 15, 16, 17, 18, 19, 20)
    for col, src in enumerate(front):
        rec[:, col] = phys[:, src] if src is not None else 0.0
    rec[:, 5], rec[:, 8], rec[:, 11] = dom[4] * v_nom, dom[5] * v_nom, phys[:, 16] * SQRT2
    rec[:, _R_K:_R_GAMMA + 1] = phys[:, 6:11]
    k, n = phys[:, 6], phys[:, 7]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        rec[:, _R_A:_R_A + 8] = np.stack(binomials(n), axis=1)
        rec[:, _R_INV_T0], rec[:, _R_K_T0_N] = 1.0 / t0, k * t0**n
    rec[:, _R_X_LO], rec[:, _R_X_HI], rec[:, _R_CPO] = x[ko[:-1]], x[ko[1:] - 1], cpo
    rec[:, _R_K0], rec[:, _R_LAST], rec[:, _R_C0], rec[:, _R_NCELL] = ko[:-1], ko[1:] - 1, co[:-1], np.diff(co)
    return rec


def w1_screenable(ko, x, coef) -> np.ndarray:
    """Per detector: whether the table kernel's W' (by synthetic division on W's Horner sums) stays within
    ~2e-11 of the reference's ``c1 + u (2 c2 + 3 u c3)`` on every interval, so LOW_RESPONSIVITY's screen may
    decide with it; elsewhere the exact sigma_P decides every sample.

    Both forms err by a few eps times ``S = |c1| + 2 |c2| h + 3 |c3| h^2`` on an interval of width ``h``;
    the test is ``S <= W1_CONDITION_LIMIT min |W'|`` over the interval (W' a quadratic: its ends and vertex;
    0 where it changes sign).

    Parameters
    ----------
    ko : ndarray (n_det + 1,)
        Knot offsets.
    x : ndarray (n_knots,)
        Knots (Ohm).
    coef : ndarray (n_knots, 8)
        The intervals' cubics, W's in columns 0-3.

    Returns
    -------
    ndarray of bool (n_det,)
    """
    ko = np.asarray(ko, dtype=np.int64)
    n_det = len(ko) - 1
    ok = np.zeros(n_det, dtype=bool)
    if n_det <= 0 or len(x) < 2:
        return ok
    h = np.diff(np.asarray(x, dtype=np.float64))
    c1, c2, c3 = (np.asarray(coef, dtype=np.float64)[:-1, k] for k in (1, 2, 3))
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        s = np.abs(c1) + 2.0 * np.abs(c2) * h + 3.0 * np.abs(c3) * h * h
        ends = (c1, c1 + h * (2.0 * c2 + 3.0 * h * c3))
        uv = np.where(c3 != 0.0, -c2 / (3.0 * c3), -1.0)
        vert = np.where((uv > 0.0) & (uv < h), c1 - c2 * c2 / (3.0 * c3), ends[0])
        lo = np.minimum(np.minimum(ends[0], ends[1]), vert)
        hi = np.maximum(np.maximum(ends[0], ends[1]), vert)
        m = np.where((lo > 0.0) | (hi < 0.0), np.minimum(np.abs(lo), np.abs(hi)), 0.0)
        good = s <= W1_CONDITION_LIMIT * m
    for d in range(n_det):
        a, b = ko[d], ko[d + 1] - 1  # intervals a .. b - 1 (the last knot closes the table)
        ok[d] = b > a and bool(np.all(good[a:b]))
    return ok


def hermite_basis(u, h):
    """Cubic Hermite weights of (y0, h-scaled y0', y1, y1') at fraction ``u`` of an interval ``h``."""
    return (1.0 + 2.0 * u) * (1.0 - u) ** 2, u * (1.0 - u) ** 2 * h, u * u * (3.0 - 2.0 * u), u * u * (u - 1.0) * h


def lagrange4(u):
    """4-point Lagrange weights at ``u`` in node units (nodes at 0, 1, 2, 3)."""
    return (
        -(u - 1.0) * (u - 2.0) * (u - 3.0) / 6.0,
        u * (u - 2.0) * (u - 3.0) / 2.0,
        -u * (u - 1.0) * (u - 3.0) / 2.0,
        u * (u - 1.0) * (u - 2.0) / 6.0,
    )


def front_numpy(ci_, cq_, tb, b, v, hk, rows, phys, dom):
    """The per-sample front end every kind shares (numpy; ``_front`` is the compiled twin).

    Parameters: counts, environment and housekeeping flags of shape
    (n_rows, n_samp); ``rows`` (n_rows,) index into ``phys``, -1 unknown.

    Returns
    -------
    r_ohm : ``Re(sqrt(2) V / i - z)`` with the pickup removed
    i_abs_a : ``|i|`` with the pickup removed
    flags : uint16, housekeeping | INVALID_INPUT | SATURATED | SUPERCONDUCTING | LATCHED
        | PHASE_RESIDUAL | ENV_OUT_OF_RANGE (outside ``dom``) | UNKNOWN_CHANNEL
    valid : bool, input usable (R meaningful)
    ok : bool, valid and on the stable branch
    """
    known = (rows >= 0)[:, None]
    ph = phys[np.maximum(rows, 0)][:, :, None]
    xi = np.asarray(ci_, dtype=np.float64)
    xq = np.asarray(cq_, dtype=np.float64)
    with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
        counts_ok = (np.abs(xi) < RAIL) & (np.abs(xq) < RAIL)
        env_ok = (tb > 0) & (np.abs(b) < np.inf) & (v > 0) & (v < np.inf)
        ire = ph[:, 0] * xi - ph[:, 1] * xq - ph[:, 2] * b
        iim = ph[:, 0] * xq + ph[:, 1] * xi - ph[:, 3] * b
        m2 = ire * ire + iim * iim
        valid = counts_ok & env_ok & (m2 > 0) & known
        invalid = known & (~counts_ok | (counts_ok & env_ok & ~(m2 > 0)) | (~env_ok & ((hk & _HK_MISSING) == 0)))
        r = SQRT2 * v * ire / m2 - ph[:, 4]
        sat = valid & ((r >= ph[:, 13]) | ((r - ph[:, 17]) * v >= -ph[:, 18]))
        low = valid & ~sat & ((r - ph[:, 12]) * v <= ph[:, 19])
        # The superconducting side: SUPERCONDUCTING always, LATCHED too where R is resistive.
        sc = low
        lat = low & ~((r - ph[:, 15]) * v <= ph[:, 20])
        # The quadrature current the model does not explain: Im(sqrt2 V/i - z) |i|^2 / (sqrt2 V).
        phase = valid & (np.abs(SQRT2 * v * iim + ph[:, 5] * m2) > ph[:, 16] * SQRT2 * v)
        # Bias bounds as products (fraction x nominal), as a caller computes a bias.
        env_out = known & env_ok & ~(
            (tb >= dom[0]) & (tb <= dom[1]) & (b >= dom[2]) & (b <= dom[3])
            & (v >= dom[4] * ph[:, 11]) & (v <= dom[5] * ph[:, 11])
        )
    f = np.array(hk, dtype=np.uint16)
    f[invalid] |= _INVALID
    f[sat] |= _SAT
    f[sc] |= _SC
    f[lat] |= _LAT
    f[phase] |= _PHASE
    f[env_out] |= _ENV
    f[~known[:, 0]] |= _UNKNOWN
    return r, np.sqrt(m2), f, valid, valid & ~sat & ~low


def _chunks(n_rows, n_samp, elements=1 << 19):
    step = max(1, elements // max(n_samp, 1))
    for r0 in range(0, n_rows, step):
        yield r0, min(n_rows, r0 + step)


def table_numpy(ci_, cq_, tb, ltb, b, v, hk, rows, phys, dom, ko, x, co, cidx, cpo, coef, out_p, out_f):
    """Structured-table conversion in numpy (same contract as :func:`table_numba`)."""
    for r0, r1 in _chunks(*out_p.shape):
        rw = rows[r0:r1]
        r, iabs, f, _, ok = front_numpy(ci_[r0:r1], cq_[r0:r1], tb[r0:r1], b[r0:r1], v[r0:r1], hk[r0:r1],
                                      rw, phys, dom)
        j, inside = lookup_numpy(np.maximum(rw, 0), r, ko, x, co, cidx, cpo)
        f[ok & ~inside] |= _OOT
        ph = phys[np.maximum(rw, 0)][:, :, None]
        bb = b[r0:r1]
        vv = v[r0:r1]
        with np.errstate(invalid="ignore", over="ignore", divide="ignore"):
            s = r - x[j]
            c = coef[j]
            w = c[..., 0] + s * (c[..., 1] + s * (c[..., 2] + s * c[..., 3]))
            inv_ts = c[..., 4] + s * (c[..., 5] + s * (c[..., 6] + s * c[..., 7]))
            delta = ph[:, 8] * bb + ph[:, 9] * bb * bb - ph[:, 10] * iabs
            xx = delta * inv_ts
            n = ph[:, 7]
            kt = w * binomial_series(xx, binomials(n))
            far = ok & inside & ~(np.abs(xx) <= SERIES_LIMIT)
            if np.any(far):
                t = 1.0 / inv_ts[far] + delta[far]
                nf = np.broadcast_to(n, far.shape)[far]
                kf = np.broadcast_to(ph[:, 6], far.shape)[far]
                kt[far] = kf * np.where(t > 0, np.exp(nf * np.log(np.maximum(t, 1e-300))), 0.0)
            p = kt - ph[:, 6] * np.exp(n * ltb[r0:r1]) - vv * vv * r / ((r + ph[:, 4]) ** 2 + ph[:, 5] ** 2)
        out_p[r0:r1] = np.where((f & _UNUSABLE) != 0, np.nan, p)
        out_f[r0:r1] = f


def grid_numpy(ci_, cq_, tb, ltb, b, v, hk, rows, phys, dom, ko, x, co, cidx, cpo,
               p_w, dp_w, bias_v, b_nodes, t_ref, bias_rtol, out_p, out_f):
    """Grid-table conversion in numpy (same contract as :func:`grid_numba`)."""
    nb = b_nodes.size
    db = b_nodes[1] - b_nodes[0]
    for r0, r1 in _chunks(*out_p.shape):
        rw = rows[r0:r1]
        rk = np.maximum(rw, 0)
        r, _, f, _, ok = front_numpy(ci_[r0:r1], cq_[r0:r1], tb[r0:r1], b[r0:r1], v[r0:r1], hk[r0:r1],
                                   rw, phys, dom)
        j, inside = lookup_numpy(rk, r, ko, x, co, cidx, cpo)
        vv = v[r0:r1]
        bv = bias_v[rk][:, None, :]                        # (rows, 1, n_bias)
        with np.errstate(invalid="ignore"):
            match = np.abs(vv[:, :, None] - bv) <= bias_rtol * bv
        state = np.argmax(match, axis=2)
        has_state = np.any(match, axis=2)
        f[ok & ~inside] |= _OOT
        f[ok & inside & ~has_state] |= _OOT | _ENV
        bb = np.where(np.isfinite(b[r0:r1]), b[r0:r1], 0.0)
        f[ok & inside & has_state & ((bb < b_nodes[0]) | (bb > b_nodes[-1]))] |= _ENV
        tpos = (bb - b_nodes[0]) / db
        j0 = np.clip(np.floor(tpos).astype(np.int64) - 1, 0, nb - 4)
        w = lagrange4(tpos - j0)
        h = x[np.minimum(j + 1, x.size - 1)] - x[j]
        with np.errstate(invalid="ignore", divide="ignore", over="ignore"):
            h00, h10, h01, h11 = hermite_basis((r - x[j]) / h, h)
            acc = np.zeros(r.shape)
            for q in range(4):
                jb = j0 + q
                acc += w[q] * (h00 * p_w[j, state, jb] + h10 * dp_w[j, state, jb]
                               + h01 * p_w[j + 1, state, jb] + h11 * dp_w[j + 1, state, jb])
            ph = phys[rk][:, :, None]
            p = acc + ph[:, 6] * (t_ref[rk][:, None] ** ph[:, 7] - np.exp(ph[:, 7] * ltb[r0:r1]))
        out_p[r0:r1] = np.where((f & _UNUSABLE) != 0, np.nan, p)
        out_f[r0:r1] = f


# --- compiled kernels ----------------------------------------------------------------------


if numba is not None:
    from numba.core import compiler as _numba_compiler

    from mntes_stream.core._baselines import compact, row_view

    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")
    # Helpers are inlined in numba IR: a real call would incref/decref every
    # array argument (atomic operations) per sample and cost ~6x in speed.
    _inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")

    class _NoAliasCompiler(_numba_compiler.Compiler):
        """numba's compiler with every pointer argument ``noalias`` (C's ``restrict``).

        Without it LLVM cannot vectorise a loop that reads the tables at computed
        indices and stores results ("cannot identify array bounds"): an output
        might alias a table. The kernels' outputs never alias an input (the
        wrappers allocate them), so the promise holds.
        """

        def __init__(self, typingctx, targetctx, library, args, return_type, flags, locals):
            flags.noalias = True
            super().__init__(typingctx, targetctx, library, args, return_type, flags, locals)

    _jit_vector = numba.njit(cache=True, nogil=True, error_model="numpy", pipeline_class=_NoAliasCompiler)

    from llvmlite import ir as _ir
    from numba.core import types as _nt
    from numba.extending import intrinsic as _intrinsic

    @_intrinsic
    def _prefetch(typingctx, arr, i):
        """Start loading the cache line of element ``i`` (flat, C order) of ``arr`` into L1; no result.

        LLVM's ``llvm.prefetch`` (``prefetcht0`` on x86), which numba does not
        expose. Unlike a load it neither waits nor faults, so a kernel can ask
        for the table lines of many rows before it reads the first of them.
        ``i`` must lie within the array only for the later read to be useful.
        """
        sig = _nt.void(arr, i)

        def codegen(context, builder, signature, args):
            aryty, ity = signature.args
            ary = context.make_array(aryty)(context, builder, args[0])
            ptr = builder.gep(ary.data, [context.cast(builder, args[1], ity, _nt.intp)])
            i8p, i32 = _ir.IntType(8).as_pointer(), _ir.IntType(32)
            fn = builder.module.declare_intrinsic("llvm.prefetch", [i8p],
                                                  _ir.FunctionType(_ir.VoidType(), [i8p, i32, i32, i32]))
            # read (0), keep in all levels (3), data cache (1)
            builder.call(fn, [builder.bitcast(ptr, i8p), i32(0), i32(3), i32(1)])
            return context.get_dummy_value()

        return sig, codegen

    @_inline
    def _front(xi, xq, tb, b, v, hk, det, dom):
        """One sample: flags so far, R, |i|^2 and whether R is on the stable branch.

        ``det`` = (g_re, g_im, m_re, m_im, z_re, v_lo, r_z, r_cap, v_hi, z_im,
        r_bottom, phase limit x sqrt2, r_top, k_top, k_z, k_bottom) with the
        domain's bias bounds ``v_lo, v_hi`` in volts, and ``dom`` the 6 domain
        bounds, both tuples of scalars hoisted out of the sample loop (array
        reads here were reloaded every sample: ~8x slower).
        """
        f = hk
        env_ok = tb > 0.0 and abs(b) < math.inf and v > 0.0 and v < math.inf
        if env_ok:
            if not (dom[0] <= tb <= dom[1] and dom[2] <= b <= dom[3] and det[5] <= v <= det[8]):
                f |= _ENV
        if not (abs(xi) < RAIL and abs(xq) < RAIL):
            return f | _INVALID, 0.0, 0.0, False
        if not env_ok:
            if (hk & _HK_MISSING) == 0:
                f |= _INVALID
            return f, 0.0, 0.0, False
        ire = det[0] * xi - det[1] * xq - det[2] * b
        iim = det[0] * xq + det[1] * xi - det[3] * b
        m2 = ire * ire + iim * iim
        if not m2 > 0.0:
            return f | _INVALID, 0.0, 0.0, False
        r = SQRT2 * v * ire / m2 - det[4]
        if abs(SQRT2 * v * iim + det[9] * m2) > det[11] * v:
            f |= _PHASE
        if r >= det[7] or (r - det[12]) * v >= -det[13]:
            return f | _SAT, r, 0.0, False
        if (r - det[6]) * v <= det[14]:
            return f | (_SC if (r - det[10]) * v <= det[15] else _SC | _LAT), r, 0.0, False
        return f, r, m2, True  # |i| only where a detector's current shift needs it: sqrt costs

    @_inline
    def _record(rec, d):
        """Row ``d`` of the record (:func:`row_constants`) as a tuple of scalars, read once per row."""
        return (rec[d, 0], rec[d, 1], rec[d, 2], rec[d, 3], rec[d, 4], rec[d, 5], rec[d, 6], rec[d, 7],
                rec[d, 8], rec[d, 9], rec[d, 10], rec[d, 11], rec[d, 12], rec[d, 13], rec[d, 14], rec[d, 15],
                rec[d, 16], rec[d, 17], rec[d, 18], rec[d, 19], rec[d, 20], rec[d, 21], rec[d, 22], rec[d, 23],
                rec[d, 24], rec[d, 25], rec[d, 26], rec[d, 27], rec[d, 28], rec[d, 29], rec[d, 30], rec[d, 31],
                rec[d, 32], rec[d, 33], rec[d, 34], rec[d, 35], rec[d, 36], rec[d, 37])

    @_inline
    def _det(q):
        """The front end's constants of record ``q`` (``_front``'s ``det``)."""
        return (q[0], q[1], q[2], q[3], q[4], q[5], q[6], q[7], q[8], q[9], q[10], q[11], q[12], q[13], q[14], q[15])

    @_inline
    def _binomials(q):
        """``C(n, 1..8)`` of record ``q``."""
        return (q[21], q[22], q[23], q[24], q[25], q[26], q[27], q[28])

    _series = _inline(binomial_series)
    _hermite = _inline(hermite_basis)
    _lagrange = _inline(lagrange4)

    @_inline
    def _bath(tb, ltb, inv_tb0, k_tb0_n, k, n, a):
        """``K T_bath^n``: binomial series around the nominal bath within 5%, exact beyond."""
        y = tb * inv_tb0 - 1.0
        if abs(y) <= SERIES_LIMIT:
            return k_tb0_n * _series(y, a)
        return k * math.exp(n * ltb)

    @_inline
    def _dom(dom):
        return (dom[0], dom[1], dom[2], dom[3], dom[4], dom[5])

    @_inline
    def _cell(r, q):
        """Index into ``cell_interval`` of the lookup cell of ``r`` (within detector record ``q``'s table).

        The cell within the table is truncated to int32 (it lies in ``[0, n_cells]``): AVX2 has a
        vector double-to-int32 conversion but none to int64, which the compiler did lane by lane in
        the vector front-end loops (an AVX-512 CPU has both)."""
        cell = np.int32((r - q[_R_X_LO]) * q[_R_CPO])
        n1 = int(q[_R_NCELL]) - 1
        return int(q[_R_C0]) + (cell if cell < n1 else n1)

    @_inline
    def find_interval(r, q, x, cidx):
        """Global knot index ``j`` of the interval holding ``r``, ``x[j] <= r < x[j + 1]`` (the last
        interval holds its right end), for ``r`` within detector record ``q``'s table.

        The interval every kernel on a bank interpolates in: the O(1) lookup
        cell, one branch-free step (a cell holds at most one knot,
        :func:`core.tables.lookup_cells`, unless its cap on cells applies; none
        where knots begin cells, as :func:`core.tables.transition_knots` places
        them), then the rare rest. Inlined where called (numba IR).
        """
        j = int(q[_R_K0]) + cidx[_cell(r, q)]
        last = int(q[_R_LAST])
        j += (j + 1 < last) & (r >= x[j + 1])
        while j + 1 < last and r >= x[j + 1]:
            j += 1
        return j

    @_inline
    def _table_sample(xi, xq, tb, ltb, b, v, hk, q, dm, x, cidx, coef):
        """One sample of the "table" kind, with every branch: the reference arithmetic.

        Returns power (NaN where unusable) and flags. The vector lanes of
        ``_table_kernel`` compute exactly this where no branch is taken.
        """
        f, r, i2, ok = _front(xi, xq, tb, b, v, hk, _det(q), dm)
        p = math.nan
        if ok:
            j = -1
            if q[_R_X_LO] <= r <= q[_R_X_HI]:
                j = find_interval(r, q, x, cidx)
            a = _binomials(q)
            k, n = q[_R_K], q[_R_N]
            kb = _bath(tb, ltb, q[_R_INV_T0], q[_R_K_T0_N], k, n, a)
            if j < 0:
                f |= _OOT
            else:
                u = r - x[j]
                w = coef[j, 0] + u * (coef[j, 1] + u * (coef[j, 2] + u * coef[j, 3]))
                inv_ts = coef[j, 4] + u * (coef[j, 5] + u * (coef[j, 6] + u * coef[j, 7]))
                gamma = q[_R_GAMMA]
                delta = q[_R_C1] * b + q[_R_C2] * b * b - (gamma * math.sqrt(i2) if gamma != 0.0 else 0.0)
                xx = delta * inv_ts
                if abs(xx) <= SERIES_LIMIT:
                    kt = w * _series(xx, a)
                else:
                    t = 1.0 / inv_ts + delta
                    kt = k * math.exp(n * math.log(t)) if t > 0.0 else 0.0
                p = kt - kb - v * v * r / ((r + q[4]) ** 2 + q[9] * q[9])
        if f & _UNUSABLE:
            p = math.nan
        return p, f

    # The vector lane in two parts around the table reads, which stay in the kernel's own loop:
    # a helper given an array leaves reference counting (calls) in the loop, and no vectorising.

    @_inline
    def _lane_front(xi, xq, tb, b, v, hk, q, dm):
        """``_front`` without a branch: flags (all but ``OUT_OF_TABLE``), R, |i|^2, whether usable,
        whether inside the table, and the R to look up (R inside, the table's start outside, so
        every lane reads in bounds). Bitwise ``&``/``|`` on booleans: ``and``/``or`` would branch.
        """
        env_ok = (tb > 0.0) & (abs(b) < math.inf) & (v > 0.0) & (v < math.inf)
        in_dom = (dm[0] <= tb) & (tb <= dm[1]) & (dm[2] <= b) & (b <= dm[3]) & (q[5] <= v) & (v <= q[8])
        counts_ok = (abs(xi) < RAIL) & (abs(xq) < RAIL)
        ire = q[0] * xi - q[1] * xq - q[2] * b
        iim = q[0] * xq + q[1] * xi - q[3] * b
        m2 = ire * ire + iim * iim
        m2_ok = m2 > 0.0
        valid = counts_ok & env_ok & m2_ok
        bad = ~counts_ok | (env_ok & ~m2_ok) | (~env_ok & ((hk & _HK_MISSING) == 0))
        r = SQRT2 * v * ire / m2 - q[4]
        phase = valid & (abs(SQRT2 * v * iim + q[9] * m2) > q[11] * v)
        sat = valid & ((r >= q[7]) | ((r - q[12]) * v >= -q[13]))
        low = valid & ~sat & ((r - q[6]) * v <= q[14])
        lat = low & ~((r - q[10]) * v <= q[15])
        ok = valid & ~sat & ~low
        x_lo = q[_R_X_LO]
        inside = ok & (x_lo <= r) & (r <= q[_R_X_HI])
        f = (hk | (_ENV * (env_ok & ~in_dom)) | (_INVALID * bad) | (_PHASE * phase) | (_SAT * sat) | (_SC * low)
             | (_LAT * lat) | (_OOT * (ok & ~inside)))
        return f, r, m2, inside, (r if inside else x_lo)

    @_inline
    def _lane_power(w, inv_ts, r, m2, tb, b, v, q):
        """Power from the table's ``W`` and ``1 / T_s`` at R, by the series alone; whether the
        series does not hold (then ``_table_sample`` gives the sample); ``x = delta / T_s`` and ``(1 + x)^n``."""
        a = _binomials(q)
        y = tb * q[_R_INV_T0] - 1.0
        kb = q[_R_K_T0_N] * _series(y, a)
        gamma = q[_R_GAMMA]
        delta = q[_R_C1] * b + q[_R_C2] * b * b - (gamma * math.sqrt(m2) if gamma != 0.0 else 0.0)
        xx = delta * inv_ts
        sn = _series(xx, a)
        kt = w * sn
        p = kt - kb - v * v * r / ((r + q[4]) ** 2 + q[9] * q[9])
        return p, ~(abs(xx) <= SERIES_LIMIT) | ~(abs(y) <= SERIES_LIMIT), xx, sn

    _NO_LQ = (0.0,) * LOW_COLS

    @_inline
    def sigma_gradient(w, w1, uu, fp, r, m2, vs, n, gamma, zr, zi):
        """``|grad_i P|`` (``core.uncertainty``) from the table's ``W``, ``W'``, ``U = 1/T_s`` and
        ``(1 + delta U)^(n-1)`` at R; sigma_P is the noise per quadrature times it. The one copy of
        this arithmetic: the conversion's LOW_RESPONSIVITY and the sigma_P pass both call it, so they
        flag alike to the bit."""
        sv_m2 = SQRT2 * vs / m2  # |grad_i R|
        rz = r + zr
        mz2 = rz * rz + zi * zi
        # dP/dR at fixed |i|: K n T^(n-1) T_s' = W' (T / T_s)^(n-1), less the Joule slope.
        a = w1 * fp - vs * vs * (zr * zr + zi * zi - r * r) / (mz2 * mz2)
        gr = a * sv_m2
        bb = -gamma * n * w * uu * fp
        g2 = gr * gr + bb * bb - 2.0 * a * bb * rz / math.sqrt(m2)
        return math.sqrt(g2 if g2 > 0.0 else 0.0)

    @_inline
    def _low_binomials(lq):
        """``C(n - 1, 1..8)`` of a LOW_RESPONSIVITY record row (``(1 + x)^(n-1)`` by the series)."""
        return (lq[2], lq[3], lq[4], lq[5], lq[6], lq[7], lq[8], lq[9])

    @_inline
    def _sigma_sample(xi, xq, b, v, q, lq, x, cidx, coef):
        """sigma_P of one usable sample with every branch (what ``core._uncertainty_kernel``'s
        reference gives): the interval by :func:`find_interval`, the exact power beyond the series;
        NaN outside the table."""
        ire = q[0] * xi - q[1] * xq - q[2] * b
        iim = q[0] * xq + q[1] * xi - q[3] * b
        m2 = ire * ire + iim * iim
        r = SQRT2 * v * ire / m2 - q[4]
        if not (q[_R_X_LO] <= r <= q[_R_X_HI]):
            return math.nan
        j = find_interval(r, q, x, cidx)
        u = r - x[j]
        w = coef[j, 0] + u * (coef[j, 1] + u * (coef[j, 2] + u * coef[j, 3]))
        w1 = coef[j, 1] + u * (2.0 * coef[j, 2] + 3.0 * u * coef[j, 3])
        uu = coef[j, 4] + u * (coef[j, 5] + u * (coef[j, 6] + u * coef[j, 7]))
        n, gamma = q[_R_N], q[_R_GAMMA]
        xx = (q[_R_C1] * b + q[_R_C2] * b * b - gamma * math.sqrt(m2)) * uu
        if abs(xx) <= SERIES_LIMIT:
            fp = _series(xx, _low_binomials(lq))
        else:
            fp = math.exp((n - 1.0) * math.log(1.0 + xx)) if xx > -1.0 else 0.0
        return lq[0] * sigma_gradient(w, w1, uu, fp, r, m2, v, n, gamma, q[4], q[9])

    @_jit
    def _fill(a, row, scratch):
        """Row ``row`` of a compact environment array (``_baselines.compact``) into ``scratch``
        (unit stride for the sample loop). A call, not inlined: once per row, and six inlined
        copies of its loops cost seconds of compilation."""
        r = row if a.shape[0] > 1 else 0
        if a.shape[1] > 1:
            for s in range(scratch.size):
                scratch[s] = a[r, s]
        else:
            value = a[r, 0]
            for s in range(scratch.size):
                scratch[s] = value

    # Rows per block of _prefetch_block: enough misses in flight to fill the memory pipeline, and
    # their lines (some 18 a row, 70 kB a block) still in L1/L2 when the rows are converted.
    _BLOCK = 64

    @_inline
    def _cell_of(xi, xq, bs, vs, rec, d):
        """Index into ``cell_interval`` of a sample's lookup cell, for prefetching only: R as the
        kernel computes it, the table's first cell where R is outside the table or NaN."""
        ire = rec[d, 0] * xi - rec[d, 1] * xq - rec[d, 2] * bs
        iim = rec[d, 0] * xq + rec[d, 1] * xi - rec[d, 3] * bs
        r = SQRT2 * vs * ire / (ire * ire + iim * iim) - rec[d, 4]
        x_lo = rec[d, _R_X_LO]
        rc = r if (x_lo <= r) & (r <= rec[d, _R_X_HI]) else x_lo  # NaN too: int(NaN) is undefined
        k = int((rc - x_lo) * rec[d, _R_CPO])
        n1 = int(rec[d, _R_NCELL]) - 1
        return int(rec[d, _R_C0]) + (k if k < n1 else n1)

    @_jit
    def _prefetch_block(ends, b, v, rows, rec, x, cidx, coef, r0, r1, cells):
        """Prefetch the table lines rows ``r0:r1`` will read: their records, the lookup cells
        between their first and last samples' R, and those cells' intervals.

        A short row (a live chunk holds about 20 samples) otherwise waits on
        a chain of cache misses before its first sample (record, then cell,
        then knot and coefficients: each address needs the line before) and the
        next row's chain starts only after. Here each link is asked for the
        whole block at once, one pass per link, so the misses of all its rows
        overlap (5120 rows of 20 samples: 0.9 us a row before, 0.3 after).
        The first and last samples bound the cells and intervals of a slowly
        varying row (the bench's span some five lines of cells, two or three
        intervals); at most eight lines of cells and nine intervals a row.
        ``ends`` (shape (>= r1 - r0, 4)) holds each row's first and last
        counts (I, Q, I, Q) as float64, so this function has one signature
        whatever the counts' type (each costs half a second of compiling).
        Only addresses are computed, nothing is written but ``cells``
        (scratch, shape (>= r1 - r0, 2), int64: each row's lowest and highest
        cell, from the second pass to the third).
        """
        n_col, n_coef = rec.shape[1], coef.shape[1]
        for row in range(r0, r1):
            d = rows[row]
            if d >= 0:
                base = d * n_col
                for c in range(0, n_col, 8):
                    _prefetch(rec, base + c)
                _prefetch(rec, base + n_col - 1)  # the last line, when rec is not line-aligned
        rb, rv = b.shape[0] > 1, v.shape[0] > 1
        b1, v1 = b.shape[1] - 1, v.shape[1] - 1
        for row in range(r0, r1):
            d = rows[row]
            c0 = c1 = -1
            if d >= 0:
                br, vr, e = row if rb else 0, row if rv else 0, row - r0
                c0 = _cell_of(ends[e, 0], ends[e, 1], b[br, 0], v[vr, 0], rec, d)
                c1 = _cell_of(ends[e, 2], ends[e, 3], b[br, b1], v[vr, v1], rec, d)
                if c1 < c0:
                    c0, c1 = c1, c0
                for c in range(c0, min(c1, c0 + 8 * 16) + 1, 16):  # int32 cells, 16 a line
                    _prefetch(cidx, c)
                _prefetch(cidx, c1)
            cells[row - r0, 0], cells[row - r0, 1] = c0, c1
        for row in range(r0, r1):
            c0, c1 = cells[row - r0, 0], cells[row - r0, 1]
            if c0 >= 0:
                k0 = int(rec[rows[row], _R_K0])
                j0, j1 = k0 + cidx[c0], k0 + cidx[c1] + 1  # j1: a row may step into the next interval
                j1 = min(j1, j0 + 8)
                for j in range(j0, j1 + 1):
                    _prefetch(coef, j * n_coef)
                    _prefetch(coef, j * n_coef + n_coef - 1)
                _prefetch(x, j0)
                _prefetch(x, j1)

    # LOW_RESPONSIVITY's screen in _table_kernel decides alone where sigma_P^2 and the tolerance^2, scaled
    # to need no division, differ by more than this fraction of their terms' magnitudes (far above the
    # rounding of either form, ~1e-15); nearer, the exact sigma_P (_sigma_sample) does.
    _LOW_MARGIN = 1e-9

    @_jit_vector
    def _table_kernel(ci_, cq_, tb, ltb, b, v, hk, rows, rec, dom, x, cidx, coef, low, out_p, out_f):
        """The "table" kind over (n_rows, n_samp) samples: ``out_p`` (NaN where unusable), ``out_f``.

        A row's front end and power run as vector lanes (the compiler's scalar
        remainder runs the same branch-free code), its table lookup between them
        sample by sample. A lane that needs a branch (a second
        lookup step, the exact power beyond the series) is marked and done
        again by the reference, :func:`_table_sample`, which is called only
        there: it reads the tables as array arguments, whose reference
        counting costs a call per sample. Rows go in blocks of ``_BLOCK``,
        whose table lines :func:`_prefetch_block` asks for first.

        ``low`` (n_bank, ``LOW_COLS``) or empty: LOW_RESPONSIVITY in the power pass, where sigma_P
        (``sigma_gradient`` on the row's noise ``low[d, 0]``) exceeds the tolerance ``low[d, 1]``:
        the arithmetic of ``core._uncertainty_kernel`` on the values this kernel has in hand (R,
        ``|i|^2``, ``W``, ``1/T_s`` and ``delta / T_s``; ``W'`` from the interval's cubic), so no
        second pass reads the counts and the tables again.
        """
        n_rows, n_samp = out_p.shape
        low_on = low.shape[0] > 0
        if coef.shape[1] != 8:
            raise ValueError("table coefficients: 8 per interval expected")
        cf = coef.reshape(coef.size)
        dm = _dom(dom)
        s_tb, s_ltb, s_b, s_v = np.empty(n_samp), np.empty(n_samp), np.empty(n_samp), np.empty(n_samp)
        s_hk = np.empty(n_samp, dtype=np.uint16)
        marks = np.zeros(n_samp, dtype=np.uint8)
        # The front end's results per sample, for the lookup and power passes.
        # Flags kept 64 bits wide until the output: narrowed in the vector front pass, each flag's mask was
        # packed to 16 bits on its own (AVX2, 4 lanes: three instructions a flag). "Inside" rides in bit 32
        # of the same word: one array fewer to write and read (the plain conversion 0.95-0.98x).
        s_f, s_c = np.empty(n_samp, dtype=np.int64), np.empty(n_samp, np.int64)
        s_r, s_m2, s_rc, s_w, s_its = np.empty(n_samp), np.empty(n_samp), np.empty(n_samp), np.empty(n_samp), \
            np.empty(n_samp)
        # W' (LOW_RESPONSIVITY) goes over the looked-up R, which only the lookup reads (no array of its own;
        # measured no faster or slower than one).
        s_w1 = s_rc
        shared = (tb.shape[0] == 1, ltb.shape[0] == 1, b.shape[0] == 1, v.shape[0] == 1, hk.shape[0] == 1)
        _fill(tb, 0, s_tb), _fill(ltb, 0, s_ltb), _fill(b, 0, s_b), _fill(v, 0, s_v), _fill(hk, 0, s_hk)
        cells, ends = np.empty((_BLOCK, 2), dtype=np.int64), np.empty((_BLOCK, 4))
        for r0 in range(0, n_rows, _BLOCK):
            r1 = min(r0 + _BLOCK, n_rows)
            if n_samp > 0:
                for row in range(r0, r1):
                    e = row - r0
                    ends[e, 0], ends[e, 1] = ci_[row, 0], cq_[row, 0]
                    ends[e, 2], ends[e, 3] = ci_[row, n_samp - 1], cq_[row, n_samp - 1]
                _prefetch_block(ends, b, v, rows, rec, x, cidx, coef, r0, r1, cells)
            for row in range(r0, r1):
                d = rows[row]
                if not shared[4]:
                    _fill(hk, row, s_hk)
                if d < 0:
                    for s in range(n_samp):
                        out_f[row, s] = s_hk[s] | _UNKNOWN
                        out_p[row, s] = math.nan
                    continue
                if not shared[0]:
                    _fill(tb, row, s_tb)
                if not shared[1]:
                    _fill(ltb, row, s_ltb)
                if not shared[2]:
                    _fill(b, row, s_b)
                if not shared[3]:
                    if v.shape[1] == 1:  # the live layout (a bias per detector): no call per row
                        v_row = v[row, 0]
                        for s in range(n_samp):
                            s_v[s] = v_row
                    else:
                        _fill(v, row, s_v)
                q = _record(rec, d)
                k0, last = int(q[_R_K0]), int(q[_R_LAST])
                n_slow = 0
                lq = _NO_LQ
                # Three passes over the row: the front end (vector), the table lookup (scalar), the power
                # (vector). Vectorised, the lookup's reads are gathers, a dozen per lane group, which cost
                # more than the same reads done one by one (this 3-pass form: +20 % on 512 x 10000).
                for s in range(n_samp):
                    f, r, m2, inside, rc = _lane_front(float(ci_[row, s]), float(cq_[row, s]), s_tb[s], s_b[s],
                                                       s_v[s], int(s_hk[s]), q, dm)
                    s_f[s], s_r[s], s_m2[s], s_rc[s] = f | (np.int64(inside) << 32), r, m2, rc
                    s_c[s] = _cell(rc, q)
                for s in range(n_samp):
                    c = s_c[s]
                    if c < 0:  # never (rc is in the table): an early exit keeps the compiler from gathering
                        break
                    # find_interval's lookup, one step, and whether it needed more. Unsigned indices (all
                    # are >= 0): numba wraps a signed index that might be negative, a compare and select
                    # on each of the eleven reads (+14 %). The step is a branch: knots begin lookup cells
                    # (core.tables.transition_knots), so it is rarely taken (0.5 % of bench convert's
                    # samples) and well predicted; the step as arithmetic was 1.02-1.06x slower
                    # (benchmarks/README.md, variant branchless_step).
                    rc = s_rc[s]
                    j = k0 + cidx[np.uint64(c)]
                    if (j + 1 < last) & (rc >= x[np.uint64(j + 1)]):
                        j += 1
                        marks[s] = (j + 1 < last) & (rc >= x[np.uint64(j + 1)])
                    else:
                        marks[s] = 0
                    u = rc - x[np.uint64(j)]
                    # The interval's eight coefficients from the flat table at a constant stride (a shift,
                    # where coef[j, k] multiplied j by the array's stride). W by Horner as the reference;
                    # its partial sums give W' (synthetic division) in three operations more.
                    ju = np.uint64(j) * np.uint64(8)
                    p3 = u * cf[ju + np.uint64(3)]
                    t3 = cf[ju + np.uint64(2)] + p3
                    t2 = cf[ju + np.uint64(1)] + u * t3
                    s_w[s] = cf[ju] + u * t2
                    s_its[s] = cf[ju + np.uint64(4)] + u * (cf[ju + np.uint64(5)] + u * (cf[ju + np.uint64(6)]
                                                                                         + u * cf[ju + np.uint64(7)]))
                    if low_on:
                        s_w1[s] = t2 + u * (t3 + p3)
                if not low_on:
                    for s in range(n_samp):
                        tbs, bs, vs, fx = s_tb[s], s_b[s], s_v[s], s_f[s]
                        f, inside = fx & 0xFFFF, (fx >> 32) != 0
                        p, beyond, _, _ = _lane_power(s_w[s], s_its[s], s_r[s], s_m2[s], tbs, bs, vs, q)
                        out_p[row, s] = p if inside & ((f & _UNUSABLE) == 0) else math.nan
                        out_f[row, s] = f
                        slow = inside & ((marks[s] != 0) | beyond)
                        marks[s] = slow
                        n_slow += slow
                else:
                    # With LOW_RESPONSIVITY: the test sigma_P > tol with |grad_i P|^2 (sigma_gradient) multiplied
                    # through by |i|^4 |R + z|^8 (1 + x)^2, so no division, no square root but |i|'s and no series
                    # but the power's (1 + x)^n = (1 + x)^(n-1) (1 + x), all shared with the power. Lanes too near
                    # the tolerance to tell are done again as slow lanes, the exact sigma_P deciding.
                    lq = (low[d, 0], low[d, 1], low[d, 2], low[d, 3], low[d, 4], low[d, 5], low[d, 6], low[d, 7],
                          low[d, 8], low[d, 9], low[d, 10])
                    gamma, zr, zi = q[_R_GAMMA], q[4], q[9]
                    sig2, zz, zi2, bbc = lq[0] * lq[0], zr * zr + zi * zi, zi * zi, -gamma * q[_R_N]
                    # sigma_P^2 > tol^2 divided through by sigma_i^2: tau = (tol / sigma_i)^2. With no noise sigma_P
                    # is 0, never above a tolerance; a detector without a nominal sigma_P (tol inf) is never flagged.
                    checks = (lq[1] < math.inf) & (sig2 > 0.0)
                    tau = lq[1] * lq[1] / sig2 if checks else 0.0
                    # The screen decides alone only where its W' is near the reference's (lq[10]) and tau finite;
                    # elsewhere the margin is infinite: every usable lane is near, the exact sigma_P decides.
                    mg = _LOW_MARGIN if (lq[10] != 0.0) & (tau < math.inf) else math.inf
                    mg2 = mg + mg
                    for s in range(n_samp):
                        tbs, bs, vs, fx = s_tb[s], s_b[s], s_v[s], s_f[s]
                        f, inside = fx & 0xFFFF, (fx >> 32) != 0
                        r, m2, uu, w = s_r[s], s_m2[s], s_its[s], s_w[s]
                        p, beyond, xx, sn = _lane_power(w, uu, r, m2, tbs, bs, vs, q)
                        usable = inside & ((f & _UNUSABLE) == 0)
                        # Each product written once (the compiler may not reassociate): the Joule term's
                        # |R + z|^2, V^2 and |i| are the power's own.
                        rz = r + zr
                        mz2 = rz * rz + zi2
                        mz4 = mz2 * mz2
                        vv = vs * vs
                        x1 = 1.0 + xx
                        jx = vv * x1
                        r2 = r * r
                        wt = s_w1[s] * sn * mz4
                        ap = wt - jx * (zz - r2)                         # dP/dR |R + z|^4 (1 + x)
                        aa = abs(wt) + jx * (zz + r2)                     # its terms' magnitude (it may cancel)
                        m2z = m2 * mz4
                        bm = (bbc * uu) * (w * sn) * m2z                  # dP/d|i| |i|^2 |R + z|^4 (1 + x)
                        im = math.sqrt(m2) if gamma != 0.0 else 0.0
                        mk = m2z * x1
                        tk = tau * (mk * mk)
                        vv2 = vv + vv
                        b2 = bm * bm
                        # |grad_i P|^2 |i|^4 |R + z|^8 (1 + x)^2 = 2 V^2 ap^2 + bm^2 - 2 ap bm (R + Re z) |i|.
                        dd = ap * (vv2 * ap - (bm + bm) * (rz * im)) + b2 - tk
                        # The rounding of either form is below eps times the terms' magnitudes: the cross term
                        # is at most 2 V^2 ap^2 + bm^2 ((R + Re z) |i| <= sqrt(2) V, as
                        # R + Re z = sqrt(2) V Re(i) / |i|^2), and dP/dR's own terms bound it where they cancel
                        # (aa for ap): S = 2 (2 V^2 aa^2 + bm^2). tau k needs no place in the margin: where
                        # dd > M S, tau k < S + |error|, so the error is ~eps S; where dd < -M S, the error is
                        # ~eps (S + |dd|), and M >> eps. (W sn is the power's K T^n term: computed once.)
                        mag = mg2 * (vv2 * aa * aa + b2)
                        out_p[row, s] = p if usable else math.nan
                        out_f[row, s] = f | (_LOW * (usable & checks & (dd > mag)))
                        near = usable & checks & ~(abs(dd) > mag)
                        slow = inside & ((marks[s] != 0) | beyond | near)
                        marks[s] = slow
                        n_slow += slow
                if n_slow:
                    for s in range(n_samp):
                        if marks[s]:
                            xi, xq = float(ci_[row, s]), float(cq_[row, s])
                            p, f = _table_sample(xi, xq, s_tb[s], s_ltb[s], s_b[s], s_v[s], int(s_hk[s]), q, dm, x,
                                                 cidx, coef)
                            if low_on and (f & _UNUSABLE) == 0:
                                if _sigma_sample(xi, xq, s_b[s], s_v[s], q, lq, x, cidx, coef) > lq[1]:
                                    f |= _LOW
                            out_p[row, s], out_f[row, s] = p, f

    @_jit
    def _grid_kernel(ci_, cq_, tb, ltb, b, v, hk, rows, rec, dom, x, cidx,
                     p_w, dp_w, bias_v, b_nodes, t_ref, bias_rtol, out_p, out_f):
        """The "grid" kind over (n_det, n_samp) samples.

        Writes ``out_p`` (float64, NaN where unusable) and ``out_f`` (uint16).
        A row in three passes: the front end as vector lanes (``_lane_front``),
        the interval, bias state and grid interpolation sample by sample, the
        bath term and the outputs as vector lanes; a sample whose bath is beyond
        the series is done again with the exact power. One function rather than
        a shared helper: array arguments to a helper leave per-sample
        reference-count calls in the loop (measured ~3x slower).
        """
        n_rows, n_samp = out_p.shape
        dm = _dom(dom)
        nb = b_nodes.size
        n_bias = bias_v.shape[1]
        b_lo, b_hi = b_nodes[0], b_nodes[nb - 1]
        inv_db = 1.0 / (b_nodes[1] - b_nodes[0])
        s_tb, s_ltb, s_b, s_v = np.empty(n_samp), np.empty(n_samp), np.empty(n_samp), np.empty(n_samp)
        s_hk = np.empty(n_samp, dtype=np.uint16)
        # The front end's results per sample, for the interpolation and output passes.
        s_f, s_in, s_c = np.empty(n_samp, dtype=np.uint16), np.empty(n_samp, dtype=np.uint8), np.empty(n_samp, np.int64)
        s_rc, s_acc = np.empty(n_samp), np.empty(n_samp)
        s_j0, s_w4 = np.empty(n_samp, np.int64), np.empty((n_samp, 4))
        marks = np.zeros(n_samp, dtype=np.uint8)
        for row in range(n_rows):
            d = rows[row]
            hk_r = row_view(hk, row, s_hk)
            if d < 0:
                for s in range(n_samp):
                    out_f[row, s] = hk_r[s] | _UNKNOWN
                    out_p[row, s] = math.nan
                continue
            q = _record(rec, d)
            tb_r, ltb_r, b_r, v_r = row_view(tb, row, s_tb), row_view(ltb, row, s_ltb), row_view(b, row, s_b), row_view(v, row, s_v)
            k0, last = int(q[_R_K0]), int(q[_R_LAST])
            a = _binomials(q)
            # Three passes over the row: the front end (vector), the interpolation (scalar: its reads
            # at computed indices, vectorised, would be gathers), the bath term and outputs (vector).
            for s in range(n_samp):
                f, r, m2, inside, rc = _lane_front(float(ci_[row, s]), float(cq_[row, s]), tb_r[s], b_r[s], v_r[s],
                                                   int(hk_r[s]), q, dm)
                s_f[s], s_in[s], s_rc[s] = f, inside, rc
                s_c[s] = _cell(rc, q)
                # The field's Lagrange weights here, as vector lanes, not in the scalar pass (+11 %);
                # b_lo where the sample is not used (int(NaN) is undefined).
                tpos = ((b_r[s] if inside else b_lo) - b_lo) * inv_db
                j0 = min(max(int(math.floor(tpos)) - 1, 0), nb - 4)
                s_j0[s] = j0
                s_w4[s, 0], s_w4[s, 1], s_w4[s, 2], s_w4[s, 3] = _lagrange(tpos - j0)
            for s in range(n_samp):
                if not s_in[s]:
                    continue
                # find_interval. Unsigned indices (all are >= 0): numba wraps a signed index that might
                # be negative, a compare and select on each read.
                r = s_rc[s]
                j = k0 + cidx[np.uint64(s_c[s])]
                j += (j + 1 < last) & (r >= x[np.uint64(j + 1)])
                while j + 1 < last and r >= x[np.uint64(j + 1)]:
                    j += 1
                vs, bs = v_r[s], b_r[s]
                state = -1
                for k in range(n_bias):
                    if abs(vs - bias_v[d, k]) <= bias_rtol * bias_v[d, k]:
                        state = k
                        break
                if state < 0:
                    s_f[s] |= _OOT | _ENV
                    continue
                if bs < b_lo or bs > b_hi:
                    s_f[s] |= _ENV
                j0 = s_j0[s]
                w4 = (s_w4[s, 0], s_w4[s, 1], s_w4[s, 2], s_w4[s, 3])
                ju, ju1, st = np.uint64(j), np.uint64(j + 1), np.uint64(state)
                h = x[ju1] - x[ju]
                h00, h10, h01, h11 = _hermite((r - x[ju]) / h, h)
                acc = 0.0
                for k in range(4):
                    jb = np.uint64(j0 + k)
                    acc += w4[k] * (h00 * p_w[ju, st, jb] + h10 * dp_w[ju, st, jb]
                                    + h01 * p_w[ju1, st, jb] + h11 * dp_w[ju1, st, jb])
                s_acc[s] = acc
            n_slow = 0
            for s in range(n_samp):
                y = tb_r[s] * q[_R_INV_T0] - 1.0
                kb = q[_R_K_T0_N] * _series(y, a)
                f, inside = s_f[s], s_in[s] != 0
                p = s_acc[s] + q[_R_K_T0_N] - kb
                out_p[row, s] = p if inside & ((f & _UNUSABLE) == 0) else math.nan
                out_f[row, s] = f
                slow = inside & ~(abs(y) <= SERIES_LIMIT)
                marks[s] = slow
                n_slow += slow
            if n_slow:
                for s in range(n_samp):
                    if marks[s] and (s_f[s] & _UNUSABLE) == 0:
                        kb = _bath(tb_r[s], ltb_r[s], q[_R_INV_T0], q[_R_K_T0_N], q[_R_K], q[_R_N], a)
                        out_p[row, s] = s_acc[s] + q[_R_K_T0_N] - kb

    def _signatures(*inner):
        """The signatures of a kernel: counts int32 or float64, then ``inner`` (numba types).

        Every input read-only and C-contiguous (the wrappers make them so;
        writable arrays pass as read-only), outputs writable. Compiled once,
        before the first conversion (:func:`compile_kernels`), and then no
        other: numba would otherwise compile a new specialisation (seconds)
        for each new combination of layouts and read-only flags, the first
        time a live stream's chunk happened to bring one.
        """
        from numba import types as t

        def c(dtype, ndim, readonly=True):
            return t.Array(dtype, ndim, "C", readonly=readonly)

        f8 = t.float64
        env = (c(f8, 2), c(f8, 2), c(f8, 2), c(f8, 2), c(t.uint16, 2), c(t.int64, 1), c(f8, 2), c(f8, 1))
        out = (c(f8, 2, False), c(t.uint16, 2, False))
        return [t.void(c(k, 2), c(k, 2), *env, *(c(*a) if isinstance(a, tuple) else a for a in inner), *out)
                for k in (t.int32, f8)]

    def _kernel_signatures(kind):
        from numba import types as t

        f8, i4 = t.float64, t.int32
        if kind == "table":
            return _table_kernel, _signatures((f8, 1), (i4, 1), (f8, 2), (f8, 2))
        return _grid_kernel, _signatures((f8, 1), (i4, 1), (f8, 3), (f8, 3), (f8, 2), (f8, 1), (f8, 1), f8)

    _compiled = set()

    def compile_kernels(kinds=("table", "grid")) -> None:
        """Compile (or load from numba's cache) the signatures of the given kinds' kernels, once per
        process; a conversion compiles its own kind's (cold, about 6 s of CPU for "table", 4 for
        "grid"; loaded from the cache, a fraction of a second)."""
        for kind in kinds:
            if kind not in _compiled:
                kernel, sigs = _kernel_signatures(kind)
                for sig in sigs:
                    kernel.compile(sig)
                kernel.disable_compile()
                _compiled.add(kind)

    def _c(*arrays):
        return [np.ascontiguousarray(x) for x in arrays]

    def _env(tb, ltb, b, v, hk):
        return [compact(a) for a in (tb, ltb, b, v, hk)]

    _NO_LOW = np.empty((0, LOW_COLS))

    def table_numba(ci_, cq_, tb, ltb, b, v, hk, rows, phys, rec, dom, ko, x, co, cidx, cpo, coef, out_p, out_f,
                    low=None):
        """Structured-table conversion (same contract as :func:`table_numpy`; ``rec``: :func:`row_constants`).

        ``phys``, ``ko``, ``co`` and ``cpo`` are in ``rec`` and not read again. ``low`` (n_bank,
        ``LOW_COLS``), optional: LOW_RESPONSIVITY flagged too (``_table_kernel``).
        """
        compile_kernels(("table",))
        low = _NO_LOW if low is None else low
        _table_kernel(*_c(ci_, cq_), *_env(tb, ltb, b, v, hk), *_c(rows, rec, dom, x, cidx, coef, low), out_p, out_f)

    def grid_numba(ci_, cq_, tb, ltb, b, v, hk, rows, phys, rec, dom, ko, x, co, cidx, cpo,
                   p_w, dp_w, bias_v, b_nodes, t_ref, bias_rtol, out_p, out_f):
        """Grid-table conversion (same contract as :func:`grid_numpy`; ``rec``: :func:`row_constants`)."""
        compile_kernels(("grid",))
        _grid_kernel(*_c(ci_, cq_), *_env(tb, ltb, b, v, hk), *_c(rows, rec, dom, x, cidx, p_w, dp_w, bias_v, b_nodes,
                                                                  t_ref), float(bias_rtol), out_p, out_f)
else:  # pragma: no cover - exercised only without numba
    table_numba = grid_numba = None

    def compile_kernels(kinds=("table", "grid")) -> None:
        """Nothing to compile without numba."""
