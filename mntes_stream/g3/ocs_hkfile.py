"""OCS HK G3 files (``--hk FILE|DIR``), read with spt3g 1.0.2 alone.

The aggregator's files hold frames with ``hkagg_type`` 0 (session), 1
(status: the providers, each with its ``description``, the feed address) and
2 (data: ``blocks``, a vector of ``G3TimesampleMap``, with ``block_names``,
``prov_id`` and, written by ocs's aggregator, ``address``). A field's full
name is the feed address, a dot, and the field's key in its block.
"""

from __future__ import annotations

import difflib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mntes_stream.errors import ConfigError, SchemaError

__all__ = ["HkSeries", "hk_files", "read_fields"]

_DATA, _STATUS = 2, 1
_G3_TICK_NS = 10  # spt3g's time unit: G3Time ticks are 10 ns


@dataclass(frozen=True)
class HkSeries:
    """The readings of one OCS field: times (ns since the epoch, increasing) and values as written."""

    name: str
    t_ns: np.ndarray
    value: np.ndarray

    def __len__(self) -> int:
        return int(self.t_ns.size)


def hk_files(path) -> list[Path]:
    """The HK G3 files of ``path``: a file, or every ``*.g3`` under a directory (the aggregator's
    ``<5 digits>/<ctime>.g3`` tree), in name order, which is time order."""
    p = Path(path)
    if p.is_dir():
        files = sorted(p.rglob("*.g3"), key=lambda f: (f.name, str(f)))
        if not files:
            raise ConfigError(f"--hk {p}: no .g3 files in it (nor below it)")
        return files
    if not p.exists():
        raise ConfigError(f"--hk {p}: no such file or directory")
    return [p]


def read_fields(path, names) -> dict[str, HkSeries]:
    """The readings of each full field name in ``names`` from OCS HK file(s) ``path``.

    Raises
    ------
    ConfigError
        A file that is not OCS HK (no ``hkagg_type`` frames), or a field no
        file holds (with the closest names that exist).
    SchemaError
        A frame spt3g cannot decode.
    """
    from mntes_stream.g3.runtime import spt3g

    core, _ = spt3g()
    names = list(dict.fromkeys(names))
    want = {n.rpartition(".")[0]: set() for n in names}
    for n in names:
        want[n.rpartition(".")[0]].add(n.rpartition(".")[2])
    times: dict[str, list] = {n: [] for n in names}
    values: dict[str, list] = {n: [] for n in names}
    seen: set[str] = set()
    for f in hk_files(path):
        providers: dict[int, str] = {}
        hk_frames = 0
        try:
            for frame in core.G3File(str(f)):
                if "hkagg_type" not in frame:
                    continue
                hk_frames += 1
                kind = frame["hkagg_type"]
                if kind == _STATUS:
                    providers = {int(p["prov_id"].value): str(p["description"].value) for p in frame["providers"]}
                elif kind == _DATA:
                    address = str(frame["address"]) if "address" in frame else providers.get(int(frame["prov_id"]), "")
                    for block in frame["blocks"]:
                        keys = list(block.keys())
                        seen.update(f"{address}.{k}" for k in keys)
                        for k in want.get(address, ()):
                            if k in keys:
                                times[f"{address}.{k}"].append(np.asarray(block.times, dtype=np.int64))
                                values[f"{address}.{k}"].append(np.asarray(block[k], dtype=np.float64))
        except RuntimeError as exc:  # spt3g's own read error
            raise SchemaError(f"--hk {f}: spt3g cannot read it: {exc}", "hk_file") from None
        if not hk_frames:
            raise ConfigError(f"--hk {f}: not an OCS HK file (no frame has hkagg_type)")
    out = {}
    for n in names:
        if not times[n]:
            near = difflib.get_close_matches(n, sorted(seen), n=3, cutoff=0.5)
            hint = f"; closest: {', '.join(near)}" if near else (f"; it has e.g. {', '.join(sorted(seen)[:3])}"
                                                                  if seen else "")
            raise ConfigError(f"--hk {path}: no field {n!r}{hint}")
        t = np.concatenate(times[n]) * _G3_TICK_NS
        v = np.concatenate(values[n])
        order = np.argsort(t, kind="stable")
        t, v = t[order], v[order]
        keep = np.ones(t.size, bool)
        keep[1:] = np.diff(t) > 0  # a reading written twice (file rotation repeats nothing, but be sure)
        out[n] = HkSeries(n, t[keep], v[keep])
    return out
