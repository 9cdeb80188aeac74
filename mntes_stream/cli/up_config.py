"""The settings of ``mntes-stream up``: each declared once, its flag, type check and help following from it.

Its own module, imported when ``up`` runs or shows its help: the command-line
parser of every other command does not pay for the declarations. The
conversion kind is the converter's own setting (``ConverterConfig.kind``).
"""

from __future__ import annotations

from dataclasses import dataclass

from mntes_stream.core.ids import NAME_PATTERN
from mntes_stream.core.settings import Settings, setting
from mntes_stream.core.timing import DFMUX_SAMPLE_RATE_HZ
from mntes_stream.io.keys import DEFAULT_SETUP

__all__ = ["UP_FLAGS", "UpSettings"]


@dataclass(frozen=True)
class UpSettings(Settings):
    """What ``up`` runs: the simulated array, where its files go, how long, and what it does when a service dies."""

    duration_s: float = setting(60.0, "seconds to run (0: until Ctrl-C)", unit="s", ge=0)
    out: str = setting("mntes-up", "parameters and recordings go here")
    setup: str = setting(DEFAULT_SETUP, "setup name in the keys", pattern=NAME_PATTERN)
    modules: int = setting(4, "readout modules", ge=1)
    channels: int = setting(64, "channels per module", ge=1, le=1024)
    sample_rate_hz: float = setting(DFMUX_SAMPLE_RATE_HZ, "DfMux ground rate, 20 MHz / 2**17", unit="Hz", gt=0)
    chunk_s: float = setting(0.1, "counts chunk length", unit="s", gt=0)
    minimal: bool = setting(False, "the minimal physics source instead of the array simulator")
    metrics_port: int | None = setting(None, "serve every service's Prometheus metrics on "
                                       "http://127.0.0.1:PORT/metrics (0: any free port; needs the metrics extra)",
                                       ge=0, le=65535)
    restarts: int = setting(3, "restart a service that dies, at most N times a minute each (0: a death ends "
                            "the run)", ge=0)


# The flags' spellings where they are not the settings' names (add_settings_args' aliases, spelled).
UP_FLAGS = ({"duration_s": ("--duration",)}, {"sample_rate_hz": "--sample-rate"})
