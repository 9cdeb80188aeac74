"""Boundary checks shared by the frozen parameter dataclasses (pure)."""

from __future__ import annotations

import math

from mntes_stream.errors import ConfigError


def finite_float(owner: str, name: str, value) -> float:
    """``float(value)``, or ConfigError naming ``owner`` and ``name`` if it is not a finite number.

    >>> finite_float("recorder", "rotate_s", "60")
    60.0
    >>> finite_float("recorder", "rotate_s", "inf")
    Traceback (most recent call last):
    ...
    mntes_stream.errors.ConfigError: recorder: rotate_s must be finite, got inf"""
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise ConfigError(f"{owner}: {name} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise ConfigError(f"{owner}: {name} must be finite, got {out}")
    return out
