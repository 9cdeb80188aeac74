"""Detector identity: one naming convention from readout coordinates to ids."""

from __future__ import annotations

import re

from mntes_stream.errors import ConfigError

_PATTERN = re.compile(r"\Ab(\d+)m(\d+)c(\d+)\Z")
# Setup, sensor, service and file-prefix names: one key segment, no wildcards.
NAME_PATTERN = re.compile(r"\A[A-Za-z0-9_.\-]+\Z")  # \Z: no trailing newline slips through
# Detector ids end up in file names, HDF5 paths and zenoh keys downstream: one safe name, never a path.
DETECTOR_ID_PATTERN = re.compile(r"\A[A-Za-z0-9_][A-Za-z0-9_.\-]{0,127}\Z")


def detector_id(board: int, module: int, channel: int) -> str:
    """``b{board}m{module}c{channel:03d}``, the id used in parameter files.

    >>> detector_id(0, 3, 7)
    'b0m3c007'
    >>> parse_detector_id(detector_id(12, 1, 127))
    (12, 1, 127)"""
    return f"b{int(board)}m{int(module)}c{int(channel):03d}"


def check_detector_id(det_id, where: str = "") -> str:
    """``det_id`` if it is a safe id (letters, digits, ``_ . -``, not starting with ``.``, up to 128 characters).

    >>> check_detector_id("b0m3c007")
    'b0m3c007'
    >>> check_detector_id("../../x", "p.toml")
    Traceback (most recent call last):
    ...
    mntes_stream.errors.ConfigError: p.toml: detector id '../../x' is not a safe name (letters, digits, '_', '.', '-'; not starting with '.'; up to 128 characters)
    """
    if not isinstance(det_id, str) or not DETECTOR_ID_PATTERN.match(det_id):
        raise ConfigError(f"{where + ': ' if where else ''}detector id {det_id!r} is not a safe name (letters, digits, "
                          "'_', '.', '-'; not starting with '.'; up to 128 characters)")
    return det_id


def parse_detector_id(det_id: str) -> tuple[int, int, int]:
    """Inverse of :func:`detector_id`."""
    m = _PATTERN.match(det_id)
    if not m:
        raise ConfigError(f"detector id {det_id!r} is not of the form b<board>m<module>c<channel>")
    return int(m.group(1)), int(m.group(2)), int(m.group(3))


def is_channel_id(det_id: str) -> bool:
    """True if ``det_id`` has the b<board>m<module>c<channel> form (else it is a name, e.g. a board's).

    >>> is_channel_id("b10m3c007"), is_channel_id("Lab10.3.07")
    (True, False)"""
    return bool(_PATTERN.match(det_id))
