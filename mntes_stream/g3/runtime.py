"""Which spt3g this process's G3 work runs on, loaded lazily; so3g/toast refused once spt3g 1.0.2 is in.

The modules of ``g3/`` import :func:`spt3g` from here (the package's ``__init__`` re-exports it:
a submodule importing its own package's ``__init__``, which imports it back, would be an import loop).
"""

from __future__ import annotations

import sys

__all__ = ["RefuseAfterSpt3g", "spt3g", "spt3g_in_use"]

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
