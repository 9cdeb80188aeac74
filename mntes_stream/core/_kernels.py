"""Table conversion kernels: compiled (numba, one core, no GIL) and numpy twins.

Both backends implement the same arithmetic and flag rules as
``core.convert`` (documented there); the tests run both against the exact
inverse. The compiled kernel does one pass over the samples with no
transcendental call per sample in normal operation: ``K T^n`` comes from
the table and a short binomial series (see ``core.tables``), and so does
``K T_bath^n`` around each detector's nominal bath (within 5%; beyond, the
exact power). It runs far above numpy's many-temporaries speed; see
``benchmarks/README.md``.

Per-detector scalars ``phys`` (n_bank, 21): gain re/im, pickup re/im, z re/im,
K, n, c1, c2, gamma, nominal bias, R at |z| and the saturation cap, nominal
bath, R at the bottom, the phase-residual limit (A), R at the top, and the
noise margins (Ohm V) at the top, at |z| and at the bottom; see
``core.model.FlagThresholds``.
``dom``: bath temperature lo/hi, field lo/hi, bias fraction lo/hi.
Per-detector constants of the compiled kernel ``pre`` (n_bank, 10), from
:func:`row_constants`: the binomials ``C(n, 1..8)``, ``1 / T0`` and ``K T0^n``
with ``T0`` the bath the table refers to; computed once per converter, not
once per row of every call (a row of a 20-sample chunk paid a ``pow`` and
seven divisions for them).
"""

from __future__ import annotations

import math

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core import model

__all__ = ["table_numba", "grid_numba", "table_numpy", "grid_numpy", "front_numpy", "lookup_numpy",
           "row_constants", "compile_kernels"]

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


def row_constants(phys, t0_k):
    """The compiled kernel's per-detector constants ``pre`` (n_det, 10), C-contiguous float64.

    Parameters
    ----------
    phys : ndarray, shape (n_det, 21)
        The kernels' per-detector scalars (column 6 K, column 7 n).
    t0_k : ndarray, shape (n_det,)
        The bath temperature the detector's table refers to (nominal bath for
        "table", ``t_ref_k`` for "grid").
    """
    phys = np.asarray(phys, dtype=np.float64)
    t0 = np.asarray(t0_k, dtype=np.float64)
    k, n = phys[:, 6], phys[:, 7]
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        cols = [*binomials(n), 1.0 / t0, k * t0**n]
    return np.ascontiguousarray(np.stack(cols, axis=1)) if len(t0) else np.empty((0, 10))


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

try:
    import numba
except ImportError:  # the numpy twins above still work
    numba = None

