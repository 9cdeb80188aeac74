"""Vectorised bracketed root finding (no I/O)."""

from __future__ import annotations

import numpy as np

from mntes_stream.errors import TableDomainError

__all__ = ["bracketed_root"]


def bracketed_root(f, lo, hi, *, xtol=0.0, rtol=4e-16, max_iter=200):
    """Find ``x`` in ``[lo, hi]`` with ``f(x) = 0`` for every element at once.

    Illinois-modified regula falsi (superlinear on smooth functions, always
    keeps a bracket), with a bisection step where the secant point is unusable.

    Parameters
    ----------
    f : callable
        Maps an array of shape ``S`` to an array of shape ``S``.
    lo, hi : ndarray, shape S
        Bracket ends; ``f(lo)`` and ``f(hi)`` must differ in sign (or be 0).

    Returns
    -------
    ndarray, shape S
        The root to within ``xtol + rtol * |x|``.

    Examples
    --------
    >>> x = bracketed_root(lambda x: x**2 - np.array([2.0, 9.0]), np.zeros(2), np.full(2, 4.0))
    >>> bool(np.allclose(x, [2**0.5, 3.0], rtol=1e-15))
    True
    """
    a = np.array(lo, dtype=float, copy=True)
    b = np.array(hi, dtype=float, copy=True)
    a, b = np.broadcast_arrays(a, b)
    a, b = a.copy(), b.copy()
    fa = np.asarray(f(a), dtype=float).copy()
    fb = np.asarray(f(b), dtype=float).copy()
    if np.any(np.sign(fa) * np.sign(fb) > 0):
        raise TableDomainError("bracketed_root: f(lo) and f(hi) have the same sign")
    x = np.where(fa == 0, a, b)
    done = (fa == 0) | (fb == 0)
    side = np.zeros(a.shape, dtype=np.int8)  # which end was kept last time
    for _ in range(max_iter):
        if np.all(done):
            break
        active = ~done
        with np.errstate(divide="ignore", invalid="ignore"):
            xs = (a * fb - b * fa) / (fb - fa)
        mid = 0.5 * (a + b)
        bad = ~np.isfinite(xs) | (xs <= np.minimum(a, b)) | (xs >= np.maximum(a, b))
        x_new = np.where(bad, mid, xs)
        x = np.where(active, x_new, x)
        fx = np.asarray(f(x), dtype=float)
        left = np.sign(fx) == np.sign(fa)  # root is in [x, b]
        # Illinois: halve the stale end's function value when the same side is kept twice.
        fb = np.where(active & left & (side == 1), 0.5 * fb, fb)
        fa = np.where(active & ~left & (side == -1), 0.5 * fa, fa)
        a = np.where(active & left, x, a)
        fa = np.where(active & left, fx, fa)
        b = np.where(active & ~left, x, b)
        fb = np.where(active & ~left, fx, fb)
        side = np.where(active, np.where(left, 1, -1), side).astype(np.int8)
        tol = xtol + rtol * np.abs(x)
        done |= (fx == 0) | (np.abs(b - a) <= 2 * tol)
    return x
