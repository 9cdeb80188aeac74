"""SPT-3G G3 readout in and out (optional extra ``mntes-stream[g3]``: spt3g).

An edge package like ``io/``: it turns G3 frames (raw DAQ Timepoint frames, or
Scan frames after spt3g's ``DfMuxCollator``) into the project's messages and
back, with spt3g's own classes and conversion functions. spt3g is imported
lazily: ``import mntes_stream.g3`` works without it, and the first call that
needs it raises :class:`~mntes_stream.errors.MissingExtraError` naming the
extra.

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
"""

from __future__ import annotations

import contextlib
import importlib

__all__ = ["OpticalPower", "spt3g"]

_LOADED = None


def spt3g():
    """``(spt3g.core, spt3g.dfmux)``, or MissingExtraError naming ``mntes-stream[g3]``.

    so3g and toast are loaded first when installed: their shared libraries
    must precede spt3g's (spt3g 1.0.2 first, then so3g or toast, segfaults),
    and a process that converts G3 may export to TOAST/sotodlib later.
    Note what that means: so3g (which toast imports) installs its *bundled*
    spt3g as ``sys.modules["spt3g"]``, so in a process with so3g the G3 code
    runs on so3g's copy (0.3.dev289 with so3g 0.2.9), and on the spt3g
    package (1.0.2) only where so3g is not installed. Both are tested
    (``tests/test_g3.py`` runs the spt3g comparison in a process without so3g).
    """
    global _LOADED
    if _LOADED is None:
        from mntes_stream.errors import import_extra

        for name in ("so3g", "toast"):
            with contextlib.suppress(ImportError):
                importlib.import_module(name)
        _LOADED = import_extra("spt3g.core", "g3"), import_extra("spt3g.dfmux", "g3")
    return _LOADED


def __getattr__(name: str):
    if name == "OpticalPower":
        from mntes_stream.g3.power import OpticalPower

        return OpticalPower
    raise AttributeError(f"module 'mntes_stream.g3' has no attribute {name!r}")
