"""How G3 input is read: the ``[g3]`` settings of ``g3-bridge``, ``convert`` and ``params``.

Apart from :mod:`.mapping`, which reads the frames with them, so that a command's parser builds its flags from
these declarations (``cli._common.add_settings_args``) without importing numpy (``mntes-stream convert --help``
stays light).
"""

from __future__ import annotations

from dataclasses import dataclass

from mntes_stream.core.settings import Settings, setting

__all__ = ["G3InputConfig"]


@dataclass(frozen=True)
class G3InputConfig(Settings):
    """How G3 input is read (the ``[g3]`` settings of ``g3-bridge``, ``convert`` and ``params``)."""

    t_bath_key: str = setting("CryoStatus.UC_Head", "GcpSlow frame key, then map entry, of the bath thermometer")
    t_bath_unit: str = setting("G3Units", "unit of that value (G3Units: spt3g's base, K = 1000)",
                               choices=("G3Units", "K", "mK"))
    t_bath_time_key: str = setting("Time", "GcpSlow frame key of the reading's G3Time (absent: time of the data "
                                   "seen last)")
    t_bath_default_k: float | None = setting(None, "bath temperature when the run has no reading (None: an error)",
                                             unit="K", gt=0)
    b_field_t: float = setting(0.0, "spt3g has no magnetic-field source: this constant field", unit="T")
    transfer_function: str = setting("spt3g_filtering_2017_full", "spt3g transfer function when the wiring frame "
                                     "names none (DfMuxTransferFunction)")
    readout_system: str = setting("ICE", "when the wiring frame has no ReadoutSystem", choices=("ICE", "DfMux"))
    hk_retention_s: float = setting(600.0, "DfMux housekeeping and bath readings kept behind the newest data (older "
                                    "ones but the one in force are dropped: bounded memory in a long run)",
                                    unit="s", gt=0)
