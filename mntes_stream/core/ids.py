"""Detector identity: one naming convention from readout coordinates to ids."""

from __future__ import annotations

import re

from mntes_stream.errors import ConfigError

_PATTERN = re.compile(r"^b(\d+)m(\d+)c(\d+)$")
# Setup, sensor, service and file-prefix names: one key segment, no wildcards.
NAME_PATTERN = re.compile(r"\A[A-Za-z0-9_.\-]+\Z")  # \Z: no trailing newline slips through


def detector_id(board: int, module: int, channel: int) -> str:
    """``b{board}m{module}c{channel:03d}``, the id used in parameter files.

    >>> detector_id(0, 3, 7)
    'b0m3c007'
    >>> parse_detector_id(detector_id(12, 1, 127))
    (12, 1, 127)"""
    return f"b{int(board)}m{int(module)}c{int(channel):03d}"


def parse_detector_id(det_id: str) -> tuple[int, int, int]:
    """Inverse of :func:`detector_id`."""
    m = _PATTERN.match(det_id)
    if not m:
        raise ConfigError(f"detector id {det_id!r} is not of the form b<board>m<module>c<channel>")
    return int(m.group(1)), int(m.group(2)), int(m.group(3))
