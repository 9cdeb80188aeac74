"""The user's cache on disk: what is in it, how big, bounded by size, cleared on request.

Three parts live under :func:`mntes_stream.cache_root` (``~/.cache/mntes-stream``):

- ``tables/``: table banks built from parameter files (``<kind>-<key>.npz``) and
  converters as built (``converter-<kind>-<key>.pickle``, ``pipeline/snapshot.py``).
  Every new parameter file, kind or software version adds entries (5-7 MB for
  256 detectors, ~130 MB for 5,000), so the part is pruned to a size cap after
  each write, least recently used first (a load touches its entry).
- ``numba/``: the compiled kernels (a few MB per software version).

``mntes-stream cache`` shows the parts and their sizes; ``--clear`` empties them.
"""

from __future__ import annotations

import logging
import os
import shutil
from dataclasses import dataclass
from pathlib import Path

from mntes_stream import cache_root

__all__ = ["PARTS", "DEFAULT_MAX_MB", "CachePart", "usage", "prune", "touch", "clear"]

log = logging.getLogger("mntes_stream.cache")

#: the parts of the cache, each a folder under the cache root, and what it holds
PARTS = {"tables": "table banks and converters as built, for fast starts",
         "numba": "compiled conversion kernels"}
#: the table cache's size cap unless configured (``[converter] table_cache_max_mb``)
DEFAULT_MAX_MB = 2048.0


@dataclass(frozen=True)
class CachePart:
    """One folder of the cache: ``name``, ``path``, ``files`` (count), ``bytes``, ``what`` it holds."""

    name: str
    path: str
    files: int
    bytes: int
    what: str


def _files(directory: Path) -> list[Path]:
    try:
        return [p for p in directory.rglob("*") if p.is_file()]
    except OSError:
        return []


def usage(root: str | None = None) -> list[CachePart]:
    """Every part of the cache under ``root`` (default: the user's), present or not."""
    base = Path(root or cache_root())
    out = []
    for name, what in PARTS.items():
        files = _files(base / name)
        size = 0
        for f in files:
            try:
                size += f.stat().st_size
            except OSError:  # removed meanwhile (another process pruning)
                pass
        out.append(CachePart(name, str(base / name), len(files), size, what))
    return out


def touch(path: Path | str) -> None:
    """Mark an entry as just used (what :func:`prune` keeps longest); a missing file is no error."""
    try:
        os.utime(path)
    except OSError:
        pass


def prune(directory: Path | str, max_bytes: float, keep: tuple = ()) -> list[Path]:
    """Delete the least recently used files of ``directory`` until it holds at most ``max_bytes``.

    ``keep``: paths never deleted (what the caller is using). Files another
    process removes meanwhile are skipped. Returns the deleted paths.
    """
    keep_set = {Path(k).resolve() for k in keep}
    entries = []
    for f in _files(Path(directory)):
        try:
            st = f.stat()
        except OSError:
            continue
        entries.append((st.st_mtime, st.st_size, f))
    total = sum(size for _, size, _ in entries)
    removed = []
    for _, size, f in sorted(entries, key=lambda e: e[0]):
        if total <= max_bytes:
            break
        if f.resolve() in keep_set:
            continue
        try:
            f.unlink()
        except OSError:
            continue
        total -= size
        removed.append(f)
    if removed:
        log.info("cache %s over %.0f MB: removed %d least recently used entries", directory, max_bytes / 1e6,
                 len(removed))
    return removed


def clear(parts: tuple[str, ...] = tuple(PARTS), root: str | None = None) -> int:
    """Delete the named parts of the cache; returns the bytes freed."""
    freed = 0
    for part in usage(root):
        if part.name in parts and os.path.isdir(part.path):
            freed += part.bytes
            shutil.rmtree(part.path, ignore_errors=True)
    return freed

