"""Calibration files: measurements (MCAP of msgpack messages), truth and fit results (TOML).

Measurement file (one detector or a whole array)
------------------------------------------------
An MCAP file written with :class:`mntes_stream.io.mcap.McapFileWriter`:
every message is an msgpack map whose JSON Schema is stored as its channel's
schema (``schemas/calib_*.v1.json``), so the file explains itself.

- topic ``calib/detector``: one ``mntes.calib_detector`` per detector (bias
  frequency, electronics gain magnitude, fiducial conditions);
- topic ``calib/<kind>``: one ``mntes.calib_<kind>`` per sweep (the swept
  condition as an array, the four others as numbers, counts and their noise);
- metadata record ``mntes.calibration``: campaign description (strings).

Truth (simulated campaigns only) is a separate parameter file whose
``[metadata]`` says ``truth = true`` and holds the readout parameters that
``DetectorParams`` has no field for. Fit results are a parameter file that
``io.paramfile.load_params`` reads directly, plus a covariance sidecar (JSON).
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Mapping
from pathlib import Path

import numpy as np

from mntes_stream import __version__
from mntes_stream.core.calib.fit import DetectorFit
from mntes_stream.core.calib.forward import PARAM_NAMES, PARAM_UNITS, Readout
from mntes_stream.core.calib.measurements import (
    CONDITIONS,
    KINDS,
    SWEPT_AXIS,
    Campaign,
    DetectorCalibration,
    Sweep,
    assemble_campaign,
)
from mntes_stream.core.params import DetectorParams
from mntes_stream.errors import ConfigError, SchemaError
from mntes_stream.io.codec import decode_array, encode_array, pack, unpack

__all__ = [
    "HEADER_SCHEMA",
    "CAMPAIGN_METADATA",
    "COVARIANCE_SCHEMA",
    "sweep_schema",
    "encode_header",
    "encode_sweep",
    "decode_message",
    "write_campaign",
    "read_campaign",
    "write_truth",
    "read_truth",
    "fit_metadata",
    "write_fit_params",
    "write_covariance",
    "read_covariance",
]

HEADER_SCHEMA = "mntes.calib_detector"
CAMPAIGN_METADATA = "mntes.calibration"
COVARIANCE_SCHEMA = "mntes-calib-covariance"
COVARIANCE_VERSION = 1
_HEADER_TOPIC = "calib/detector"
_KIND_OF_SCHEMA = {f"mntes.calib_{k}": k for k in KINDS}


def sweep_schema(kind: str) -> str:
    return f"mntes.calib_{kind}"


# --------------------------------------------------------------------------- messages


def encode_header(det: DetectorCalibration, t_ns: int | None = None) -> bytes:
    return pack(HEADER_SCHEMA, {
        "detector_id": det.detector_id,
        "t_ns": int(time.time_ns() if t_ns is None else t_ns),
        "bias_freq_hz": det.bias_freq_hz,
        "gain_abs_a_per_count": det.gain_abs_a_per_count,
        "p_opt_w": det.p_opt_w,
        "t_bath_k": det.t_bath_k,
        "b_field_t": det.b_field_t,
    })


def encode_sweep(sweep: Sweep, seq: int = 0, t_ns: int | None = None) -> bytes:
    body = {"detector_id": sweep.detector_id, "seq": int(seq), "t_ns": int(time.time_ns() if t_ns is None else t_ns)}
    for c in CONDITIONS:
        body[c] = encode_array(np.asarray(sweep.swept, dtype="<f8")) if c == sweep.axis else float(sweep.fixed[c])
    body["counts"] = encode_array(np.asarray(sweep.counts, dtype="<c16"))
    body["sigma_counts"] = encode_array(np.asarray(sweep.sigma_counts, dtype="<f8"))
    return pack(sweep_schema(sweep.kind), body)


def _number(msg: dict, name: str, where: str) -> float:
    value = msg.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise SchemaError(f"{where}: {name} must be a number, got {value!r}")
    return float(value)


def decode_message(payload: bytes) -> DetectorCalibration | Sweep:
    """A calibration message back to its core object; SchemaError names what is wrong."""
    msg = unpack(payload, (HEADER_SCHEMA, *_KIND_OF_SCHEMA))
    det_id = msg.get("detector_id")
    if not isinstance(det_id, str) or not det_id:
        raise SchemaError(f"{msg['schema']}: detector_id must be a non-empty string")
    where = f"{msg['schema']} of {det_id}"
    try:
        if msg["schema"] == HEADER_SCHEMA:
            return DetectorCalibration(
                det_id, *(_number(msg, k, where) for k in ("bias_freq_hz", "gain_abs_a_per_count", "p_opt_w", "t_bath_k", "b_field_t"))
            )
        kind = _KIND_OF_SCHEMA[msg["schema"]]
        axis = SWEPT_AXIS[kind]
        swept = decode_array(msg.get(axis), f"{where}.{axis}", dtype="<f8", ndim=1)
        counts = decode_array(msg.get("counts"), f"{where}.counts", dtype="<c16", ndim=1)
        sigma = decode_array(msg.get("sigma_counts"), f"{where}.sigma_counts", dtype="<f8", ndim=1)
        fixed = {c: _number(msg, c, where) for c in CONDITIONS if c != axis}
        return Sweep(kind, det_id, swept, fixed, counts, sigma)
    except ConfigError as exc:
        raise SchemaError(f"{where}: {exc}") from None


# --------------------------------------------------------------------------- MCAP campaign files


def write_campaign(path: str | Path, campaign: Campaign, *, overwrite: bool = False) -> int:
    """Write a campaign to one MCAP file; returns the number of messages."""
    from mntes_stream.io.mcap import McapFileWriter, writer_description

    path = Path(path)
    if path.exists():
        if not overwrite:
            raise ConfigError(f"{path} exists (use overwrite / --force)")
        path.unlink()
    meta = {CAMPAIGN_METADATA: {str(k): str(v) for k, v in campaign.metadata.items()},
            "mntes.recording": writer_description()}
    n = 0
    t0 = time.time_ns()
    with McapFileWriter(path, metadata=meta) as w:
        for det in campaign.detectors.values():
            w.write(_HEADER_TOPIC, encode_header(det, t0), t0 + n)
            n += 1
            seqs: dict[str, int] = {}
            for s in det.sweeps:
                seq = seqs.get(s.kind, 0)
                seqs[s.kind] = seq + 1
                w.write(f"calib/{s.kind}", encode_sweep(s, seq, t0), t0 + n)
                n += 1
    return n


def read_campaign(path: str | Path) -> Campaign:
    """Read a campaign file (or a directory/list of MCAP files).

    Raises SchemaError for a malformed calibration message; sweeps whose
    detector has no header are kept as :attr:`Campaign.orphans` (flagged by the fit).
    """
    from mntes_stream.io.mcap import iter_messages, read_metadata

    headers, sweeps = [], []
    try:
        for rec in iter_messages(path):
            if rec.schema_name != HEADER_SCHEMA and rec.schema_name not in _KIND_OF_SCHEMA:
                continue
            obj = decode_message(rec.payload)
            (headers if isinstance(obj, DetectorCalibration) else sweeps).append(obj)
        meta = {}
        for m in read_metadata(path):
            if m.name == CAMPAIGN_METADATA:
                meta.update(m.data)
    except SchemaError as exc:
        raise SchemaError(f"{path}: {exc}") from None
    if not headers and not sweeps:
        raise SchemaError(f"{path}: no calibration messages")
    return assemble_campaign(headers, sweeps, meta)


# --------------------------------------------------------------------------- truth


def write_truth(path: str | Path, truth: Mapping[str, tuple[DetectorParams, Readout]], metadata: Mapping | None = None) -> None:
    """The simulation truth, as a parameter file clearly marked as such."""
    from mntes_stream.io.paramfile import dump_params

    meta = {
        "truth": True,
        "note": "SIMULATION TRUTH: the parameters the campaign was generated from; for comparisons only",
        "readout": {det_id: r.to_dict() for det_id, (_, r) in truth.items()},
    }
    meta.update(dict(metadata or {}))
    dump_params([p for p, _ in truth.values()], path, metadata=meta)


def read_truth(path: str | Path) -> dict[str, tuple[DetectorParams, Readout]]:
    import tomllib

    from mntes_stream.io.paramfile import load_params

    params = load_params(path)
    doc = tomllib.loads(Path(path).read_text())
    meta = doc.get("metadata", {})
    if meta.get("truth") is not True:
        raise ConfigError(f"{path}: not a truth file (metadata.truth is not true)")
    readout = meta.get("readout", {})
    out = {}
    for det_id, p in params.items():
        r = readout.get(det_id)
        if not isinstance(r, dict):
            raise ConfigError(f"{path}: no readout parameters for {det_id}")
        out[det_id] = (p, Readout(**{k: float(v) for k, v in r.items()}))
    return out


# --------------------------------------------------------------------------- fit results


def _finite_or_str(x: float):
    return float(x) if math.isfinite(x) else str(x)


def fit_metadata(fits: Mapping[str, DetectorFit], transition: str, source: str = "") -> dict:
    """The ``[metadata.calibration]`` table of a fitted parameter file."""
    by_status = {s: sorted(d for d, f in fits.items() if f.status == s) for s in ("ok", "flagged", "failed")}
    per_det = {}
    for det_id, f in fits.items():
        entry: dict = {"status": f.status}
        if f.reasons:
            entry["reasons"] = list(f.reasons)
        if f.notes:
            entry["notes"] = list(f.notes)
        if f.theta is not None:
            entry["chi2"] = _finite_or_str(f.chi2)
            entry["ndf"] = int(f.ndf)
            entry["value"] = {n: float(v) for n, v in zip(PARAM_NAMES, f.theta)}
            entry["sigma"] = {n: _finite_or_str(float(s)) for n, s in zip(PARAM_NAMES, f.sigma)}
        per_det[det_id] = entry
    return {
        "calibration": {
            "software": f"mntes-stream {__version__}",
            "source": str(source),
            "transition": transition,
            "units": {n: PARAM_UNITS[n] for n in PARAM_NAMES},
            "gauge": "|gain_a_per_count| taken from the campaign header (the counts fix every other "
                     "parameter relative to it; conversion to watts does not depend on it)",
            "excluded": "detectors with status flagged or failed are NOT in [detectors]; see reasons",
            "n_ok": len(by_status["ok"]),
            "n_flagged": len(by_status["flagged"]),
            "n_failed": len(by_status["failed"]),
            "flagged": by_status["flagged"],
            "failed": by_status["failed"],
            "fit": per_det,
        }
    }


def write_fit_params(path: str | Path, fits: Mapping[str, DetectorFit], params: Mapping[str, DetectorParams],
                     transition: str, source: str = "") -> None:
    """Parameter file of the usable detectors (``params``), with every fit's record as metadata."""
    from mntes_stream.io.paramfile import dump_params

    if not params:
        raise ConfigError("no detector passed the calibration fit; nothing to write (see the flagged reasons)")
    dump_params(list(params.values()), path, metadata=fit_metadata(fits, transition, source))


