"""The converter as built at its last start, kept on disk: a restart loads it instead of building it again.

Building a converter for 5,120 detectors reads and checks every detector's
parameters, loads (or builds) their table bank and solves two operating
points per detector for its flag thresholds: tens of seconds on a busy
2-core machine. All of it depends only on the parameter and table files,
the converter's kind and part of the focal plane, and the software; a
snapshot keyed by exactly those (the files by the SHA-256 of their bytes)
gives the same converter back in a fraction of a second.

A snapshot is a pickle, and loading a pickle runs what it says: it is only
loaded from a file owned by this user that no one else may write, in a
directory no one else may write (the table cache, ``~/.cache/mntes-stream/tables``
by default). Anything wrong with it (other owner, damaged, another software
version) and it is ignored with a warning: the converter is built as before.
"""

from __future__ import annotations

import copyreg
import functools
import hashlib
import logging
import os
import pickle
import platform
import stat
import tempfile
import types
from pathlib import Path

import numpy as np

from mntes_stream.io.cache import prune, touch

__all__ = ["snapshot_key", "load_snapshot", "save_snapshot", "build_fingerprint"]

log = logging.getLogger("mntes_stream.converter")


def _mappingproxy(d: dict) -> types.MappingProxyType:
    return types.MappingProxyType(d)


# The converter's read-only views (bank arrays) pickle as the dict they show.
copyreg.pickle(types.MappingProxyType, lambda m: (_mappingproxy, (dict(m),)))


def _digest(path: str) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


@functools.cache
def build_fingerprint() -> str:
    """SHA-256 of the source of ``mntes_stream/core/*.py``: what builds tables, thresholds and converters.

    Part of every cache key (table banks, converter snapshots): the version number
    does not change with every edit of the code, and a bank or converter built by
    other code must not be taken for this code's (its identity would differ).
    """
    h = hashlib.sha256()
    for path in sorted((Path(__file__).resolve().parent.parent / "core").glob("*.py")):
        h.update(path.name.encode() + b"\0" + path.read_bytes() + b"\0")
    return h.hexdigest()


def snapshot_key(spec) -> str | None:
    """What the converter built from ``spec`` (``pipeline.build.ConverterSpec``) depends on: the bytes of its
    parameters and tables, kind, part of the focal plane, software. None for parameters given in memory."""
    from mntes_stream import __version__
    from mntes_stream.core.tables import TABLE_FORMAT

    if spec.params:
        return None
    params = _digest(spec.params_file) if spec.params_file else \
        hashlib.sha256(spec.params_toml.encode()).hexdigest() if spec.params_toml else ""
    parts = [
        f"params={params}",
        f"tables={_digest(spec.tables) if spec.tables else ''}",
        f"kind={spec.kind}", f"boards={list(spec.boards)}", f"modules={list(spec.modules)}", f"shard={spec.shard}",
        f"software={__version__}", f"code={build_fingerprint()}", f"format={TABLE_FORMAT}", f"numpy={np.__version__}",
        f"python={platform.python_version()}", f"pickle={pickle.HIGHEST_PROTOCOL}",
    ] + (["drop_untaken"] if spec.drop_untaken else []) + ([f"options={sorted(spec.options)!r}"] if spec.options else [])
    return hashlib.sha256("\n".join(parts).encode()).hexdigest()


def _path(spec, key: str) -> Path:
    return Path(os.path.expanduser(spec.table_cache)) / f"converter-{spec.kind}-{key[:32]}.pickle"


def _private(path: Path) -> str | None:
    """Why ``path`` must not be trusted (None: owned by this user, writable by no one else)."""
    st = path.stat()
    if st.st_uid != os.getuid():
        return f"{path} is owned by uid {st.st_uid}, not by this user"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"{path} is writable by others"
    return None


def load_snapshot(spec):
    """``(key, (params, streams, converter, params_toml))`` saved by an earlier build of ``spec``
    (``pipeline.build.ConverterSpec``) with the same key, else ``(key, None)`` (key None: no cache, or nothing to
    key it by); ``params_toml``: the converter's parameters as ``params_to_toml`` wrote them."""
    if not spec.table_cache:
        return None, None
    try:
        key = snapshot_key(spec)
    except OSError:  # a missing file: the normal path says so, once
        return None, None
    if key is None:
        return None, None
    path = _path(spec, key)
    if not path.exists():
        return key, None
    try:
        why = _private(path.parent) or _private(path)
        if why:
            log.warning("converter snapshot not loaded: %s", why)
            return key, None
        with open(path, "rb") as f:
            value = pickle.load(f)
        touch(path)  # recently used: the last the size cap removes
        params, streams, conv, text = value
        if not hasattr(conv, "convert") or not hasattr(conv, "detector_ids") or not isinstance(text, str):
            raise TypeError(f"not a converter: {type(conv).__name__}")
    except Exception as exc:  # damaged, truncated, or from code that moved: build instead
        log.warning("converter snapshot %s unusable (%s: %s): building", path, type(exc).__name__, exc)
        return key, None
    log.info("converter %s loaded from the snapshot %s", str(conv.identity)[:12], path)
    return key, (params, streams, conv, text)


def save_snapshot(spec, key: str | None, params, streams, conv) -> None:
    """Keep what :func:`load_snapshot` gives back (best effort: a read-only cache only logs)."""
    if not spec.table_cache or key is None:
        return
    from mntes_stream.io.paramfile import params_to_toml

    path = _path(spec, key)
    try:
        path.parent.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd, tmp = tempfile.mkstemp(prefix=".snapshot-", dir=path.parent)  # mode 0600
        try:
            with os.fdopen(fd, "wb") as f:
                text = params_to_toml(list(conv.params)) if getattr(conv, "params", None) else ""
                pickle.dump((params, streams, conv, text), f, protocol=pickle.HIGHEST_PROTOCOL)
            os.replace(tmp, path)
        except BaseException:
            os.unlink(tmp)
            raise
        prune(path.parent, spec.table_cache_max_mb * 1e6, keep=(path,))
    except (OSError, pickle.PicklingError, TypeError, AttributeError) as exc:
        log.warning("cannot write the converter snapshot %s: %s", path, exc)
