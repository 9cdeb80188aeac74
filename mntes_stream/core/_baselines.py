"""The baselines' kernel (``linear``, ``electrical``): one compiled pass, flags and power.

Same flag rules as :func:`core._kernels.front_numpy` (documented in
``core.convert``) plus ``OUT_OF_TABLE`` outside each detector's linearisation
R range, and the same arithmetic as the numpy expressions of
``LinearConverter`` and ``ElectricalConverter``, operation for operation:
numpy's complex multiply fuses one product and one sum (FMA) and divides
by Smith's method, and so does this kernel (``_fma`` below), so the values are
the numpy expressions' bit for bit on a machine with FMA. It runs without
temporaries, and its sample loop vectorises (no branches, unit strides): the
numpy route made some thirty full-size arrays per block (35 M samples/s on the
bench's 512 x 10,000 block where ``a * x + b`` does 780; this kernel 410).

Per-detector constants ``cst`` (n_bank, ``N_CONST``), from :func:`constants`.
"""

from __future__ import annotations

import math

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.core import model
from mntes_stream.core._numba import numba as _numba  # None: the converters' numpy route still works

__all__ = ["N_CONST", "constants", "linear_power", "electrical_power", "baseline_numba", "available"]

SQRT2 = model.SQRT2
RAIL = float(2**31 - 1)
LINEAR, ELECTRICAL = 0, 1
# Columns of ``cst``.
_G_RE, _G_IM, _M_RE, _M_IM, _Z_RE, _Z_IM = range(6)
_R_CAP, _R_TOP, _K_TOP, _R_Z, _K_Z, _R_BOT, _K_BOT, _PHASE_LIM, _V_LO, _V_HI, _R_LO, _R_HI = range(6, 18)
_A, _B, _C, _D, _E, _SMITH_RE = range(18, 24)
N_CONST = 24


def constants(phys: np.ndarray, dom: np.ndarray, r_range: np.ndarray, power: np.ndarray) -> np.ndarray:
    """Per-detector constants of the kernel, shape (n_bank, ``N_CONST``).

    Parameters
    ----------
    phys : (n_bank, 21) the converters' per-detector scalars (``core.convert._phys``)
    dom : (6,) bath lo/hi, field lo/hi, bias fraction lo/hi
    r_range : (n_bank, 2) the linearisation's R range (Ohm)
    power : (n_bank, 6) the kind's own: :func:`linear_power` or :func:`electrical_power`
    """
    out = np.empty((phys.shape[0], N_CONST))
    out[:, :6] = phys[:, :6]
    out[:, _R_CAP], out[:, _R_TOP], out[:, _K_TOP] = phys[:, 13], phys[:, 17], phys[:, 18]
    out[:, _R_Z], out[:, _K_Z], out[:, _R_BOT], out[:, _K_BOT] = phys[:, 12], phys[:, 19], phys[:, 15], phys[:, 20]
    out[:, _PHASE_LIM] = phys[:, 16]
    out[:, _V_LO], out[:, _V_HI] = dom[4] * phys[:, 11], dom[5] * phys[:, 11]
    out[:, _R_LO], out[:, _R_HI] = r_range[:, 0], r_range[:, 1]
    out[:, _A:] = power
    return out


def linear_power(p0_w: np.ndarray, i0_a: np.ndarray, s_a_per_w: np.ndarray) -> np.ndarray:
    """``linear``'s constants (n, 6): P0, i0 re/im, and Smith's ratio, scale and branch for
    dividing by S (numpy's complex division), so the kernel divides exactly as numpy does."""
    sr, si = s_a_per_w.real, s_a_per_w.imag
    real_major = np.abs(sr) >= np.abs(si)
    with np.errstate(divide="ignore", invalid="ignore"):
        rat = np.where(real_major, si / sr, sr / si)
        scl = 1.0 / np.where(real_major, sr + si * rat, si + sr * rat)
    return np.stack([p0_w, i0_a.real, i0_a.imag, rat, scl, real_major.astype(float)], axis=1)


def electrical_power(p_total_w: np.ndarray) -> np.ndarray:
    """``electrical``'s constants (n, 6): the nominal total power, then unused columns."""
    out = np.zeros((p_total_w.size, 6))
    out[:, 0] = p_total_w
    return out


def available() -> bool:
    """True when numba is installed (the numpy route is used otherwise)."""
    return _numba is not None


