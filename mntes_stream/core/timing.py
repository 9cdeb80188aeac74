"""DfMux and G3 timing facts, exact (pure constants, nothing imported so the CLI can use them at parse time).

The DfMux samples at 20 MHz / 2**17 = 152.587890625 Hz: one sample every
655,360 ticks of the 100 MHz (10 ns) clock that G3 timestamps count in.
"152.59 Hz" would drift 0.8 ms a minute against those timestamps.

>>> DFMUX_SAMPLE_RATE_HZ
152.587890625
>>> DFMUX_TICKS_PER_SAMPLE * G3_TICK_NS == round(1e9 / DFMUX_SAMPLE_RATE_HZ)
True
"""

__all__ = ["DFMUX_SAMPLE_RATE_HZ", "DFMUX_TICKS_PER_SAMPLE", "G3_TICK_NS"]

G3_TICK_NS = 10                          # spt3g G3Time / G3Units: 1 tick = 10 ns
DFMUX_TICKS_PER_SAMPLE = 2**17 * 5       # 655,360 ticks of 10 ns
DFMUX_SAMPLE_RATE_HZ = 20e6 / 2**17      # 152.587890625 Hz, exact in binary floating point
