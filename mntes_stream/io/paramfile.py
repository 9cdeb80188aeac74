"""Detector parameter files (TOML): shared defaults plus per-detector overrides.

Format (``version`` is the file format version)::

    schema = "mntes-params"
    version = 1

    [defaults]            # optional; any parameter key, or preset = "table1"
    preset = "table1"
    t_bath_k = 0.1

    [detectors.b0m0c000]  # one table per detector; keys override defaults
    t_c_k = 0.1812
    z_thev_ohm = [0.05, 0.05]   # complex values as [re, im]

Keys are the fields of ``DetectorParams`` plus the transition keys
(``transition = "arctan" | "tabulated"``, ``t_c_k``, ``iqr_k``, ``r_n_ohm``,
``transition_t_k``, ``transition_r_ohm``).
"""

from __future__ import annotations

import tomllib
from pathlib import Path

from mntes_stream.core.ids import check_detector_id
from mntes_stream.core.params import PRESETS, DetectorParams, params_from_dict
from mntes_stream.errors import ConfigError

__all__ = ["PARAMS_SCHEMA", "PARAMS_VERSION", "load_params", "dump_params", "params_to_toml"]

PARAMS_SCHEMA = "mntes-params"
PARAMS_VERSION = 1


def _expand_preset(d: dict, where: str) -> dict:
    if not isinstance(d, dict):
        raise ConfigError(f"{where} must be a table of parameter values, got {d!r}"[:300])
    d = dict(d)
    preset = d.pop("preset", None)
    if preset is None:
        return d
    if not isinstance(preset, str) or preset not in PRESETS:
        raise ConfigError(f"{where}: unknown preset {preset!r} (known: {sorted(PRESETS)})")
    base = PRESETS[preset]().to_dict()
    base.pop("detector_id")
    base.update(d)
    return base


def parse_params(doc: dict, source: str = "<params>") -> dict[str, DetectorParams]:
    """Detectors (in file order) from an already-parsed TOML document."""
    if doc.get("schema") != PARAMS_SCHEMA:
        raise ConfigError(f"{source}: schema must be {PARAMS_SCHEMA!r}, got {doc.get('schema')!r}")
    if doc.get("version") != PARAMS_VERSION:
        raise ConfigError(
            f"{source}: unsupported parameter file version {doc.get('version')!r} (this build reads {PARAMS_VERSION})"
        )
    unknown_top = set(doc) - {"schema", "version", "defaults", "detectors", "metadata"}
    if unknown_top:
        raise ConfigError(f"{source}: unknown top-level key(s) {sorted(unknown_top)}")
    defaults = _expand_preset(doc.get("defaults", {}), f"{source} [defaults]")
    detectors = doc.get("detectors", {})
    if not isinstance(detectors, dict) or not detectors:
        raise ConfigError(f"{source}: no [detectors.<id>] tables")
    out: dict[str, DetectorParams] = {}
    for det_id, overrides in detectors.items():
        check_detector_id(det_id, source)
        if not isinstance(overrides, dict):
            raise ConfigError(f"{source}: detectors.{det_id} must be a table")
        merged = dict(defaults)
        merged.update(_expand_preset(overrides, f"{source} [detectors.{det_id}]"))
        merged["detector_id"] = det_id
        out[det_id] = params_from_dict(merged, f"{source} [detectors.{det_id}]")
    return out


def load_params(path: str | Path) -> dict[str, DetectorParams]:
    """Read a parameter file; raises ConfigError with the file and detector named."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise ConfigError(f"parameter file not found: {path}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"{path}: not a text (UTF-8 TOML) file") from None
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(f"{path}: not valid TOML: {exc}") from None
    return parse_params(doc, str(path))


def params_to_toml(params: list[DetectorParams], metadata: dict | None = None) -> str:
    """TOML text for a list of detectors (every value explicit, no defaults).

    Writing 5,120 detectors takes about 0.6 s: a caller that has the text already (a converter
    restarted from its snapshot, ``service/snapshot.py``) passes it on instead of writing it again.
    """
    import tomli_w

    doc: dict = {"schema": PARAMS_SCHEMA, "version": PARAMS_VERSION}
    if metadata:
        doc["metadata"] = metadata
    doc["detectors"] = {}
    for p in params:
        d = p.to_dict()
        det_id = d.pop("detector_id")
        doc["detectors"][det_id] = d
    return tomli_w.dumps(doc)


def dump_params(params: list[DetectorParams], path: str | Path, metadata: dict | None = None) -> None:
    Path(path).write_text(params_to_toml(params, metadata))
