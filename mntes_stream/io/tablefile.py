"""Table bank files: one ``.npz`` per array, self-describing and hash-checked.

Contents (numpy ``.npz``, no pickles):

- ``__header__``: uint8 bytes of a JSON object: ``format`` ("mntes-tables"),
  ``version`` (the format version), kind, detector ids, the full detector
  parameters, domain and build options (:meth:`TableBank.header`);
- ``__identity__``: uint8 bytes of the sha256 hex identity;
- one entry per table array (layout in :mod:`mntes_stream.core.tables`).

Loading recomputes the identity from the contents and refuses the file
(:class:`SchemaError`) when it differs from the stored one, when the format
or version is not this build's, or when the file is not a readable archive.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
import zipfile
from pathlib import Path

import numpy as np

from mntes_stream.core.tables import TableBank
from mntes_stream.errors import ConfigError, SchemaError

__all__ = ["save_bank", "load_bank", "read_header"]

_HEADER = "__header__"
_IDENTITY = "__identity__"


def save_bank(bank: TableBank, path: str | Path) -> Path:
    """Write ``bank`` to ``path`` atomically (temp file + rename). Returns the path."""
    path = Path(path)
    payload = {name: np.asarray(a) for name, a in bank.arrays.items()}
    payload[_HEADER] = np.frombuffer(json.dumps(bank.header(), sort_keys=True).encode(), dtype=np.uint8)
    payload[_IDENTITY] = np.frombuffer(bank.identity.encode(), dtype=np.uint8)
    fd, tmp = tempfile.mkstemp(dir=path.parent if str(path.parent) else ".", prefix=path.name, suffix=".tmp")
    try:
        with os.fdopen(fd, "wb") as f:
            np.savez(f, **payload)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return path


@contextlib.contextmanager
def _open(path: Path):
    """The archive, read through our own file handle (np.load leaks its own on a bad file)."""
    if not path.exists():
        raise ConfigError(f"table file not found: {path}")
    with open(path, "rb") as f:
        try:
            npz = np.load(f, allow_pickle=False)
        except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
            raise SchemaError(f"{path}: not a readable table file ({type(exc).__name__}: {exc})") from None
        if not isinstance(npz, np.lib.npyio.NpzFile):
            raise SchemaError(f"{path}: not a table file (a single array, not an archive)")
        with npz:
            yield npz


def _header(npz, path: Path) -> tuple[dict, str]:
    try:
        header = json.loads(bytes(npz[_HEADER]).decode())
        stored = bytes(npz[_IDENTITY]).decode()
    except KeyError as exc:
        raise SchemaError(f"{path}: not a table file (missing {exc.args[0]})") from None
    except (zipfile.BadZipFile, ValueError, OSError, EOFError, UnicodeDecodeError) as exc:
        raise SchemaError(f"{path}: corrupted table file header ({type(exc).__name__}: {exc})") from None
    if not isinstance(header, dict):
        raise SchemaError(f"{path}: table file header is not an object")
    return header, stored


def read_header(path: str | Path) -> dict:
    """The JSON header and stored identity, without loading or checking the arrays."""
    path = Path(path)
    with _open(path) as npz:
        header, stored = _header(npz, path)
    return dict(header, identity=stored)


def load_bank(path: str | Path) -> TableBank:
    """Read and verify a table bank.

    Raises
    ------
    ConfigError
        The file does not exist.
    SchemaError
        Not a table file, another format version, corrupted, or its contents
        do not hash to the identity stored in it.
    """
    path = Path(path)
    with _open(path) as npz:
        header, stored = _header(npz, path)
        try:
            arrays = {name: npz[name] for name in npz.files if name not in (_HEADER, _IDENTITY)}
        except (zipfile.BadZipFile, ValueError, OSError, EOFError) as exc:
            raise SchemaError(f"{path}: corrupted table data ({type(exc).__name__}: {exc})") from None
    try:
        bank = TableBank.from_header(header, arrays)
    except (SchemaError, ConfigError) as exc:
        raise SchemaError(f"{path}: {exc}") from None
    if bank.identity != stored:
        raise SchemaError(
            f"{path}: contents hash to {bank.identity[:16]}..., the file says {stored[:16]}...: "
            "corrupted or edited; rebuild the tables"
        )
    return bank
