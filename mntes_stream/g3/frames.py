"""G3 frames built with spt3g's own classes: wiring, housekeeping tree, Timepoints, GcpSlow.

What a DfMux DAQ writes, for the simulator (``simulate --format g3``) and
for tests. The housekeeping tree is built bottom-up (inserting into an spt3g
map copies; reading an item gives a live reference): channel -> module ->
mezzanine -> board, 2 mezzanines of 4 modules, everything 1-indexed, while
the wiring map's module (0-7) and channel are 0-indexed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from mntes_stream.core.timing import G3_TICK_NS
from mntes_stream.g3.runtime import spt3g

__all__ = ["ModuleHk", "wiring_frame", "housekeeping_frame", "timepoint_frame", "gcpslow_frame", "g3_time",
           "MODULES_PER_MEZZ", "MEZZANINES"]

MEZZANINES = 2
MODULES_PER_MEZZ = 4


@dataclass(frozen=True)
class ModuleHk:
    """Housekeeping of one module (wiring-map module numbering, 0-7).

    Attributes
    ----------
    nuller_gain, carrier_gain : int
        Analog gain settings, 0-15.
    carrier_amplitude : ndarray, shape (n_ch,)
        Normalized carrier amplitude per channel (0-indexed rows).
    carrier_frequency_hz : ndarray, shape (n_ch,)
    """

    nuller_gain: int
    carrier_gain: int
    carrier_amplitude: np.ndarray
    carrier_frequency_hz: np.ndarray


def g3_time(t_ns: int):
    core, _ = spt3g()
    return core.G3Time(int(t_ns) // G3_TICK_NS)


def wiring_frame(layout: dict, system: str = "ICE", transfer_function: str = "spt3g_filtering_2017_full"):
    """Wiring frame; ``layout`` maps bolometer name -> (board serial, module 0-7, channel 0-indexed)."""
    core, dfmux = spt3g()
    wm = dfmux.DfMuxWiringMap()
    for name, (board, module, channel) in layout.items():
        m = dfmux.DfMuxChannelMapping()
        m.board_serial, m.module, m.channel = int(board), int(module), int(channel)
        m.board_slot, m.crate_serial = int(board) % 16 + 1, 1
        wm[str(name)] = m
    frame = core.G3Frame(core.G3FrameType.Wiring)
    frame["WiringMap"] = wm
    frame["ReadoutSystem"] = system
    frame["DfMuxTransferFunction"] = transfer_function
    return frame


def housekeeping_frame(t_ns: int, boards: dict):
    """Housekeeping frame; ``boards`` maps board serial -> {module 0-7: ModuleHk}."""
    core, dfmux = spt3g()
    hk = dfmux.DfMuxHousekeepingMap()
    for serial, modules in boards.items():
        board = dfmux.HkBoardInfo()
        board.serial = str(serial)
        board.timestamp = g3_time(t_ns)
        board.timestamp_port = "SOCKET"
        for z in range(MEZZANINES):
            mezz = dfmux.HkMezzanineInfo()
            mezz.present = mezz.power = True
            for k in range(MODULES_PER_MEZZ):
                mod = dfmux.HkModuleInfo()
                mod.module_number = k + 1
                mhk = modules.get(z * MODULES_PER_MEZZ + k)
                if mhk is not None:
                    mod.nuller_gain, mod.carrier_gain = int(mhk.nuller_gain), int(mhk.carrier_gain)
                    for c, (amp, freq) in enumerate(zip(mhk.carrier_amplitude, mhk.carrier_frequency_hz)):
                        ch = dfmux.HkChannelInfo()
                        ch.channel_number = c + 1
                        ch.carrier_amplitude = float(amp)
                        ch.carrier_frequency = ch.demod_frequency = float(freq) * core.G3Units.Hz
                        ch.dan_streaming_enable = True
                        ch.dan_accumulator_enable = ch.dan_feedback_enable = True
                        ch.state = "tuned"
                        mod.channels[c + 1] = ch
                mezz.modules[k + 1] = mod
            board.mezz[z + 1] = mezz
        hk[int(serial)] = board
    frame = core.G3Frame(core.G3FrameType.Housekeeping)
    frame["DfMuxHousekeeping"] = hk
    return frame


def timepoint_frame(t_ns: int, samples: dict, n_channels: int):
    """Timepoint frame; ``samples`` maps (board serial, module) -> (I, Q) int arrays of shape (n_channels,)."""
    core, dfmux = spt3g()
    meta = dfmux.DfMuxMetaSample()
    ticks = int(t_ns) // G3_TICK_NS
    boards: dict = {}
    for (serial, module), (ci, cq) in samples.items():
        s = dfmux.DfMuxSample(ticks, 2 * n_channels)
        view = np.asarray(s)
        view[0::2] = ci
        view[1::2] = cq
        boards.setdefault(int(serial), dfmux.DfMuxBoardSamples())[int(module)] = s
    for serial, bs in boards.items():
        bs.nmodules = max(8, len(bs))
        bs.nchannels = n_channels
        bs.nblocks = 1
        meta[serial] = bs
    frame = core.G3Frame(core.G3FrameType.Timepoint)
    frame["EventHeader"] = core.G3Time(ticks)
    frame["DfMux"] = meta
    return frame


def gcpslow_frame(t_ns: int, t_bath_k: float, key: str = "CryoStatus.UC_Head", time_key: str = "Time"):
    """GcpSlow frame with the bath thermometer (in G3Units, base mK) and its time."""
    core, _ = spt3g()
    head, _, entry = key.partition(".")
    frame = core.G3Frame(core.G3FrameType.GcpSlow)
    frame[head] = core.G3MapDouble({entry: float(t_bath_k) * core.G3Units.K})
    frame[time_key] = g3_time(t_ns)
    return frame
