"""TOAST 3: power blocks as ``toast.Observation`` and files written by ``toast.io.save_hdf5``.

What an observation holds (built with TOAST's own classes):

- ``detdata["signal"]``: float64 (n_det, n_samp), units ``u.W``: the power
  bit for bit, NaN where no usable power;
- ``detdata["flags"]``: uint8, TOAST's bits: ``defaults.det_mask_invalid`` (1)
  wherever the sample carries any :data:`~mntes_stream.core.flags.UNUSABLE`
  bit (its power is NaN; ``invalid_mask`` changes the set) or the signal is not
  finite. Our other bits are NOT copied into TOAST's flags (our 2 and 4 would
  read as TOAST's "processing" and "sso");
- ``detdata["mntes_flags"]``: uint16, the full ``core.flags`` bitmask;
- per-detector flags: ``det_mask_invalid`` for a detector with no valid sample;
- ``shared["times"]``: float64 s since the epoch (``t_ns / 1e9``);
  ``shared["flags"]``: uint8, ``shared_mask_invalid`` (1) where every detector
  has GAP (a missing chunk), else 0;
- ``telescope.focalplane``: detector names, ``quat`` from (xi, eta, gamma)
  (``instrument_coords.xieta_to_quat``), ``gamma``, columns ``board``,
  ``module``, ``channel``, ``position_placeholder``; ``sample_rate`` in Hz;
- ``telescope.site``: a ``GroundSite`` named ``unknown-site`` at 0, 0, 0 m
  unless one is given (a placeholder: the readout does not know where it is);
- ``obs["mntes_stream"]``: provenance and conventions (units, flag bits, placeholders).

One observation per module and segment (TOAST observations are evenly sampled).
"""

from __future__ import annotations

import time
from collections.abc import Mapping

import numpy as np

from mntes_stream.core import flags as fl
from mntes_stream.errors import ConfigError, import_extra
from mntes_stream.feeds.frameworks import _common as c

__all__ = ["to_toast", "export_toast", "EXTRA"]

EXTRA = "toast"


def _toast():
    return import_extra("toast", EXTRA)


