"""Readout-noise files (``mntes-stream noise RUN --out FILE``): JSON, per detector and per module.

Layout::

    {"format": "mntes-noise", "version": 1, "source": "...", "estimator": "...",
     "readout_noise_a": {"b0m0c000": 2.0e-12, ...},      # per detector, A per quadrature
     "by_module": {"b0m0": 2.0e-12, ...},                 # median of the module's detectors
     "channels": {"b0m0c000": {"sigma_counts_i": ..., "sigma_counts_q": ..., "samples": ...}, ...}}

:func:`load_noise` gives the mapping :func:`core.uncertainty.noise_model`
takes (detectors and modules together; a detector's own entry wins).
"""

from __future__ import annotations

import json
import math
from pathlib import Path

from mntes_stream.core.uncertainty import NOISE_FILE_FORMAT, NoiseModel, UncertaintySettings, noise_model
from mntes_stream.errors import ConfigError

NOISE_FILE_VERSION = 1


def write_noise(doc: dict, path: str | Path) -> None:
    """Write a noise document (whole: a temporary file renamed)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".partial")
    tmp.write_text(json.dumps(doc, indent=1, allow_nan=False) + "\n")
    tmp.replace(path)


def load_noise(path: str | Path) -> tuple[dict[str, float], str]:
    """Readout noise (A per quadrature) by detector id and by module, and the file's name for provenance.

    Raises
    ------
    ConfigError
        Unreadable file, another format, or a value that is not a finite number >= 0.
    """
    try:
        doc = json.loads(Path(path).read_text())
    except (OSError, ValueError) as exc:
        raise ConfigError(f"{path}: cannot read a noise file: {exc}") from None
    if not isinstance(doc, dict) or doc.get("format") != NOISE_FILE_FORMAT:
        raise ConfigError(f"{path}: not a noise file (format {NOISE_FILE_FORMAT!r} expected)")
    if doc.get("version") != NOISE_FILE_VERSION:
        raise ConfigError(f"{path}: noise file version {doc.get('version')!r}, this build reads {NOISE_FILE_VERSION}")
    out: dict[str, float] = {}
    for table in ("by_module", "readout_noise_a"):  # detectors last: their own entry wins
        entries = doc.get(table, {})
        if not isinstance(entries, dict):
            raise ConfigError(f"{path}: {table} must be a table of id -> A")
        for key, value in entries.items():
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < 0:
                raise ConfigError(f"{path}: {table}.{key}: expected a finite number >= 0 (A), got {value!r}")
            out[str(key)] = float(value)
    return out, str(path)


def noise_model_for(params, settings: UncertaintySettings | None = None, gradients=None) -> NoiseModel:
    """:func:`core.uncertainty.noise_model` with the settings' ``noise_file`` read (the converter's call);
    ``gradients``: the detectors' ``core.uncertainty.nominal_gradients``, if known."""
    settings = settings or UncertaintySettings()
    if settings.noise_file:
        measured, source = load_noise(settings.noise_file)
        return noise_model(params, settings, measured, source, gradients=gradients)
    return noise_model(params, settings, gradients=gradients)
