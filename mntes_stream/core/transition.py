"""Superconducting transition models R(T, I, B).

Every model is described by its *shape* ``T_s(R)``: the temperature at which the
film has resistance ``R`` with no current and no magnetic field. The shape is
the primitive because the MNTES inverse needs exactly that direction
(measured current -> R -> T), so the inverse is exact for every model and needs
no root finding. Current and field enter through a shift of the transition
temperature that is common to all shapes (see ``ARCHITECTURE.md``)::

    T(R, |I|, B) = T_s(R) + c1 B + c2 B**2 - gamma |I|

so ``R(T, I, B) = T_s^{-1}(T - c1 B - c2 B**2 + gamma |I|)``. ``gamma`` (K/A)
gives the logarithmic current sensitivity ``beta = gamma |I| / (R dT_s/dR)``.

A shape provides ``temperature_k(r)`` with its first and second derivative in R,
the open resistance interval on which it is strictly monotone, and the forward
``resistance_ohm(t)`` (exact inverse of ``temperature_k``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, Protocol, runtime_checkable

import numpy as np

from mntes_stream.core.solve import bracketed_root
from mntes_stream.errors import ConfigError

__all__ = [
    "Transition",
    "ArctanTransition",
    "TabulatedTransition",
    "transition_from_dict",
]


@runtime_checkable
class Transition(Protocol):
    """Interface every transition shape implements (vectorised over arrays)."""

    kind: str

    @property
    def r_normal_ohm(self) -> float: ...

    def r_domain_ohm(self) -> tuple[Any, Any]:
        """Open interval ``(r_min, r_max)`` on which ``T_s`` is strictly increasing."""

    def temperature_k(self, r_ohm): ...

    def dtemperature_dr(self, r_ohm) -> tuple[Any, Any]:
        """``(dT_s/dR, d2T_s/dR2)`` in K/Ohm and K/Ohm^2, same shape as ``r_ohm``."""

    def resistance_ohm(self, t_k): ...

    def to_dict(self) -> dict: ...


@dataclass(frozen=True)
class ArctanTransition:
    """The paper's placeholder: ``R = R_n (1/2 + atan((T - T_c)/(IQR/2))/pi)``.

    Fields may be floats (one detector) or numpy arrays that broadcast against
    the sample arrays (many detectors, e.g. shape ``(n_det, 1)``).
    """

    t_c_k: Any
    iqr_k: Any
    r_n_ohm: Any
    kind: str = field(default="arctan", init=False)

    def __post_init__(self) -> None:
        for name in ("t_c_k", "iqr_k", "r_n_ohm"):
            value = np.asarray(getattr(self, name), dtype=float)
            if not np.all(np.isfinite(value)) or np.any(value <= 0):
                raise ConfigError(f"arctan transition: {name} must be finite and > 0, got {value}")

    @property
    def r_normal_ohm(self):
        return self.r_n_ohm

    def r_domain_ohm(self):
        return (0.0 * self.r_n_ohm, self.r_n_ohm)

    def _theta(self, r_ohm):
        return np.pi * (np.asarray(r_ohm, dtype=float) / self.r_n_ohm - 0.5)

    def temperature_k(self, r_ohm):
        return self.t_c_k + 0.5 * self.iqr_k * np.tan(self._theta(r_ohm))

    def dtemperature_dr(self, r_ohm):
        th = self._theta(r_ohm)
        tan = np.tan(th)
        sec2 = 1.0 + tan * tan
        scale = 0.5 * self.iqr_k * np.pi / self.r_n_ohm
        d1 = scale * sec2
        d2 = scale * (np.pi / self.r_n_ohm) * 2.0 * sec2 * tan
        return d1, d2

    def resistance_ohm(self, t_k):
        x = (np.asarray(t_k, dtype=float) - self.t_c_k) / (0.5 * self.iqr_k)
        return self.r_n_ohm * (0.5 + np.arctan(x) / np.pi)

    def to_dict(self) -> dict:
        return {
            "transition": "arctan",
            "t_c_k": float(self.t_c_k),
            "iqr_k": float(self.iqr_k),
            "r_n_ohm": float(self.r_n_ohm),
        }


@dataclass(frozen=True)
class TabulatedTransition:
    """A measured transition given as points ``(T_k, R_k)``.

    ``T_s(R)`` is the monotone cubic (PCHIP) interpolant through the points of
    the strictly increasing part of the curve, so it has no overshoot between
    measured points and continuous first derivative (needed for alpha).
    Below the lowest and above the highest measured resistance the model is
    undefined (superconducting / normal) and the inverse flags it.

    Parameters
    ----------
    t_k, r_ohm : tuple of float, shape (n_points,)
        Temperatures strictly increasing, resistances non-decreasing.
    """

    t_k: tuple
    r_ohm: tuple
    kind: str = field(default="tabulated", init=False)

    def __post_init__(self) -> None:
        t = np.asarray(self.t_k, dtype=float)
        r = np.asarray(self.r_ohm, dtype=float)
        if t.ndim != 1 or t.shape != r.shape or t.size < 4:
            raise ConfigError("tabulated transition needs >= 4 (T, R) points of equal length")
        if not (np.all(np.isfinite(t)) and np.all(np.isfinite(r))):
            raise ConfigError("tabulated transition: points must be finite")
        if np.any(np.diff(t) <= 0):
            raise ConfigError("tabulated transition: temperatures must be strictly increasing")
        if np.any(np.diff(r) < 0) or np.any(r < 0):
            raise ConfigError("tabulated transition: resistances must be >= 0 and non-decreasing")
        # Keep the strictly increasing core: the last point at the minimum
        # resistance to the first point at the maximum.
        lo = int(np.flatnonzero(r == r[0])[-1])
        hi = int(np.flatnonzero(r == r[-1])[0])
        rc, tc = r[lo : hi + 1], t[lo : hi + 1]
        if rc.size < 4 or np.any(np.diff(rc) <= 0):
            raise ConfigError(
                "tabulated transition: need >= 4 strictly increasing resistance points inside the transition"
            )
        # Imported here: scipy.interpolate costs a converter's start ~0.25 s, and only tabulated curves need it.
        from scipy.interpolate import PchipInterpolator

        object.__setattr__(self, "_t_of_r", PchipInterpolator(rc, tc, extrapolate=False))
        object.__setattr__(self, "_r_core", (float(rc[0]), float(rc[-1])))

    @property
    def r_normal_ohm(self) -> float:
        return float(self.r_ohm[-1])

    def r_domain_ohm(self):
        return self._r_core

    def temperature_k(self, r_ohm):
        return self._t_of_r(np.asarray(r_ohm, dtype=float))

    def dtemperature_dr(self, r_ohm):
        r = np.asarray(r_ohm, dtype=float)
        return self._t_of_r(r, 1), self._t_of_r(r, 2)

    def resistance_ohm(self, t_k):
        t = np.asarray(t_k, dtype=float)
        r_lo, r_hi = self._r_core
        t_lo = float(self._t_of_r(r_lo))
        t_hi = float(self._t_of_r(r_hi))
        inside = (t > t_lo) & (t < t_hi)
        out = np.where(t <= t_lo, self.r_ohm[0], self.r_normal_ohm).astype(float)
        if np.any(inside):
            ti = t[inside] if t.ndim else t
            root = bracketed_root(
                lambda r: self._t_of_r(r) - ti,
                np.full(np.shape(ti), r_lo),
                np.full(np.shape(ti), r_hi),
            )
            if t.ndim:
                out[inside] = root
            else:
                out = root
        return out

    def to_dict(self) -> dict:
        return {
            "transition": "tabulated",
            "transition_t_k": [float(x) for x in self.t_k],
            "transition_r_ohm": [float(x) for x in self.r_ohm],
        }


def transition_from_dict(d: dict) -> Transition:
    """Build a transition from the keys written by ``to_dict``."""
    kind = d.get("transition", "arctan")
    if kind == "arctan":
        try:
            return ArctanTransition(t_c_k=d["t_c_k"], iqr_k=d["iqr_k"], r_n_ohm=d["r_n_ohm"])
        except KeyError as exc:
            raise ConfigError(f"arctan transition: missing {exc.args[0]}") from None
    if kind == "tabulated":
        try:
            return TabulatedTransition(
                t_k=tuple(d["transition_t_k"]), r_ohm=tuple(d["transition_r_ohm"])
            )
        except KeyError as exc:
            raise ConfigError(f"tabulated transition: missing {exc.args[0]}") from None
    raise ConfigError(f"unknown transition model {kind!r} (known: arctan, tabulated)")

