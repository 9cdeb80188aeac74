"""Detector positions from a G3 run's ``BolometerProperties`` (Calibration frame), keyed by detector id.

The Wiring frame's map gives each bolometer name its readout channel, hence
its detector id (``b<board>m<module>c<channel>``); the Calibration frame's
``BolometerProperties`` give ``x_offset`` (in azimuth), ``y_offset`` (in
elevation) and ``pol_angle`` in G3 angle units. They are taken as
``xi = x_offset``, ``eta = y_offset``, ``gamma = pol_angle`` in radians: the
sign and axis conventions of SPT-3G's offsets and polarisation angles are
NOT reconciled here with TOAST's and sotodlib's xi/eta/gamma (both are small
offsets from the boresight, x along azimuth, y along elevation); check them
before using the positions for science.
"""

from __future__ import annotations

import numpy as np

from mntes_stream.errors import ConfigError

__all__ = ["positions_from_g3", "G3_NOTE"]

G3_NOTE = ("from G3 BolometerProperties: xi = x_offset, eta = y_offset, gamma = pol_angle (rad); SPT-3G's sign and "
           "axis conventions not reconciled with TOAST/sotodlib xi/eta/gamma")


def positions_from_g3(paths) -> dict:
    """``detector id -> (xi_rad, eta_rad, gamma_rad)`` from the first Wiring and Calibration frames of G3 files.

    Parameters
    ----------
    paths : path or list of paths
        G3 files (a run, or a calibration file holding both frames).

    Returns
    -------
    dict of str to (float, float, float)
        Bolometers with a finite x_offset, y_offset and pol_angle that the wiring map knows.

    Raises
    ------
    ConfigError
        No Wiring frame, no Calibration frame with ``BolometerProperties``, or no usable bolometer.
    """
    from mntes_stream.g3.files import read_frames
    from mntes_stream.g3.mapping import Wiring
    from mntes_stream.g3.runtime import spt3g

    core, _ = spt3g()
    wiring = props = None
    for frame in read_frames(paths):
        if wiring is None and frame.type == core.G3FrameType.Wiring:
            wiring = Wiring.from_frame(frame)
        elif props is None and frame.type == core.G3FrameType.Calibration and "BolometerProperties" in frame:
            props = frame["BolometerProperties"]
        if wiring is not None and props is not None:
            break
    if wiring is None:
        raise ConfigError(f"{paths}: no Wiring frame (WiringMap): cannot tell which bolometer is which detector")
    if props is None:
        raise ConfigError(f"{paths}: no Calibration frame with BolometerProperties")
    out = {}
    rad = core.G3Units.rad
    for name, p in props.items():
        vals = (p.x_offset / rad, p.y_offset / rad, p.pol_angle / rad)
        try:
            det = wiring.id_of(str(name))
        except KeyError:
            continue  # a bolometer not read out in this run
        if np.isfinite(vals).all():
            out[det] = tuple(float(v) for v in vals)
    if not out:
        raise ConfigError(f"{paths}: no wired bolometer has finite x_offset, y_offset and pol_angle")
    return out
