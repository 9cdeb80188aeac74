"""The lab's detector calibration from sotodlib's ``det_cal`` HDF5 (its own loader, the ``sotodlib`` extra).

sotodlib's ``site_pipeline.update_det_cal`` writes, per observation, a
``ResultSet`` of sodetlib's IV and bias-step results with
``sotodlib.io.metadata.write_dataset``; :func:`load_det_cal` reads one with
``sotodlib.io.metadata.read_dataset`` into :class:`core.calib.lab.LabCalibration`
by detector id. Fields used (sotodlib's names): ``readout_id``, ``r_n``,
``p_sat``, ``r_frac``, ``loopgain``, ``s_i`` (magnitude taken), ``p_bias``;
others are ignored, absent ones are "not measured", and non-finite values
(a failed fit) too.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from pathlib import Path

from mntes_stream.core.calib.lab import LabCalibration
from mntes_stream.core.ids import check_detector_id
from mntes_stream.errors import ConfigError, import_extra

# sotodlib field -> LabCalibration field
FIELDS = {"r_n": "r_n_ohm", "p_sat": "p_sat_w", "r_frac": "r_frac", "loopgain": "loop_gain", "s_i": "s_i_per_v",
          "p_bias": "p_bias_w"}


def load_det_cal(path: str | Path, dataset: str, id_map: Mapping[str, str] | None = None) -> dict[str, LabCalibration]:
    """The lab calibration of each detector in one ``det_cal`` dataset (an observation id).

    Parameters
    ----------
    path : str or Path
        The HDF5 file ``update_det_cal`` wrote.
    dataset : str
        The dataset (observation id) inside it.
    id_map : mapping readout_id -> detector id, optional
        Without it, readout ids must be detector ids themselves.

    Raises
    ------
    MissingExtraError
        sotodlib is not installed.
    ConfigError
        Unreadable file or dataset, no ``readout_id`` column, an id that is not a safe detector id.
    """
    meta = import_extra("sotodlib.io.metadata", "sotodlib")
    where = f"{path} [{dataset}]"
    if not Path(path).is_file():
        raise ConfigError(f"{path}: no such file")
    try:
        rs = meta.read_dataset(str(path), dataset)
    except (OSError, KeyError, ValueError) as exc:
        raise ConfigError(f"{where}: cannot read a det_cal dataset: {exc}") from None
    keys = list(rs.keys)
    if "readout_id" not in keys:
        raise ConfigError(f"{where}: no readout_id column (columns: {', '.join(map(str, keys))})")
    col = {k: keys.index(k) for k in keys}
    out: dict[str, LabCalibration] = {}
    for row in rs.rows:
        rid = str(row[col["readout_id"]])
        det = id_map.get(rid) if id_map is not None else rid
        if det is None:
            continue  # a readout channel the map does not name: not one of ours
        det = check_detector_id(det, where)
        values = {}
        for src, dst in FIELDS.items():
            if src in col:
                try:
                    v = float(row[col[src]])
                except (TypeError, ValueError):
                    raise ConfigError(f"{where}: {rid} {src}: expected a number, got {row[col[src]]!r}") from None
                if math.isfinite(v):
                    values[dst] = abs(v) if src == "s_i" else v
        out[det] = LabCalibration(detector_id=det, source=where, **values)
    return out
