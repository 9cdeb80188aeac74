"""litebird_sim: power blocks as ``litebird_sim.Observation`` and files written by ``write_list_of_observations``.

What an observation holds (built with litebird_sim's own classes):

- ``tod``: float64 (n_det, n_samp), the power in W bit for bit, NaN where no
  usable power. **litebird_sim has no unit for power** (its ``Units`` are
  K_CMB, K_RJ, Jy/sr, ADU, dimensionless, ...): the TOD's units are the
  plain string ``"W"``, stored as the dataset's ``units`` attribute, and its
  description says so. ``read_list_of_observations`` does not know ``"W"``:
  it logs a warning and labels the TOD with its default, K_CMB (it turns any
  ``TodDescription`` it is given into a bare name first).
  :func:`read_litebird` sets ``"W"`` back from the file's attribute.
- ``local_flags``: uint16 (n_det, n_samp), the ``core.flags`` bits copied
  (litebird_sim has no flag convention of its own; its mapmakers do not read
  flags: select usable samples yourself, ``local_flags & UNUSABLE == 0``).
  No ``global_flags``: litebird_sim 0.18.0 writes them run-length encoded
  and its loader reads them back without decoding.
- times: litebird_sim has no per-sample times: ``start_time`` (float s since
  the Unix epoch) + k / ``sampling_rate_hz``. A block whose times stray from
  that grid by more than ``max_time_error_ns`` is refused. The exact int64 ns
  times go alongside: ``obs.mntes_t_ns`` in memory, dataset ``mntes_t_ns``
  in the file (litebird_sim's loader ignores it; :func:`read_litebird` reads it).
- detectors (``DetectorInfo`` fields): ``name`` (detector id), ``wafer``
  (``<setup>_b<board>m<module>``), ``pixel`` (channel), ``sampling_rate_hz``,
  ``pol_angle_rad`` (gamma), ``pointing_u_v`` (xi, eta in rad), ``quat`` the
  identity (boresight): the documented placeholder unless positions are given,
  and even then only gamma, xi and eta are carried, not a quaternion;
  ``bandcenter_ghz`` 1, ``bandwidth_ghz`` 0 (a placeholder: litebird_sim's
  loader refuses a detector whose band centre is not > 0) unless ``band_ghz`` is given.
- ``pointing_provider``: a constant identity boresight->ecliptic quaternion
  unless one is given (a placeholder: ``read_list_of_observations`` 0.18.0
  cannot load a file without one).
- ``obs.mntes_stream`` / file attribute ``mntes_stream`` (JSON): provenance
  and conventions (units W, flag bits, placeholders).

One observation per module and segment, one file each.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import asdict
from pathlib import Path

import numpy as np

from mntes_stream.errors import ConfigError, import_extra
from mntes_stream.feeds.frameworks import _common as c

__all__ = ["to_litebird", "export_litebird", "read_litebird", "EXTRA", "UNITS", "TOD_DESCRIPTION", "PLACEHOLDER_BAND_GHZ"]

EXTRA = "litebird"
UNITS = "W"
TOD_DESCRIPTION = ("optical power at the TES in W (MNTES), NaN where no usable power; litebird_sim.Units has no "
                   "watt, so the units are the string 'W', not one of its Units (NOT K_CMB)")
DEFAULT_MAX_TIME_ERROR_NS = 1000
# litebird_sim's loader refuses bandcenter_ghz <= 0; the readout knows no band: an obvious placeholder.
PLACEHOLDER_BAND_GHZ = (1.0, 0.0)


def _lbs():
    return import_extra("litebird_sim", EXTRA)


def _tod_description(lbs):
    return lbs.TodDescription(name="tod", units=UNITS, dtype=np.float64, description=TOD_DESCRIPTION)


def to_litebird(data, *, name: str | None = None, sample_rate_hz: float | None = None,
                positions: Mapping | None = None, segment: int = 0,
                max_time_error_ns: int = DEFAULT_MAX_TIME_ERROR_NS, band_ghz: tuple | None = None, pointing=None):
    """One evenly sampled block of one module as a ``litebird_sim.Observation``.

    Parameters
    ----------
    data : TodBlock or list of TodBlock
        One stream, one segment (see :func:`~mntes_stream.feeds.frameworks.segments`).
    name : str, optional
        Observation name, kept in ``obs.mntes_stream["observation"]``.
    sample_rate_hz : float, optional
        Nominal rate (default: from the median sample step).
    positions : mapping of detector id to (xi_rad, eta_rad, gamma_rad), optional
    max_time_error_ns : int
        Largest allowed distance between a recorded time and ``start + k / rate``.
    band_ghz : (centre, width), optional
        Detector band in GHz; default the placeholder :data:`PLACEHOLDER_BAND_GHZ`
        (litebird_sim's loader refuses a detector without a band centre > 0).
    pointing : litebird_sim.PointingProvider, optional
        Boresight pointing; default a placeholder, the constant identity quaternion.

    Returns
    -------
    litebird_sim.Observation
        ``tod`` (n_det, n_samp) float64 W, ``local_flags`` (n_det, n_samp) uint16,
        ``mntes_t_ns`` (n_samp,) int64, ``mntes_stream`` dict.

    Raises
    ------
    ConfigError
        A segment break, or times off the even grid by more than ``max_time_error_ns``.
    """
    lbs = _lbs()
    b = c.single_segment(data)
    rate = c.sample_rate_hz(b, sample_rate_hz)
    fp = c.focal_plane(b.detectors, positions)
    name = name or b.name
    grid_ns = np.int64(b.t_ns[0]) + np.rint(np.arange(b.n_samples) * (1e9 / rate)).astype(np.int64)
    err_ns = int(np.abs(b.t_ns - grid_ns).max())
    if err_ns > max_time_error_ns:
        raise ConfigError(f"{name}: sample times stray {err_ns} ns from start + k / {rate:g} Hz (allowed "
                          f"{max_time_error_ns} ns); litebird_sim has no per-sample times: use another format")
    # As read_one_observation builds them: DetectorInfo (its quat defaults to the identity) as dicts.
    center_ghz, width_ghz = (PLACEHOLDER_BAND_GHZ if band_ghz is None else band_ghz)
    if not center_ghz > 0 or not width_ghz >= 0:
        raise ConfigError(f"band_ghz: centre must be > 0 and width >= 0 (GHz), got {band_ghz!r}")
    dets = [asdict(lbs.DetectorInfo(name=d, wafer=b.name, pixel=int(ch), sampling_rate_hz=rate,
                                    pol_angle_rad=float(g), pointing_u_v=np.array([x, e]),
                                    bandcenter_ghz=float(center_ghz), bandwidth_ghz=float(width_ghz)))
            for d, ch, x, e, g in zip(b.detectors, b.channels.tolist(), fp.xi_rad, fp.eta_rad, fp.gamma_rad)]
    obs = lbs.Observation(detectors=dets, n_samples_global=b.n_samples, start_time_global=int(b.t_ns[0]) / 1e9,
                          sampling_rate_hz=rate, tods=[_tod_description(lbs)])
    obs.tod[:] = b.p_opt_w
    # read_list_of_observations reads a pointing provider unconditionally (0.18.0): without one it cannot load
    # the file. The readout knows no pointing: a constant identity boresight->ecliptic quaternion, documented.
    obs.pointing_provider = pointing if pointing is not None else lbs.PointingProvider(
        bore2ecliptic_quats=lbs.RotQuaternion(np.array([[0.0, 0.0, 0.0, 1.0]])))
    obs.local_flags = np.array(b.flags)
    obs.mntes_t_ns = np.array(b.t_ns)
    obs.mntes_sigma_p_w = None if b.sigma_p_w is None else np.array(b.sigma_p_w)
    obs.mntes_stream = c.metadata(
        b, name, rate, fp, segment, max_time_error_ns=err_ns,
        litebird_units="litebird_sim.Units has no watt: tod units are the string 'W'; read_list_of_observations "
                       "does not know it and labels the tod K_CMB with a warning (read_litebird sets 'W' back)",
        litebird_flags="local_flags: core.flags bits as they are (litebird_sim has no flag convention)",
        litebird_times="start_time (float s since the epoch) + k / sampling_rate_hz; exact ns in mntes_t_ns",
        litebird_focal_plane="quat is the identity (boresight); gamma in pol_angle_rad, (xi, eta) rad in pointing_u_v",
        litebird_pointing=("placeholder: constant identity boresight->ecliptic quaternion (the loader needs one)"
                           if pointing is None else "given"),
        litebird_band=("placeholder bandcenter_ghz 1, bandwidth_ghz 0 (the loader needs a centre > 0)"
                       if band_ghz is None else f"given: {center_ghz} GHz, width {width_ghz} GHz"),
    )
    return obs


def export_litebird(source, out, *, overwrite: bool = False, compression: str | None = "gzip",
                    positions: Mapping | None = None, **selection):
    """Every module-segment of a recording as ``<out>/<observation>.h5``, by ``write_list_of_observations``.

    Written in float64 (litebird_sim's default is float32); each file also
    holds ``mntes_t_ns`` and the ``mntes_stream`` attribute. Read back with
    :func:`read_litebird`, or ``litebird_sim.read_list_of_observations(files,
    tod_dtype=numpy.float64, limit_mpi_rank=False)``.

    Returns
    -------
    ExportSummary
        ``path`` is the directory.
    """
    lbs = _lbs()
    import h5py

    from mntes_stream.feeds.recorded import RecordedPower

    t_start = time.perf_counter()
    rec = RecordedPower(source, **selection)
    names, n = [], 0
    with c.output_dir(out, overwrite) as tmp:
        for name, k, block, rate in c.observation_blocks(rec, room_in=tmp):
            obs = to_litebird(block, name=name, sample_rate_hz=rate, segment=k, positions=positions)
            (path,) = lbs.write_list_of_observations(
                obs, tmp, tod_dtype=np.float64, file_name_mask=f"{name}.h5", start_index=len(names),
                collective_mpi_call=False, tod_fields=["tod"], gzip_compression=compression == "gzip")
            # Beside what litebird_sim writes: exact times and our metadata, which its loader leaves alone.
            with h5py.File(path, "a") as f:
                f.create_dataset("mntes_t_ns", data=obs.mntes_t_ns)
                if obs.mntes_sigma_p_w is not None:
                    f.create_dataset("mntes_sigma_p_w", data=obs.mntes_sigma_p_w)
                f.attrs["mntes_stream"] = json.dumps(obs.mntes_stream)
            names.append(name)
            n += block.p_opt_w.size
    return c.summary(out, rec, names, n, t_start)


def read_litebird(paths) -> list:
    """Observations of an export by ``litebird_sim.read_list_of_observations``, in float64, units W.

    Parameters
    ----------
    paths : directory, file, or list of files

    Returns
    -------
    list of litebird_sim.Observation
        In file-name order, each with ``mntes_t_ns`` and ``mntes_stream`` added from the file,
        and the TOD units set back to ``"W"`` (the loader, not knowing them, gives K_CMB).
    """
    lbs = _lbs()
    import h5py

    p = [Path(paths)] if isinstance(paths, (str, Path)) else [Path(x) for x in paths]
    files = sorted(f for x in p for f in (sorted(x.glob("*.h5")) if x.is_dir() else [x]))
    if not files:
        raise ConfigError(f"no .h5 files in {paths}")
    obs_list = lbs.read_list_of_observations(files, tod_dtype=np.float64, limit_mpi_rank=False, tod_fields=["tod"])
    for obs, f in zip(obs_list, files):
        with h5py.File(f, "r") as h:
            # The loader falls back to K_CMB for units it does not know ("W").
            for tod in obs.tod_list:
                if h[tod.name].attrs.get("units") == UNITS:
                    tod.units = UNITS
            if "mntes_t_ns" in h:
                obs.mntes_t_ns = h["mntes_t_ns"][:]
            obs.mntes_sigma_p_w = h["mntes_sigma_p_w"][:] if "mntes_sigma_p_w" in h else None
            if "mntes_stream" in h.attrs:
                obs.mntes_stream = json.loads(h.attrs["mntes_stream"])
    return obs_list
