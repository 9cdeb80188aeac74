"""Compiled sigma_P and LOW_RESPONSIVITY from a ``"table"`` bank (see ``core.uncertainty``).

One pass over (n_det, n_samp) samples that the converter has already
flagged: only usable samples are read. Per sample: R from the counts, the
table's interval (the bank's O(1) lookup cells), ``W``, ``W'`` and ``U``
from the interval's cubics, ``(1 + delta U)^(n-1)`` (a binomial series near
1, the exact power beyond), then ``|grad_i P|``. No transcendental call in
normal operation. Its own kernel rather than a branch of the conversion
kernel: the conversion does not pay for it unless asked.

Per-detector record ``rec`` (n_bank, 27), :func:`row_constants`. A row's
front end and sigma_P run as vector lanes (branch-free, ``noalias``
pointers, as the conversion kernel does), its table lookup between them
sample by sample; the rare sample needing a branch is done again by the
scalar reference.
"""

from __future__ import annotations

import math

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core._kernels import binomials
from mntes_stream.core._numba import numba  # None: the model route in core.uncertainty still works

SQRT2 = math.sqrt(2.0)
SERIES_LIMIT = 0.05
_UNUSABLE = int(fl.UNUSABLE)
_LOW = int(fl.LOW_RESPONSIVITY)


def row_constants(phys, noise, bank_arrays) -> np.ndarray:
    """The kernel's per-detector record ``rec`` (n_det, 27), C-contiguous float64.

    Columns: gain re/im, pickup re/im; the table's first knot, last knot, first
    lookup cell, number of cells, cells per ohm, R range lo/hi; n, c1, c2,
    gamma, Re z, Im z; sigma_i and the LOW_RESPONSIVITY tolerance (W);
    ``C(n - 1, 1..8)``.
    """
    phys = np.asarray(phys, dtype=np.float64)
    ko, x, co, cpo = (bank_arrays[k] for k in ("knot_offset", "r_knot_ohm", "cell_offset", "cell_per_ohm"))
    n = phys[:, 7]
    k0 = ko[:-1].astype(float)
    last = (ko[1:] - 1).astype(float)
    cols = [phys[:, 0], phys[:, 1], phys[:, 2], phys[:, 3], k0, last, co[:-1].astype(float),
            (co[1:] - co[:-1]).astype(float), np.asarray(cpo, float), x[ko[:-1]], x[ko[1:] - 1], n, phys[:, 8],
            phys[:, 9], phys[:, 10], phys[:, 4], phys[:, 5], np.asarray(noise.sigma_i_a, float),
            np.asarray(noise.tolerance_w, float), *binomials(n - 1.0)]
    return np.ascontiguousarray(np.stack(cols, axis=1)) if len(n) else np.empty((0, 27))


def available() -> bool:
    """True when the compiled kernel can run."""
    return numba is not None


