"""sotodlib: power blocks as ``core.AxisManager`` and files written by ``AxisManager.save``.

What an AxisManager holds (built with sotodlib's own classes):

- axes ``dets`` (``LabelAxis``: detector ids) and ``samps`` (``OffsetAxis``:
  n_samp, offset = the block's first sample in the stream);
- ``timestamps`` float64 (samps,) s since the epoch;
- ``signal`` float64 (dets, samps): power in W bit for bit, NaN where no usable power;
- ``flags``: a ``FlagManager`` with one ``so3g.proj.RangesMatrix`` per
  ``core.flags`` bit, named as in ``core.flags.NAMES`` (``saturated``,
  ``gap``, ...), plus ``unusable`` (the union of the UNUSABLE bits: the
  samples a mapmaker cuts; their signal is NaN);
- ``focal_plane``: (dets,) ``xi``, ``eta``, ``gamma`` (rad) and
  ``position_placeholder`` (the documented boresight placeholder unless positions are given);
- ``mntes_stream``: provenance and conventions as scalars (``signal_units`` = "W",
  ``sample_rate_hz``, ``flag_bits``, ...).

sotodlib has no unit field on arrays: ``mntes_stream.signal_units`` says W.
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.errors import import_extra
from mntes_stream.feeds.frameworks import _common as c

__all__ = ["to_axismanager", "export_sotodlib", "EXTRA"]

EXTRA = "sotodlib"


def _core():
    return import_extra("sotodlib.core", EXTRA)


def to_axismanager(data, *, name: str | None = None, sample_rate_hz: float | None = None,
                   positions: Mapping | None = None, segment: int = 0):
    """One evenly sampled block of one module as a sotodlib ``AxisManager``.

    Parameters
    ----------
    data : TodBlock or list of TodBlock
        One stream, one segment (see :func:`~mntes_stream.feeds.frameworks.segments`).
    name : str, optional
        Observation name, kept in ``mntes_stream.observation``.
    sample_rate_hz : float, optional
        Nominal rate (default: from the median sample step).
    positions : mapping of detector id to (xi_rad, eta_rad, gamma_rad), optional

    Returns
    -------
    sotodlib.core.AxisManager
    """
    core = _core()
    from so3g.proj import RangesMatrix

    b = c.single_segment(data)
    rate = c.sample_rate_hz(b, sample_rate_hz)
    fp = c.focal_plane(b.detectors, positions)
    name = name or b.name
    dets = core.LabelAxis("dets", list(b.detectors))
    samps = core.OffsetAxis("samps", b.n_samples, int(b.first_sample))
    aman = core.AxisManager(dets, samps)
    aman.wrap("timestamps", b.t_s, [(0, "samps")])
    aman.wrap("signal", np.array(b.p_opt_w), [(0, "dets"), (1, "samps")])
    if b.sigma_p_w is not None:  # per-sample noise (W): weight 1 / sigma_p_w**2
        aman.wrap("sigma_p_w", np.array(b.sigma_p_w), [(0, "dets"), (1, "samps")])
    flags = core.FlagManager.for_tod(aman)
    for bit, flag_name in fl.NAMES.items():
        flags.wrap(flag_name, RangesMatrix.from_mask((b.flags & bit) != 0), [(0, "dets"), (1, "samps")])
    flags.wrap("unusable", RangesMatrix.from_mask((b.flags & fl.UNUSABLE) != 0), [(0, "dets"), (1, "samps")])
    aman.wrap("flags", flags)
    focal = core.AxisManager(dets)
    focal.wrap("xi", fp.xi_rad, [(0, "dets")])
    focal.wrap("eta", fp.eta_rad, [(0, "dets")])
    focal.wrap("gamma", fp.gamma_rad, [(0, "dets")])
    focal.wrap("position_placeholder", np.full(b.n_detectors, fp.placeholder), [(0, "dets")])
    aman.wrap("focal_plane", focal)
    meta = core.AxisManager()
    for k, v in c.metadata(b, name, rate, fp, segment,
                           sotodlib_flags="flags: one RangesMatrix per core.flags bit name, plus unusable "
                                          "(union of the UNUSABLE bits)").items():
        meta.wrap(k, v)
    aman.wrap("mntes_stream", meta)
    return aman


def export_sotodlib(source, out, *, overwrite: bool = False, compression: str | None = "gzip",
                    positions: Mapping | None = None, **selection):
    """Every module-segment of a recording as a group ``/<observation>`` of one HDF5 file, by ``AxisManager.save``.

    Read back with ``sotodlib.core.AxisManager.load(out, "<observation>")``;
    the root attribute ``observations`` (JSON list) names the groups.

    Returns
    -------
    ExportSummary
    """
    _core()
    import json

    import h5py

    from mntes_stream.feeds.recorded import RecordedPower

    t_start = time.perf_counter()
    out, tmp = c.partial_file(out, overwrite)
    rec = RecordedPower(source, **selection)
    names, n = [], 0
    try:
        with h5py.File(tmp, "w") as f:
            for name, k, block, rate in c.observation_blocks(rec, room_in=tmp):
                am = to_axismanager(block, name=name, sample_rate_hz=rate, segment=k, positions=positions)
                am.save(f, name, compression=compression)
                names.append(name)
                n += block.p_opt_w.size
            f.attrs["observations"] = json.dumps(names)
            f.attrs["software_version"] = c.metadata_version()
        tmp.replace(out)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return c.summary(out, rec, names, n, t_start)
