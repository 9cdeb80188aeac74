"""SPT-3G G3 readout in and out (optional extra ``mntes-stream[g3]``: spt3g).

An edge package like ``io/``: it turns G3 frames (raw DAQ Timepoint frames, or
Scan frames after spt3g's ``DfMuxCollator``) into the project's messages and
back, with spt3g's own classes and conversion functions. spt3g is imported
lazily: ``import mntes_stream.g3`` works without it, and the first call that
needs it raises :class:`~mntes_stream.errors.MissingExtraError` naming the
extra.

G3 work runs on the spt3g package (1.0.2) whatever else is installed: this
package never imports so3g or toast (so3g would install its bundled, older
spt3g as ``spt3g``, which cannot read current DfMux housekeeping), and once
spt3g 1.0.2 is loaded an import of so3g/toast in the same process is refused
with one line instead of the segfault it would be. Work that needs both a G3
file and a framework reads the G3 in a child process (:mod:`.isolated`).

- :mod:`.runtime`: :func:`spt3g` (the package's one way to spt3g) and the so3g refusal.
- :mod:`.settings`: :class:`G3InputConfig`, how G3 input is read (the ``[g3]`` settings; no numpy).
- :mod:`.mapping`: the wiring map both ways (bolometer name <-> detector id),
  housekeeping -> per-channel amps-per-count and bias (spt3g's own
  functions), GcpSlow -> bath temperature.
- :mod:`.counts`: counts from both layouts (Scan frames, raw Timepoints).
- :mod:`.frames`: G3 frames built with spt3g's classes (simulator, tests).
- :mod:`.translate`: frames -> counts/housekeeping messages, shared by the
  live bridge and the offline tools (so both give identical counts).
- :mod:`.power`: :class:`OpticalPower`, a spt3g pipeline module that appends
  ``MntesOpticalPower`` and ``MntesFlags`` to Scan frames.
- :mod:`.files`: ``convert`` / ``export`` on G3 files of either layout.
- :mod:`.bridge`: the ``g3-bridge`` service (a G3Reader on the DAQ's network tee).
- :mod:`.sim`: the simulator writing G3 (``simulate --format g3``).
- :mod:`.isolated`: G3 work in a child process without so3g (``export RUN.g3 --format toast``).
"""

from __future__ import annotations

from mntes_stream.g3.runtime import RefuseAfterSpt3g, spt3g, spt3g_in_use

__all__ = ["OpticalPower", "RefuseAfterSpt3g", "spt3g", "spt3g_in_use"]


def __getattr__(name: str):
    if name == "OpticalPower":
        from mntes_stream.g3.power import OpticalPower

        return OpticalPower
    raise AttributeError(f"module 'mntes_stream.g3' has no attribute {name!r}")