if numba is not None:
    from numba.core import compiler as _numba_compiler

    _jit = numba.njit(cache=True, nogil=True, error_model="numpy")
    _inline = numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")

    class _NoAliasCompiler(_numba_compiler.Compiler):
        """numba's compiler with every pointer argument ``noalias`` (C's ``restrict``): without it LLVM
        does not vectorise a loop reading the tables at computed indices (an output might alias them).
        The kernel's outputs never alias an input (the caller allocates them)."""

        def __init__(self, typingctx, targetctx, library, args, return_type, flags, locals):
            flags.noalias = True
            super().__init__(typingctx, targetctx, library, args, return_type, flags, locals)

    _jit_vector = numba.njit(cache=True, nogil=True, error_model="numpy", pipeline_class=_NoAliasCompiler)

    from mntes_stream.core._kernels import sigma_gradient as _gradient  # the conversion's LOW_RESPONSIVITY's too

    @_inline
    def _series(xx, a0, a1, a2, a3, a4, a5, a6, a7):
        """``(1 + xx)^(n-1)`` by the binomial series (Estrin's scheme)."""
        x2 = xx * xx
        x4 = x2 * x2
        return 1.0 + xx * (((a0 + a1 * xx) + x2 * (a2 + a3 * xx)) + x4 * ((a4 + a5 * xx) + x2 * (a6 + a7 * xx)))

    @_inline
    def _sample(xi, xq, bs, vs, q, x, cidx, coef):
        """One usable sample with every branch (the reference; the vector lanes equal it where no branch
        is taken): sigma_P, NaN outside the table."""
        g_re, g_im, m_re, m_im, k0, last, c0, n_cells, cpo, x_lo, x_hi = (q[0], q[1], q[2], q[3], q[4], q[5], q[6],
                                                                          q[7], q[8], q[9], q[10])
        n, c1, c2, gamma, zr, zi, sig = q[11], q[12], q[13], q[14], q[15], q[16], q[17]
        ire = g_re * xi - g_im * xq - m_re * bs
        iim = g_re * xq + g_im * xi - m_im * bs
        m2 = ire * ire + iim * iim
        r = SQRT2 * vs * ire / m2 - zr
        if not (x_lo <= r <= x_hi):
            return math.nan
        cell = min(int((r - x_lo) * cpo), n_cells - 1)
        j = k0 + cidx[c0 + cell]
        while j + 1 < last and r >= x[j + 1]:
            j += 1
        u = r - x[j]
        w = coef[j, 0] + u * (coef[j, 1] + u * (coef[j, 2] + u * coef[j, 3]))
        w1 = coef[j, 1] + u * (2.0 * coef[j, 2] + 3.0 * u * coef[j, 3])
        uu = coef[j, 4] + u * (coef[j, 5] + u * (coef[j, 6] + u * coef[j, 7]))
        xx = (c1 * bs + c2 * bs * bs - gamma * math.sqrt(m2)) * uu
        if abs(xx) <= SERIES_LIMIT:
            fp = _series(xx, q[19], q[20], q[21], q[22], q[23], q[24], q[25], q[26])
        else:
            fp = math.exp((n - 1.0) * math.log(1.0 + xx)) if xx > -1.0 else 0.0
        return sig * _gradient(w, w1, uu, fp, r, m2, vs, n, gamma, zr, zi)

    @_jit_vector
    def _kernel(ci_, cq_, b, v, rows, rec, x, cidx, coef, out_s, out_f):
        """sigma_P into ``out_s`` and LOW_RESPONSIVITY into ``out_f`` (the block's flags), vector lanes.

        Branch-free over every sample of a row (unusable ones computed on a safe R and discarded), in
        three passes: front end (vector), table lookup (scalar), sigma_P (vector). A lane that needs a
        branch (a second lookup step, the exact power beyond the series) is marked and done again by
        :func:`_sample`.
        """
        n_rows, n_samp = out_s.shape
        s_b, s_v = np.empty(n_samp), np.empty(n_samp)
        marks = np.zeros(n_samp, dtype=np.uint8)
        # The front end's and the lookup's results per sample, for the next pass.
        s_c, s_in = np.empty(n_samp, dtype=np.int64), np.empty(n_samp, dtype=np.uint8)
        s_rc, s_m2, s_w, s_w1, s_uu = np.empty(n_samp), np.empty(n_samp), np.empty(n_samp), np.empty(n_samp), \
            np.empty(n_samp)
        for row in range(n_rows):
            d = rows[row]
            if d < 0:
                for s in range(n_samp):
                    out_s[row, s] = math.nan
                continue
            for s in range(n_samp):  # unit stride for the lanes (the environment is often a broadcast view)
                s_b[s] = b[row, s]
                s_v[s] = v[row, s]
            q = (rec[d, 0], rec[d, 1], rec[d, 2], rec[d, 3], int(rec[d, 4]), int(rec[d, 5]), int(rec[d, 6]),
                 int(rec[d, 7]), rec[d, 8], rec[d, 9], rec[d, 10], rec[d, 11], rec[d, 12], rec[d, 13], rec[d, 14],
                 rec[d, 15], rec[d, 16], rec[d, 17], rec[d, 18], rec[d, 19], rec[d, 20], rec[d, 21], rec[d, 22],
                 rec[d, 23], rec[d, 24], rec[d, 25], rec[d, 26])
            g_re, g_im, m_re, m_im, k0, last, c0, n_cells, cpo, x_lo, x_hi = (q[0], q[1], q[2], q[3], q[4], q[5],
                                                                              q[6], q[7], q[8], q[9], q[10])
            n, c1, c2, gamma, zr, zi, sig, tol = q[11], q[12], q[13], q[14], q[15], q[16], q[17], q[18]
            n_slow = 0
            # Three passes over the row: the front end (vector), the table lookup (scalar), sigma_P
            # (vector). Vectorised, the lookup's reads are gathers, a dozen per lane group, which cost
            # more than the same reads done one by one (as in _kernels._table_kernel).
            for s in range(n_samp):
                bs, vs = s_b[s], s_v[s]
                xi = float(ci_[row, s])
                xq = float(cq_[row, s])
                ire = g_re * xi - g_im * xq - m_re * bs
                iim = g_re * xq + g_im * xi - m_im * bs
                m2 = ire * ire + iim * iim
                r = SQRT2 * vs * ire / m2 - zr
                inside = ((out_f[row, s] & _UNUSABLE) == 0) & (x_lo <= r) & (r <= x_hi)
                rc = r if inside else x_lo
                cell = int((rc - x_lo) * cpo)
                s_c[s] = c0 + (cell if cell < n_cells - 1 else n_cells - 1)
                s_rc[s], s_m2[s], s_in[s] = rc, (m2 if inside else 1.0), inside
            for s in range(n_samp):
                c = s_c[s]
                if c < 0:  # never (rc is in the table): an early exit keeps the compiler from gathering
                    break
                # One lookup step and whether it needed more. Unsigned indices (all are >= 0): numba
                # wraps a signed index that might be negative, a compare and select on each read.
                rc = s_rc[s]
                j = k0 + cidx[np.uint64(c)]
                j += (j + 1 < last) & (rc >= x[np.uint64(j + 1)])
                marks[s] = (j + 1 < last) & (rc >= x[np.uint64(j + 1)])
                ju = np.uint64(j)
                u = rc - x[ju]
                s_w[s] = coef[ju, 0] + u * (coef[ju, 1] + u * (coef[ju, 2] + u * coef[ju, 3]))
                s_w1[s] = coef[ju, 1] + u * (2.0 * coef[ju, 2] + 3.0 * u * coef[ju, 3])
                s_uu[s] = coef[ju, 4] + u * (coef[ju, 5] + u * (coef[ju, 6] + u * coef[ju, 7]))
            for s in range(n_samp):
                f = out_f[row, s]
                bs, vs, rc, m2c, uu, inside = s_b[s], s_v[s], s_rc[s], s_m2[s], s_uu[s], s_in[s] != 0
                xx = (c1 * bs + c2 * bs * bs - gamma * math.sqrt(m2c)) * uu
                fp = _series(xx, q[19], q[20], q[21], q[22], q[23], q[24], q[25], q[26])
                sp = sig * _gradient(s_w[s], s_w1[s], uu, fp, rc, m2c, vs, n, gamma, zr, zi)
                out_s[row, s] = sp if inside else math.nan
                out_f[row, s] = f | (_LOW * (inside & (sp > tol)))
                slow = inside & ((marks[s] != 0) | ~(abs(xx) <= SERIES_LIMIT))
                marks[s] = slow
                n_slow += slow
            if n_slow:
                for s in range(n_samp):
                    if marks[s]:
                        sp = _sample(float(ci_[row, s]), float(cq_[row, s]), s_b[s], s_v[s], q, x, cidx, coef)
                        out_s[row, s] = sp
                        f = out_f[row, s] & ~_LOW
                        out_f[row, s] = f | (_LOW if sp > tol else 0)

    def _signatures():
        from numba import types as t

        def c(dtype, ndim, readonly=True):
            return t.Array(dtype, ndim, "C", readonly=readonly)

        def a(dtype, ndim):
            return t.Array(dtype, ndim, "A", readonly=True)

        f8 = t.float64
        rest = (a(f8, 2), a(f8, 2), c(t.int64, 1), c(f8, 2), c(f8, 1), c(t.int32, 1), c(f8, 2),
                c(t.float32, 2, False), c(t.uint16, 2, False))
        return [t.void(c(k, 2), c(k, 2), *rest) for k in (t.int32, f8)]

    _compiled: list = []

    def compile_kernel() -> None:
        """Compile (or load from numba's cache) the kernel's two signatures, once per process."""
        if not _compiled:
            for sig in _signatures():
                _kernel.compile(sig)
            _kernel.disable_compile()
            _compiled.append(True)

    def run(ci_, cq_, b, v, rows, rec, x, cidx, coef, out_s, out_f) -> None:
        """Fill ``out_s`` (float32) and OR LOW_RESPONSIVITY into ``out_f`` (uint16, the block's flags);
        ``rec`` from :func:`row_constants`."""
        compile_kernel()
        c = np.ascontiguousarray
        _kernel(c(ci_), c(cq_), b, v, c(rows), c(rec), c(x), c(cidx), c(coef), out_s, out_f)
else:  # pragma: no cover - exercised only without numba
    def compile_kernel() -> None:
        """Nothing to compile without numba."""

    def run(*args) -> None:
        raise RuntimeError("numba is not installed")
