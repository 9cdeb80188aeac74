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

import sys

__all__ = ["OpticalPower", "RefuseAfterSpt3g", "spt3g", "spt3g_in_use"]

_LOADED = None
# so3g (imported by toast and sotodlib) loaded after spt3g 1.0.2 segfaults the process.
_AFTER_SPT3G = ("so3g", "toast", "sotodlib")


class RefuseAfterSpt3g:
    """A ``sys.meta_path`` finder: so3g/toast/sotodlib after spt3g 1.0.2 is a clear ImportError, not a segfault."""

    def find_spec(self, name, path=None, target=None):
        if name.partition(".")[0] in _AFTER_SPT3G:
            from mntes_stream.errors import MissingExtraError

            raise MissingExtraError(
                f"{name} cannot be imported in a process that has loaded spt3g 1.0.2 (so3g's libraries after "
                "spt3g's segfault): do the framework work in another process (mntes_stream.g3.isolated)")
        return None


def _bundled(core) -> bool:
    return "so3g" in (getattr(core, "__file__", "") or "")


def spt3g():
    """``(spt3g.core, spt3g.dfmux)``, or MissingExtraError naming ``mntes-stream[g3]``.

    Never imports so3g or toast: in a process that has not loaded so3g this is
    the spt3g package itself (1.0.2), and further imports of so3g/toast/sotodlib
    are refused (they would segfault). A process that loaded so3g first (a
    framework export, the test session) gets so3g's bundled copy, as
    :func:`spt3g_in_use` says; it cannot read DfMux housekeeping written by
    current spt3g.
    """
    global _LOADED
    if _LOADED is None:
        from mntes_stream.errors import import_extra

        core = import_extra("spt3g.core", "g3")
        _LOADED = core, import_extra("spt3g.dfmux", "g3")
        # Registers BolometerProperties with the reader: a Calibration frame is undecodable without it
        # (so3g happens to load it; spt3g 1.0.2 alone does not).
        import_extra("spt3g.calibration", "g3")
        if not _bundled(core) and not any(m in sys.modules for m in _AFTER_SPT3G):
            sys.meta_path.insert(0, RefuseAfterSpt3g())
    return _LOADED


def spt3g_in_use() -> str:
    """One line: which spt3g this process's G3 work runs on (loads it)."""
    core, _ = spt3g()
    import spt3g as pkg

    version = getattr(pkg, "__version__", None) or getattr(getattr(pkg, "version", None), "version", "?")
    if _bundled(core):
        return (f"so3g's bundled spt3g {version} (so3g was loaded first in this process; it cannot read DfMux "
                "housekeeping written by spt3g 1.0.2)")
    return f"spt3g {version} ({core.__file__.rsplit('/core/', 1)[0]})"


def __getattr__(name: str):
    if name == "OpticalPower":
        from mntes_stream.g3.power import OpticalPower

        return OpticalPower
    raise AttributeError(f"module 'mntes_stream.g3' has no attribute {name!r}")