if numba is not None:
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")
    # Helpers are inlined in numba IR: a real call would incref/decref every
    # array argument (atomic operations) per sample and cost ~6x in speed.
    _inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")

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
    def _det(phys, d, dom):
        v_nom = phys[d, 11]
        return (phys[d, 0], phys[d, 1], phys[d, 2], phys[d, 3], phys[d, 4], dom[4] * v_nom,
                phys[d, 12], phys[d, 13], dom[5] * v_nom, phys[d, 5], phys[d, 15], phys[d, 16] * SQRT2,
                phys[d, 17], phys[d, 18], phys[d, 19], phys[d, 20])

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

    @_jit
    def _kernel(ci_, cq_, tb, ltb, b, v, hk, rows, phys, pre, dom, ko, x, co, cidx, cpo,
                grid, coef, p_w, dp_w, bias_v, b_nodes, t_ref, bias_rtol, out_p, out_f):
        """Both table kinds in one pass over (n_det, n_samp) samples (``grid`` picks the kind).

        Writes ``out_p`` (float64, NaN where unusable) and ``out_f`` (uint16).
        One function rather than a shared helper: array arguments to a helper
        leave per-sample reference-count calls in the loop (measured ~3x slower).
        """
        n_rows, n_samp = out_p.shape
        dm = _dom(dom)
        nb = b_nodes.size
        n_bias = bias_v.shape[1]
        inv_db = 1.0 / (b_nodes[1] - b_nodes[0]) if grid else 0.0
        for row in range(n_rows):
            d = rows[row]
            if d < 0:
                for s in range(n_samp):
                    out_f[row, s] = hk[row, s] | _UNKNOWN
                    out_p[row, s] = math.nan
                continue
            det = _det(phys, d, dom)
            k0, last, c0 = ko[d], ko[d + 1] - 1, co[d]
            x_lo, x_hi, n_cells, cells_per_ohm = x[k0], x[last], co[d + 1] - c0, cpo[d]
            k, n, c1, c2, gamma = phys[d, 6], phys[d, 7], phys[d, 8], phys[d, 9], phys[d, 10]
            zr, zi = phys[d, 4], phys[d, 5]
            a = (pre[d, 0], pre[d, 1], pre[d, 2], pre[d, 3], pre[d, 4], pre[d, 5], pre[d, 6], pre[d, 7])
            inv_t0, k_t0_n = pre[d, 8], pre[d, 9]  # of the table's bath (row_constants)
            for s in range(n_samp):
                bs = b[row, s]
                vs = v[row, s]
                f, r, i2, ok = _front(float(ci_[row, s]), float(cq_[row, s]), tb[row, s], bs, vs,
                                        int(hk[row, s]), det, dm)
                p = math.nan
                if ok:
                    j = -1
                    if x_lo <= r <= x_hi:
                        # O(1) lookup cell; a cell holds at most one knot (lookup_cells),
                        # so one branch-free step; the loop only guards rounding at cell edges.
                        cell = min(int((r - x_lo) * cells_per_ohm), n_cells - 1)
                        j = k0 + cidx[c0 + cell]
                        j += (j + 1 < last) & (r >= x[j + 1])
                        while j + 1 < last and r >= x[j + 1]:
                            j += 1
                    kb = _bath(tb[row, s], ltb[row, s], inv_t0, k_t0_n, k, n, a)
                    if j < 0:
                        f |= _OOT
                    elif not grid:
                        u = r - x[j]
                        w = coef[j, 0] + u * (coef[j, 1] + u * (coef[j, 2] + u * coef[j, 3]))
                        inv_ts = coef[j, 4] + u * (coef[j, 5] + u * (coef[j, 6] + u * coef[j, 7]))
                        delta = c1 * bs + c2 * bs * bs - (gamma * math.sqrt(i2) if gamma != 0.0 else 0.0)
                        xx = delta * inv_ts
                        if abs(xx) <= SERIES_LIMIT:
                            kt = w * _series(xx, a)
                        else:
                            t = 1.0 / inv_ts + delta
                            kt = k * math.exp(n * math.log(t)) if t > 0.0 else 0.0
                        p = kt - kb - vs * vs * r / ((r + zr) ** 2 + zi * zi)
                    else:
                        state = -1
                        for q in range(n_bias):
                            if abs(vs - bias_v[d, q]) <= bias_rtol * bias_v[d, q]:
                                state = q
                                break
                        if state < 0:
                            f |= _OOT | _ENV
                        else:
                            if bs < b_nodes[0] or bs > b_nodes[nb - 1]:
                                f |= _ENV
                            tpos = (bs - b_nodes[0]) * inv_db
                            j0 = min(max(int(math.floor(tpos)) - 1, 0), nb - 4)
                            w4 = _lagrange(tpos - j0)
                            h = x[j + 1] - x[j]
                            h00, h10, h01, h11 = _hermite((r - x[j]) / h, h)
                            acc = 0.0
                            for q in range(4):
                                jb = j0 + q
                                acc += w4[q] * (h00 * p_w[j, state, jb] + h10 * dp_w[j, state, jb]
                                                + h01 * p_w[j + 1, state, jb] + h11 * dp_w[j + 1, state, jb])
                            p = acc + k_t0_n - kb
                if f & _UNUSABLE:
                    p = math.nan
                out_p[row, s] = p
                out_f[row, s] = f

    _NO_COEF = np.zeros((0, 8))
    _NO_GRID = np.zeros((0, 1, 1))

    def _signatures():
        """The kernel's only signatures: counts int32 or float64; read-only inputs.

        Counts, tables and outputs C-contiguous (the wrappers make them so; unit
        strides keep the sample loop ~5% faster than strided access), the
        per-sample environment of any layout (it is usually a broadcast view).
        Compiled once, before the first conversion (:func:`compile_kernels`), and
        then no other: numba would otherwise compile a new specialisation
        (seconds) for each new combination of layouts and read-only flags, the
        first time a live stream's chunk happened to bring one.
        """
        from numba import types as t

        def c(dtype, ndim, readonly=True):
            return t.Array(dtype, ndim, "C", readonly=readonly)

        def a(dtype, ndim):
            return t.Array(dtype, ndim, "A", readonly=True)

        f8 = t.float64
        rest = (a(f8, 2), a(f8, 2), a(f8, 2), a(f8, 2), a(t.uint16, 2), c(t.int64, 1), c(f8, 2), c(f8, 2),
                c(f8, 1), c(t.int64, 1), c(f8, 1), c(t.int64, 1), c(t.int32, 1), c(f8, 1), t.boolean, c(f8, 2),
                c(f8, 3), c(f8, 3), c(f8, 2), c(f8, 1), c(f8, 1), f8, c(f8, 2, False), c(t.uint16, 2, False))
        return [t.void(c(k, 2), c(k, 2), *rest) for k in (t.int32, f8)]

    def _c(*arrays):
        return [np.ascontiguousarray(x) for x in arrays]

    _compiled = []

    def compile_kernels() -> None:
        """Compile (or load from numba's cache) the kernel's signatures, once per process."""
        if not _compiled:
            for sig in _signatures():
                _kernel.compile(sig)
            _kernel.disable_compile()
            _compiled.append(True)

    def table_numba(ci_, cq_, tb, ltb, b, v, hk, rows, phys, pre, dom, ko, x, co, cidx, cpo, coef, out_p, out_f):
        """Structured-table conversion (same contract as :func:`table_numpy`; ``pre``: :func:`row_constants`)."""
        compile_kernels()
        _kernel(*_c(ci_, cq_), tb, ltb, b, v, hk, *_c(rows, phys, pre, dom, ko, x, co, cidx, cpo), False,
                np.ascontiguousarray(coef), _NO_GRID, _NO_GRID, np.ones((1, 1)), np.zeros(4), np.ones(1), 0.0,
                out_p, out_f)

    def grid_numba(ci_, cq_, tb, ltb, b, v, hk, rows, phys, pre, dom, ko, x, co, cidx, cpo,
                   p_w, dp_w, bias_v, b_nodes, t_ref, bias_rtol, out_p, out_f):
        """Grid-table conversion (same contract as :func:`grid_numpy`; ``pre``: :func:`row_constants`)."""
        compile_kernels()
        _kernel(*_c(ci_, cq_), tb, ltb, b, v, hk, *_c(rows, phys, pre, dom, ko, x, co, cidx, cpo), True, _NO_COEF,
                *_c(p_w, dp_w, bias_v, b_nodes, t_ref), float(bias_rtol), out_p, out_f)
else:  # pragma: no cover - exercised only without numba
    table_numba = grid_numba = None

    def compile_kernels() -> None:
        """Nothing to compile without numba."""