if _numba is not None:
    from llvmlite import ir as _ir
    from numba.core import types as _t
    from numba.extending import intrinsic as _intrinsic

    @_intrinsic
    def _fma(typingctx, a, b, c):
        """``a * b + c`` rounded once, as numpy's complex multiply computes its parts."""
        sig = _t.float64(_t.float64, _t.float64, _t.float64)

        def codegen(context, builder, signature, args):
            f8 = _ir.DoubleType()
            fn = builder.module.declare_intrinsic("llvm.fma", [f8], _ir.FunctionType(f8, [f8, f8, f8]))
            return builder.call(fn, args)

        return sig, codegen

    _INVALID, _SAT, _SC, _LAT = int(fl.INVALID_INPUT), int(fl.SATURATED), int(fl.SUPERCONDUCTING), int(fl.LATCHED)
    _PHASE, _OOT, _ENV, _UNKNOWN = int(fl.PHASE_RESIDUAL), int(fl.OUT_OF_TABLE), int(fl.ENV_OUT_OF_RANGE), int(
        fl.UNKNOWN_CHANNEL)
    _HK_MISSING, _UNUSABLE = int(fl.HK_MISSING), int(fl.UNUSABLE)

    _inline = _numba.njit(cache=True, nogil=True, error_model="numpy", inline="always")

    @_inline
    def _front(xi, xq, tbs, bs, vs, h, c):
        """One sample's flags and measured current, without branches (so the loop vectorises).

        ``c``: the row's constants as scalars (see ``_kernel``); bitwise ``&``/``|`` on
        booleans rather than ``and``/``or``, which would branch.
        """
        (g0, g1, m0, m1, zr, zi, r_cap, r_top, k_top, r_z, k_z, r_bot, k_bot, plim2,
         v_lo, v_hi, r_lo, r_hi, tb_lo, tb_hi, b_lo, b_hi) = c
        counts_ok = (abs(xi) < RAIL) & (abs(xq) < RAIL)
        env_ok = (tbs > 0.0) & (abs(bs) < math.inf) & (vs > 0.0) & (vs < math.inf)
        # The measured current (numpy's complex product: one FMA per part), then the pickup off.
        i_re = _fma(g0, xi, -(g1 * xq))
        i_im = _fma(g0, xq, g1 * xi)
        ire = g0 * xi - g1 * xq - m0 * bs
        iim = g0 * xq + g1 * xi - m1 * bs
        m2 = ire * ire + iim * iim
        m2_ok = m2 > 0.0
        valid = counts_ok & env_ok & m2_ok
        bad = ~counts_ok | (counts_ok & env_ok & ~m2_ok) | (~env_ok & ((h & _HK_MISSING) == 0))
        r = SQRT2 * vs * ire / m2 - zr
        sat = valid & ((r >= r_cap) | ((r - r_top) * vs >= -k_top))
        low = valid & ~sat & ((r - r_z) * vs <= k_z)
        lat = low & ~((r - r_bot) * vs <= k_bot)
        phase = valid & (abs(SQRT2 * vs * iim + zi * m2) > plim2 * vs)
        env_out = env_ok & ~((tb_lo <= tbs) & (tbs <= tb_hi) & (b_lo <= bs) & (bs <= b_hi)
                             & (v_lo <= vs) & (vs <= v_hi))
        oot = valid & ~sat & ~low & ~((r >= r_lo) & (r <= r_hi))
        f = (h | (_INVALID * bad) | (_SAT * sat) | (_SC * low) | (_LAT * lat) | (_PHASE * phase)
             | (_ENV * env_out) | (_OOT * oot))
        return f, i_re, i_im

    @_inline
    def row_view(a, row, scratch):
        """Row ``row`` of a compact environment array (see :func:`compact`), unit stride (``_kernels`` too)."""
        r = a[row if a.shape[0] > 1 else 0]
        if a.shape[1] == scratch.size:
            return r
        scratch[:] = r[0]
        return scratch

    @_numba.njit(cache=True, nogil=True, error_model="numpy")
    def _kernel(ci_, cq_, tb, b, v, hk, rows, cst, dom, kind, out_p, out_f):
        n_rows, n_samp = out_p.shape
        # Rows of unit stride whatever the environment's layout: a value per row is spread
        # over a scratch row once, so the sample loop reads only contiguous memory (and vectorises).
        s_tb, s_b, s_v = np.empty(n_samp), np.empty(n_samp), np.empty(n_samp)
        s_hk = np.empty(n_samp, dtype=np.uint16)
        inv_s2 = 1.0 / SQRT2  # numpy divides a complex by a real as by (SQRT2 + 0j): times 1/SQRT2
        for row in range(n_rows):
            d = rows[row]
            if d < 0:
                hk_r = row_view(hk, row, s_hk)
                for s in range(n_samp):
                    out_f[row, s] = hk_r[s] | _UNKNOWN
                    out_p[row, s] = math.nan
                continue
            c = (cst[d, 0], cst[d, 1], cst[d, 2], cst[d, 3], cst[d, 4], cst[d, 5], cst[d, _R_CAP], cst[d, _R_TOP],
                 cst[d, _K_TOP], cst[d, _R_Z], cst[d, _K_Z], cst[d, _R_BOT], cst[d, _K_BOT], cst[d, _PHASE_LIM] * SQRT2,
                 cst[d, _V_LO], cst[d, _V_HI], cst[d, _R_LO], cst[d, _R_HI], dom[0], dom[1], dom[2], dom[3])
            zr, zi = cst[d, 4], cst[d, 5]
            ca, cb, cc, cd, ce = cst[d, _A], cst[d, _B], cst[d, _C], cst[d, _D], cst[d, _E]
            # Smith's two branches as one expression: a factor 1.0 is exact, so the sum is numpy's.
            k_r, k_i = (1.0, cd) if cst[d, _SMITH_RE] != 0.0 else (cd, 1.0)
            ci_r, cq_r, p_r, f_r = ci_[row], cq_[row], out_p[row], out_f[row]
            tb_r, b_r, v_r = row_view(tb, row, s_tb), row_view(b, row, s_b), row_view(v, row, s_v)
            hk_r = row_view(hk, row, s_hk)
            if kind == LINEAR:
                for s in range(n_samp):
                    f, i_re, i_im = _front(float(ci_r[s]), float(cq_r[s]), tb_r[s], b_r[s], v_r[s], hk_r[s], c)
                    # p0 + Re((i - i0) / S), the division as numpy's (Smith's method).
                    p = ca + ((i_re - cb) * k_r + (i_im - cc) * k_i) * ce
                    p_r[s] = math.nan if f & _UNUSABLE else p
                    f_r[s] = f
            else:
                for s in range(n_samp):
                    vs = v_r[s]
                    f, i_re, i_im = _front(float(ci_r[s]), float(cq_r[s]), tb_r[s], b_r[s], vs, hk_r[s], c)
                    # p_total - Re((v - z i_rms) conj(i_rms)), products as numpy's.
                    jr, ji = i_re * inv_s2, i_im * inv_s2
                    ar = vs - _fma(zr, jr, -(zi * ji))
                    ai = 0.0 - _fma(zr, ji, zi * jr)
                    p = ca - _fma(ar, jr, -(ai * -ji))
                    p_r[s] = math.nan if f & _UNUSABLE else p
                    f_r[s] = f

    def baseline_numba(ci_, cq_, tb, b, v, hk, rows, cst, dom, kind, out_p, out_f):
        """Flags and power of a baseline into ``out_p`` (float64) and ``out_f`` (uint16), in one pass.

        Parameters: counts (n_rows, n_samp) int32 or float64; environment and
        housekeeping flags broadcast to that shape (views); ``rows`` index into
        ``cst`` (-1 unknown); ``dom`` the environment domain; ``kind`` 0 linear, 1 electrical.
        """
        _compile()
        ci_ = np.ascontiguousarray(ci_)
        cq_ = np.ascontiguousarray(cq_)
        _kernel(ci_, cq_, compact(tb), compact(b), compact(v), compact(hk), np.ascontiguousarray(rows), cst, dom,
                kind, out_p, out_f)

    _compiled = []

    def _compile() -> None:
        """Compile (or load from numba's cache) the kernel's only signatures, once per process:
        counts int32 or float64, every input read-only and C-contiguous (writable arrays pass as
        read-only), so a live stream never meets a new specialisation (seconds to compile) mid-run."""
        if _compiled:
            return
        t = _t

        def c(dtype, ndim, readonly=True):
            return t.Array(dtype, ndim, "C", readonly=readonly)

        f8 = t.float64
        rest = (c(f8, 2), c(f8, 2), c(f8, 2), c(t.uint16, 2), c(t.int64, 1), c(f8, 2), c(f8, 1), t.int64,
                c(f8, 2, False), c(t.uint16, 2, False))
        for k in (t.int32, f8):
            _kernel.compile(t.void(c(k, 2), c(k, 2), *rest))
        _kernel.disable_compile()
        _compiled.append(True)

    def compact(a: np.ndarray) -> np.ndarray:
        """A broadcast view as the small C-contiguous array behind it: (1 or n_rows, 1 or n_samp)."""
        if a.ndim == 2 and a.shape[0] > 1 and a.strides[0] == 0:
            a = a[:1]
        if a.ndim == 2 and a.shape[1] > 1 and a.strides[1] == 0:
            a = a[:, :1]
        return np.ascontiguousarray(a)
else:  # pragma: no cover - numba is a dependency of the default install
    baseline_numba = None
