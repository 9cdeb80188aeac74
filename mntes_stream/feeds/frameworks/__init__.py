"""Recorded or live power as the mapmaking frameworks' own objects and files.

=============  ===========================  ====================================  ==================
framework      in memory                    file (its own writer / loader)        extra
=============  ===========================  ====================================  ==================
TOAST 3        :func:`to_toast`             ``toast.io.save_hdf5`` / ``load_hdf5``  ``[toast]``
sotodlib       :func:`to_axismanager`       ``AxisManager.save`` / ``load``         ``[sotodlib]``
litebird_sim   :func:`to_litebird`          ``write_list_of_observations`` /        ``[litebird]``
                                            ``read_list_of_observations``
=============  ===========================  ====================================  ==================

Each takes one evenly sampled block of one module (a :class:`TodBlock`, or a
list of consecutive blocks of one stream, e.g. from a live feed); a recording
or a feed gives one object per module and segment (:func:`segments`: split at
steps in time beyond the feed's ``max_gap_s``). The frameworks are imported
only when used; a missing one is a one-line ``MissingExtraError`` naming
``pip install 'mntes-stream[EXTRA]'``. What each object holds, unit by unit
and flag by flag, is in its module's docstring.
"""

from __future__ import annotations

from mntes_stream.errors import ConfigError
from mntes_stream.feeds.frameworks._common import FocalPlane, focal_plane, read_positions, segments
from mntes_stream.feeds.frameworks.litebird_io import export_litebird, read_litebird, to_litebird
from mntes_stream.feeds.frameworks.sotodlib_io import export_sotodlib, to_axismanager
from mntes_stream.feeds.frameworks.toast_io import export_toast, to_toast

__all__ = ["FRAMEWORKS", "to_framework", "to_toast", "to_axismanager", "to_litebird", "export_toast",
           "export_sotodlib", "export_litebird", "read_litebird", "segments", "focal_plane", "FocalPlane",
           "from_blocks", "read_positions"]

# name -> (in-memory converter, file export, extra)
FRAMEWORKS = {
    "toast": (to_toast, export_toast, "toast"),
    "sotodlib": (to_axismanager, export_sotodlib, "sotodlib"),
    "litebird_sim": (to_litebird, export_litebird, "litebird"),
}


def to_framework(name: str):
    """The in-memory converter of framework ``name`` (``toast``, ``sotodlib``, ``litebird_sim``)."""
    if name not in FRAMEWORKS:
        raise ConfigError(f"unknown framework {name!r}; one of {sorted(FRAMEWORKS)}")
    return FRAMEWORKS[name][0]


def from_blocks(blocks_by_stream, framework: str, *, sample_rates: dict | None = None, **kwargs) -> list:
    """Framework objects of assembled streams: one per stream and segment.

    Parameters
    ----------
    blocks_by_stream : mapping of name to TodBlock or list of TodBlock
        Each value one stream in sample order (``RecordedPower.read()``, or a live feed's blocks grouped).
    framework : {"toast", "sotodlib", "litebird_sim"}
    sample_rates : mapping of name to float, optional
        Nominal rate per stream (default: from the median sample step).
    **kwargs
        Passed to the converter (``positions=``, ...).

    Returns
    -------
    list
        Named ``<setup>_b<board>m<module>``, with ``_seg<k>`` when a stream has several segments.
    """
    convert = to_framework(framework)
    out = []
    for name, data in blocks_by_stream.items():
        segs = [s for s in segments(data) if s.n_samples]
        rate = (sample_rates or {}).get(name)
        for k, seg in enumerate(segs):
            out.append(convert(seg, name=name if len(segs) == 1 else f"{name}_seg{k}", sample_rate_hz=rate,
                               segment=k, **kwargs))
    return out
