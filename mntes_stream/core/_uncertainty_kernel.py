"""Compiled sigma_P and LOW_RESPONSIVITY from a ``"table"`` bank (see ``core.uncertainty``).

One pass over (n_det, n_samp) samples that the converter has already
flagged: only usable samples are read. Per sample: R from the counts, the
table's interval (the bank's O(1) lookup cells), ``W``, ``W'`` and ``U``
from the interval's cubics, ``(1 + delta U)^(n-1)`` (a binomial series near
1, the exact power beyond), then ``|grad_i P|``. No transcendental call in
normal operation. Its own kernel rather than a branch of the conversion
kernel: the conversion does not pay for it unless asked.

Per-detector constants ``pre`` (n_bank, 17), :func:`row_constants`: K, n,
c1, c2, gamma, Re z, Im z, sigma_i, the LOW_RESPONSIVITY tolerance, and
``C(n - 1, 1..8)``.
"""

from __future__ import annotations

import math

import numpy as np

from mntes_stream.core import flags as fl

SQRT2 = math.sqrt(2.0)
SERIES_LIMIT = 0.05
_UNUSABLE = int(fl.UNUSABLE)
_LOW = int(fl.LOW_RESPONSIVITY)


def binomials(n):
    """``C(n, k)``, k = 1..8 (plain arithmetic: the compiled kernel uses this very function)."""
    a1 = n
    a2 = a1 * (n - 1.0) / 2.0
    a3 = a2 * (n - 2.0) / 3.0
    a4 = a3 * (n - 3.0) / 4.0
    a5 = a4 * (n - 4.0) / 5.0
    a6 = a5 * (n - 5.0) / 6.0
    a7 = a6 * (n - 6.0) / 7.0
    a8 = a7 * (n - 7.0) / 8.0
    return a1, a2, a3, a4, a5, a6, a7, a8


def row_constants(phys, noise) -> np.ndarray:
    """``pre`` (n_det, 17) from the converter's ``_phys`` and a ``NoiseModel``."""
    phys = np.asarray(phys, dtype=np.float64)
    n = phys[:, 7]
    cols = [phys[:, 6], n, phys[:, 8], phys[:, 9], phys[:, 10], phys[:, 4], phys[:, 5],
            np.asarray(noise.sigma_i_a, float), np.asarray(noise.tolerance_w, float), *binomials(n - 1.0)]
    return np.ascontiguousarray(np.stack(cols, axis=1)) if len(n) else np.empty((0, 17))


try:
    import numba
except ImportError:  # the model route in core.uncertainty still works
    numba = None


def available() -> bool:
    """True when the compiled kernel can run."""
    return numba is not None