def write_covariance(path: str | Path, fits: Mapping[str, DetectorFit]) -> None:
    """Covariance sidecar (JSON): parameter order, values and full covariance per fitted detector."""
    doc = {
        "schema": COVARIANCE_SCHEMA,
        "version": COVARIANCE_VERSION,
        "param_names": list(PARAM_NAMES),
        "units": [PARAM_UNITS[n] for n in PARAM_NAMES],
        "detectors": {
            d: {"status": f.status, "theta": f.theta.tolist(), "cov": f.cov.tolist()}
            for d, f in fits.items() if f.theta is not None and f.cov is not None
        },
    }
    Path(path).write_text(json.dumps(doc, indent=1, allow_nan=True))


def read_covariance(path: str | Path) -> tuple[tuple[str, ...], dict[str, tuple[np.ndarray, np.ndarray]]]:
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise ConfigError(f"{path}: cannot read covariance file: {exc}") from None
    if doc.get("schema") != COVARIANCE_SCHEMA or doc.get("version") != COVARIANCE_VERSION:
        raise ConfigError(f"{path}: not a {COVARIANCE_SCHEMA} v1 file")
    try:
        dets = {d: (np.array(e["theta"], float), np.array(e["cov"], float)) for d, e in doc["detectors"].items()}
    except (KeyError, TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: malformed covariance entry: {exc}") from None
    return tuple(doc["param_names"]), dets

