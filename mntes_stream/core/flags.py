"""Per-sample quality flags (uint16 bitmask). One definition for the whole package.

A sample with any flag other than ``HK_INTERPOLATED`` set must not be trusted
as optical power; where no power can be computed it is NaN and flagged,
never a silent number.
"""

from __future__ import annotations

import numpy as np

FLAG_DTYPE = np.dtype("<u2")

SATURATED = 1 << 0          # TES normal / saturated, or its response below the counts' resolution
SUPERCONDUCTING = 1 << 1    # superconducting side: R not certainly above |z| (off the operating branch)
OUT_OF_TABLE = 1 << 2       # counts outside the range the response table covers
ENV_OUT_OF_RANGE = 1 << 3   # bath temperature, field or bias outside the tabulated range
HK_STALE = 1 << 4           # housekeeping held longer than the allowed staleness
HK_MISSING = 1 << 5         # no housekeeping at all for this sample
INVALID_INPUT = 1 << 6      # NaN / absurd counts, zero current, bad gain
UNKNOWN_CHANNEL = 1 << 7    # channel has no detector parameters / table
GAP = 1 << 8                # sample lies in a gap (missing chunk) of the stream
PHASE_RESIDUAL = 1 << 9     # quadrature the model does not explain beyond its noise: gain phase, pickup off
LATCHED = 1 << 10           # with SUPERCONDUCTING: R above the bottom, the TES latched resistive (loop gain <= 0)
NONLINEAR = 1 << 11         # baseline (linear, electrical) differs from the physics model by more than its tolerance
LOW_RESPONSIVITY = 1 << 12  # sigma_P (readout noise through the local responsivity) above its tolerance (core.uncertainty)
UNTUNED = 1 << 13           # the board's housekeeping says the channel is not tuned (latched, overbiased, untuned...)
RAILED = 1 << 14            # the board's housekeeping says the channel's DAN, or its module's carrier/nuller/demod, railed

NAMES = {
    SATURATED: "saturated",
    SUPERCONDUCTING: "superconducting",
    OUT_OF_TABLE: "out_of_table",
    ENV_OUT_OF_RANGE: "env_out_of_range",
    HK_STALE: "hk_stale",
    HK_MISSING: "hk_missing",
    INVALID_INPUT: "invalid_input",
    UNKNOWN_CHANNEL: "unknown_channel",
    GAP: "gap",
    PHASE_RESIDUAL: "phase_residual",
    LATCHED: "latched",
    NONLINEAR: "nonlinear",
    LOW_RESPONSIVITY: "low_responsivity",
    UNTUNED: "untuned",
    RAILED: "railed",
}

# Flags after which the power value is not usable (NaN in the output). PHASE_RESIDUAL and
# NONLINEAR are warnings: the value is kept (validate compares linear against MNTES with it).
# LOW_RESPONSIVITY is a warning too; core.uncertainty drops the value where its settings say so
# (low_responsivity_unusable), so the bit keeps one meaning in every file.
UNUSABLE = (SATURATED | SUPERCONDUCTING | LATCHED | OUT_OF_TABLE | HK_MISSING | INVALID_INPUT | UNKNOWN_CHANNEL
            | GAP | UNTUNED | RAILED)


def describe(mask: int) -> list[str]:
    """Names of the bits set in ``mask``.

    >>> describe(SATURATED | HK_STALE)
    ['saturated', 'hk_stale']"""
    return [name for bit, name in NAMES.items() if mask & bit]


def counts_by_flag(flags: np.ndarray) -> dict[str, int]:
    """How many samples carry each flag (for status messages).

    >>> c = counts_by_flag(np.array([[SATURATED, 0], [SATURATED | GAP, 0]], dtype=FLAG_DTYPE))
    >>> c[NAMES[SATURATED]], c[NAMES[GAP]], sum(c.values())
    (2, 1, 3)"""
    flags = np.asarray(flags)
    return {name: int(np.count_nonzero(flags & bit)) for bit, name in NAMES.items()}