if numba is not None:
    _jit = numba.njit(cache=True, nogil=True, error_model="numpy", fastmath={"contract", "arcp", "reassoc"})

    @_jit
    def _kernel(ci_, cq_, b, v, rows, phys, pre, ko, x, co, cidx, cpo, coef, out_s, out_f):
        n_rows, n_samp = out_s.shape
        for row in range(n_rows):
            d = rows[row]
            if d < 0:
                for s in range(n_samp):
                    out_s[row, s] = math.nan
                continue
            g_re, g_im, m_re, m_im = phys[d, 0], phys[d, 1], phys[d, 2], phys[d, 3]
            n, c1, c2, gamma, zr, zi = pre[d, 1], pre[d, 2], pre[d, 3], pre[d, 4], pre[d, 5], pre[d, 6]
            sig, tol = pre[d, 7], pre[d, 8]
            a0, a1, a2, a3, a4, a5, a6, a7 = (pre[d, 9], pre[d, 10], pre[d, 11], pre[d, 12], pre[d, 13],
                                              pre[d, 14], pre[d, 15], pre[d, 16])
            z2 = zr * zr + zi * zi
            k0, last, c0 = ko[d], ko[d + 1] - 1, co[d]
            x_lo, x_hi, n_cells, cells_per_ohm = x[k0], x[last], co[d + 1] - c0, cpo[d]
            for s in range(n_samp):
                f = out_f[row, s]
                if f & _UNUSABLE:
                    out_s[row, s] = math.nan
                    continue
                xi = float(ci_[row, s])
                xq = float(cq_[row, s])
                bs = b[row, s]
                vs = v[row, s]
                ire = g_re * xi - g_im * xq - m_re * bs
                iim = g_re * xq + g_im * xi - m_im * bs
                m2 = ire * ire + iim * iim
                sv_m2 = SQRT2 * vs / m2  # |grad_i R|: one division for R and the gradient
                r = sv_m2 * ire - zr
                if not (x_lo <= r <= x_hi):
                    out_s[row, s] = math.nan
                    continue
                cell = min(int((r - x_lo) * cells_per_ohm), n_cells - 1)
                j = k0 + cidx[c0 + cell]
                j += (j + 1 < last) & (r >= x[j + 1])
                while j + 1 < last and r >= x[j + 1]:
                    j += 1
                u = r - x[j]
                w = coef[j, 0] + u * (coef[j, 1] + u * (coef[j, 2] + u * coef[j, 3]))
                w1 = coef[j, 1] + u * (2.0 * coef[j, 2] + 3.0 * u * coef[j, 3])
                uu = coef[j, 4] + u * (coef[j, 5] + u * (coef[j, 6] + u * coef[j, 7]))
                i_abs = math.sqrt(m2) if gamma != 0.0 else 0.0
                xx = (c1 * bs + c2 * bs * bs - gamma * i_abs) * uu
                if xx == 0.0:
                    fp = 1.0
                elif abs(xx) <= SERIES_LIMIT:
                    x2 = xx * xx
                    x4 = x2 * x2
                    fp = 1.0 + xx * (((a0 + a1 * xx) + x2 * (a2 + a3 * xx))
                                     + x4 * ((a4 + a5 * xx) + x2 * (a6 + a7 * xx)))
                else:
                    fp = math.exp((n - 1.0) * math.log(1.0 + xx)) if xx > -1.0 else 0.0
                rz = r + zr
                mz2 = rz * rz + zi * zi
                # dP/dR at fixed |i|: K n T^(n-1) T_s' = W' (T / T_s)^(n-1), less the Joule slope.
                a = w1 * fp - vs * vs * (z2 - r * r) / (mz2 * mz2)
                gr = a * sv_m2
                if gamma != 0.0:
                    bb = -gamma * n * w * uu * fp
                    g2 = gr * gr + bb * bb - 2.0 * a * bb * rz / i_abs
                else:
                    g2 = gr * gr
                sp = sig * math.sqrt(g2 if g2 > 0.0 else 0.0)
                out_s[row, s] = sp
                # Unconditional store: a conditional one cost 40% of the kernel (measured).
                out_f[row, s] = f | (_LOW if sp > tol else 0)

    def _signatures():
        from numba import types as t

        def c(dtype, ndim, readonly=True):
            return t.Array(dtype, ndim, "C", readonly=readonly)

        def a(dtype, ndim):
            return t.Array(dtype, ndim, "A", readonly=True)

        f8 = t.float64
        rest = (a(f8, 2), a(f8, 2), c(t.int64, 1), c(f8, 2), c(f8, 2), c(t.int64, 1), c(f8, 1), c(t.int64, 1),
                c(t.int32, 1), c(f8, 1), c(f8, 2), c(t.float32, 2, False), c(t.uint16, 2, False))
        return [t.void(c(k, 2), c(k, 2), *rest) for k in (t.int32, f8)]

    _compiled: list = []

    def compile_kernel() -> None:
        """Compile (or load from numba's cache) the kernel's two signatures, once per process."""
        if not _compiled:
            for sig in _signatures():
                _kernel.compile(sig)
            _kernel.disable_compile()
            _compiled.append(True)

    def run(ci_, cq_, b, v, rows, phys, pre, ko, x, co, cidx, cpo, coef, out_s, out_f) -> None:
        """Fill ``out_s`` (float32) and OR LOW_RESPONSIVITY into ``out_f`` (uint16, the block's flags)."""
        compile_kernel()
        c = np.ascontiguousarray
        _kernel(c(ci_), c(cq_), b, v, c(rows), c(phys), c(pre), c(ko), c(x), c(co), c(cidx), c(cpo), c(coef),
                out_s, out_f)
else:  # pragma: no cover - exercised only without numba
    def compile_kernel() -> None:
        """Nothing to compile without numba."""

    def run(*args) -> None:
        raise RuntimeError("numba is not installed")
