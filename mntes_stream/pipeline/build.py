"""Building a converter: the table cache (banks built from parameters, kept keyed by them).

Banks are kept in the table cache (``~/.cache/mntes-stream/tables`` by default) under a key of the
parameters, kind, table format, software version and the core's source digest
(:func:`~mntes_stream.pipeline.snapshot.build_fingerprint`), so a bank built by other code is never reused.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from mntes_stream import cache_root
from mntes_stream.io.cache import DEFAULT_MAX_MB

__all__ = ["cached_bank", "default_table_cache"]

log = logging.getLogger("mntes_stream.converter")


def default_table_cache() -> str:
    """The table cache the converter service and offline ``convert`` use unless told otherwise."""
    return os.path.join(cache_root(), "tables")


def cached_bank(kind: str, params: dict, table_cache: str, max_mb: float = DEFAULT_MAX_MB):
    """The bank of ``kind`` for ``params`` from the cache, or built and put there (a broken entry is rebuilt).

    Parameters
    ----------
    kind : {"table", "grid"}
    params : dict of str to DetectorParams
    table_cache : str
        The cache directory (``~`` expanded).
    max_mb : float
        The cache's size cap: after a write the least recently used entries beyond it are removed.
    """
    from mntes_stream import __version__
    from mntes_stream.core.tables import TABLE_FORMAT, build_bank, params_identity
    from mntes_stream.errors import MntesError
    from mntes_stream.io.cache import prune, touch
    from mntes_stream.io.tablefile import load_bank, save_bank
    from mntes_stream.pipeline.snapshot import build_fingerprint

    key = params_identity(list(params.values()), {"kind": kind, "format": TABLE_FORMAT, "software": __version__,
                                                  "code": build_fingerprint()})
    directory = Path(os.path.expanduser(table_cache))
    path = directory / f"{kind}-{key[:32]}.npz"
    if path.exists():
        try:
            bank = load_bank(path)  # verifies the content hash: a damaged entry is not used
            log.info("table bank %s from the cache %s", bank.identity[:12], path)
            touch(path)  # recently used: the last the size cap removes
            return bank
        except MntesError as exc:
            log.warning("table cache entry %s unusable (%s): rebuilding", path, exc)
    bank = build_bank(params, kind=kind)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        save_bank(bank, path)
        prune(directory, max_mb * 1e6, keep=(path,))
    except OSError as exc:  # a read-only home must not stop the converter
        log.warning("cannot write the table cache %s: %s", path, exc)
    return bank