def to_toast(data, *, name: str | None = None, sample_rate_hz: float | None = None, positions: Mapping | None = None,
             site=None, comm=None, telescope_name: str = "mntes", segment: int = 0,
             invalid_mask: int = fl.UNUSABLE):
    """One evenly sampled block of one module as a ``toast.Observation``.

    Parameters
    ----------
    data : TodBlock or list of TodBlock
        One stream, one segment (see :func:`~mntes_stream.feeds.frameworks.segments`).
    name : str, optional
        Observation name (default: the stream's, ``<setup>_b<board>m<module>``).
    sample_rate_hz : float, optional
        Nominal rate (default: from the median sample step).
    positions : mapping of detector id to (xi_rad, eta_rad, gamma_rad), optional
        Detector positions; default: the documented boresight placeholder.
    site : toast.instrument.Site, optional
        Default: a ``GroundSite`` placeholder ``unknown-site``.
    comm : toast.Comm, optional
        Default: a serial ``toast.Comm(world=None)``; a group of one process only.
    invalid_mask : int
        ``core.flags`` bits that make a sample TOAST-invalid (default ``UNUSABLE``: the samples whose power is NaN).

    Returns
    -------
    toast.Observation
    """
    toast = _toast()
    import astropy.units as u
    from astropy.table import QTable
    from toast.instrument import Focalplane, GroundSite, Telescope
    from toast.instrument_coords import xieta_to_quat

    b = c.single_segment(data)
    rate = c.sample_rate_hz(b, sample_rate_hz)
    fp = c.focal_plane(b.detectors, positions)
    name = name or b.name
    n_det, n = b.n_detectors, b.n_samples
    quats = np.atleast_2d(xieta_to_quat(fp.xi_rad, fp.eta_rad, fp.gamma_rad)).reshape(n_det, 4)
    table = QTable(
        [list(b.detectors), quats, fp.gamma_rad * u.rad, np.full(n_det, b.board, np.int32),
         np.full(n_det, b.module, np.int32), np.asarray(b.channels, np.int32), np.full(n_det, fp.placeholder)],
        names=["name", "quat", "gamma", "board", "module", "channel", "position_placeholder"],
    )
    focalplane = Focalplane(detector_data=table, sample_rate=rate * u.Hz)
    if site is None:
        site = GroundSite("unknown-site", 0.0 * u.deg, 0.0 * u.deg, 0.0 * u.m)
    telescope = Telescope(telescope_name, focalplane=focalplane, site=site)
    comm = comm if comm is not None else toast.Comm(world=None)
    if comm.group_size != 1:
        raise ConfigError(f"to_toast builds a serial observation (one process); this comm's group has "
                          f"{comm.group_size} processes (use toast's own distribution after loading the export)")
    obs = toast.Observation(comm, telescope, n, name=name)
    obs.shared.create_column("times", shape=(n,), dtype=np.float64)
    obs.shared["times"].set(b.t_s, offset=(0,), fromrank=0)
    defaults = toast.observation.default_values
    # A missing chunk (GAP on every detector) is a sample missing for the whole module: TOAST's shared invalid.
    missing = np.all((b.flags & fl.GAP) != 0, axis=0) if n_det else np.zeros(n, bool)
    obs.shared.create_column("flags", shape=(n,), dtype=np.uint8)
    obs.shared["flags"].set(np.where(missing, np.uint8(defaults.shared_mask_invalid), np.uint8(0)), offset=(0,),
                            fromrank=0)
    obs.detdata.create("signal", dtype=np.float64, units=u.W)
    obs.detdata["signal"][:] = b.p_opt_w
    bad = ((b.flags & invalid_mask) != 0) | ~np.isfinite(b.p_opt_w)
    obs.detdata.create("flags", dtype=np.uint8)
    obs.detdata["flags"][:] = np.where(bad, np.uint8(defaults.det_mask_invalid), np.uint8(0))
    obs.detdata.create("mntes_flags", dtype=np.uint16)
    obs.detdata["mntes_flags"][:] = b.flags
    if b.sigma_p_w is not None:
        # Per-sample noise (issue 26): a mapmaker's weight is 1 / sigma_p_w**2 (TOAST's noise models are per detector).
        obs.detdata.create("sigma_p_w", dtype=np.float64, units=u.W)
        obs.detdata["sigma_p_w"][:] = b.sigma_p_w
    # A detector with no usable sample at all is flagged as a whole, as TOAST's per-detector flags do.
    obs.update_local_detector_flags({d: defaults.det_mask_invalid for d, row in zip(b.detectors, bad) if row.all()})
    obs["mntes_stream"] = c.metadata(
        b, name, rate, fp, segment,
        toast_flags=(f"detdata flags: det_mask_invalid (1) where core.flags & {int(invalid_mask)} or the signal is "
                     "not finite; shared flags: shared_mask_invalid (1) where every detector has GAP; "
                     "detector flags: det_mask_invalid for a detector with no valid sample; full bits in mntes_flags"),
        site="given" if site.name != "unknown-site" else "placeholder GroundSite unknown-site (0, 0, 0 m)",
    )
    return obs


def export_toast(source, out, *, overwrite: bool = False, positions: Mapping | None = None, **selection):
    """Every module-segment of a recording as ``<out>/<observation>.h5``, written by ``toast.io.save_hdf5``.

    Read back with ``toast.io.load_hdf5(path, toast.Comm(world=None))``.

    Returns
    -------
    ExportSummary
        ``path`` is the directory.
    """
    _toast()
    from toast.io import save_hdf5

    from mntes_stream.feeds.recorded import RecordedPower

    t_start = time.perf_counter()
    rec = RecordedPower(source, **selection)
    names, n = [], 0
    with c.output_dir(out, overwrite) as tmp:
        for name, k, block, rate in c.observation_blocks(rec, room_in=tmp):
            obs = to_toast(block, name=name, sample_rate_hz=rate, segment=k, positions=positions)
            save_hdf5(obs, str(tmp))
            names.append(name)
            n += block.p_opt_w.size
    return c.summary(out, rec, names, n, t_start)
