"""The converter pipeline's settings: the ``[alignment]`` table, plus keys and status cadence."""

from __future__ import annotations

from dataclasses import dataclass, fields

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.io import keys

__all__ = ["INPUT_KINDS", "SCALAR_SENSORS", "AlignmentConfig", "PipelineConfig", "input_topics"]

SCALAR_SENSORS = ("t_bath", "b_field")
#: Key kinds a converter consumes (also the default selection of a replay, any setup).
INPUT_KINDS = ("counts", "hk")


def input_topics(setup: str) -> tuple[str, ...]:
    """Key expressions of a converter's inputs for one setup: counts and housekeeping."""
    return (keys.counts_key(setup), keys.hk_key(setup))


@dataclass(frozen=True)
class AlignmentConfig(Settings):
    """How the converter aligns housekeeping to samples and holds chunks back (the ``[alignment]`` table).

    A sensor not in ``required_hk`` uses its reading when there is one, else
    its default. Two ranges per sensor: a reading outside ``*_accept_*`` is
    impossible (a failed read, a switched-off supply): rejected at the door,
    counted (``hk_range``), never used, the last good reading holds. A reading
    accepted but outside ``*_range_*`` is plausible yet beyond what the
    tables cover: used, and flags ENV_OUT_OF_RANGE. Non-finite readings, and
    a bias or bath temperature not above zero, are rejected whatever the
    acceptance range says (no converter can use them). Power is NaN for
    housekeeping only where there is none (HK_MISSING) or where the last good
    reading is older than its staleness limit (HK_STALE, see ``hk_stale_power``).
    """

    required_hk: tuple[str, ...] = setting(
        SCALAR_SENSORS, "sensors chunks wait for; no reading at all -> HK_MISSING (NaN power)", choices=SCALAR_SENSORS)
    hk_staleness_s: float = setting(2.0, "a value whose nearest good reading is older -> HK_STALE",
                                    unit="s", ge=0)
    hk_stale_power: str = setting("nan", "power of an HK_STALE sample: nan, or keep (the value the held reading "
                                  "gives, flagged)", choices=("nan", "keep"))
    hk_wait_s: float = setting(1.0, "longest a chunk waits for a reading at/after its last sample (0: never wait)",
                               unit="s", ge=0)
    bias_staleness_s: float = setting(600.0, "as hk_staleness_s for the bias (a setting, read back seldom; "
                                      "before any reading the nominal bias, never stale)",
                                      unit="s", ge=0)
    t_bath_default_k: float = setting(0.100, "bath temperature of a sensor not required and never reported",
                                      unit="K", gt=0)
    b_field_default_t: float = setting(0.0, "field of a sensor not required and never reported", unit="T")
    t_bath_range_k: tuple[float, float] = setting((0.02, 0.5), "[low, high]; readings outside -> ENV_OUT_OF_RANGE",
                                                  unit="K", increasing=True)
    b_field_range_t: tuple[float, float] = setting((-0.01, 0.01), "[low, high]; readings outside -> ENV_OUT_OF_RANGE",
                                                   unit="T", increasing=True)
    bias_range_v: tuple[float, float] = setting((0.0, 1e-3), "[low, high]; accepted readings outside -> "
                                                "ENV_OUT_OF_RANGE",
                                                unit="V", increasing=True)
    t_bath_accept_k: tuple[float, float] = setting(
        (0.0, 5.0), "[low, high]; readings outside (or <= 0 K) are physically impossible here: rejected, counted "
        "(hk_range), never used",
        unit="K", increasing=True)
    b_field_accept_t: tuple[float, float] = setting(
        (-1.0, 1.0), "[low, high]; readings outside are physically impossible here: rejected, counted (hk_range), "
        "never used", unit="T", increasing=True)
    bias_accept_v: tuple[float, float] = setting(
        (0.0, 1.0), "as t_bath_accept_k for the bias (0 V or below is never an operating bias: always rejected)",
        unit="V", increasing=True)
    max_hk_readings: int = setting(10_000, "readings one housekeeping message may carry; more: rejected (too_large)",
                                   ge=1)
    overload: str = setting("shed", "in a real overload (the converter service behind for [converter] "
                            "overload_after_s), a chunk further behind its stream's own pace than max_lag_s: set "
                            "aside, converted late when there is time, shed beyond [converter] set_aside_mb (all in "
                            "the ledger); keep: converted in turn (latency grows without bound). Offline convert "
                            "never sheds", choices=("shed", "keep"))
    max_lag_s: float = setting(2.0, "how far behind its stream's pace a chunk may be before overload applies",
                               unit="s", gt=0)
    max_pending: int = setting(4096, "chunks held at most; beyond, the oldest is converted at once", ge=1)
    hk_retention_s: float = setting(600.0, "housekeeping history kept behind the data clock; older readings rejected",
                                    unit="s", gt=0)
    hk_max_ahead_s: float = setting(10.0, "readings stamped further ahead of the data clock are rejected",
                                    unit="s", ge=0)


@dataclass(frozen=True)
class PipelineConfig(AlignmentConfig):
    """Everything :class:`~mntes_stream.pipeline.pipeline.ConverterPipeline` takes: the alignment, plus
    the keys it publishes on (``mntes/<setup>/power/...``, ``mntes/<setup>/status/<service>``) and the
    status cadence (receive clock)."""

    setup: str = setting(keys.DEFAULT_SETUP, "keys mntes/<setup>/...", pattern=NAME_PATTERN)
    service: str = setting("converter", "status on mntes/<setup>/status/<service>", pattern=NAME_PATTERN)
    status_interval_s: float = setting(1.0, "status message cadence", unit="s", gt=0)

    @classmethod
    def from_parts(cls, alignment: AlignmentConfig, **rest) -> PipelineConfig:
        return cls(**{f.name: getattr(alignment, f.name) for f in fields(AlignmentConfig)}, **rest)
