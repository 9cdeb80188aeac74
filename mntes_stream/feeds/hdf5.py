"""HDF5 export of recorded power in this package's own layout, read with h5py.

The mapmaking frameworks' loaders do not read this layout; their own files
come from :mod:`mntes_stream.feeds.frameworks` (``export --format``).

Layout (``FORMAT = "mntes-stream/power"``, ``FORMAT_VERSION = 2``)::

    /                           attrs: format, format_version, software_version, created_utc,
                                       source_files, observations, selection, recording (JSON), max_gap_s,
                                       units, flags_schema (JSON: schemas/flags.v1.json)
    /provenance/<k>             one group per distinct mntes.provenance record (k = 0, 1, ...):
                                attrs setup, params_toml, table_identity, converter_kind,
                                software_version, t_ns, recorded_log_time_ns, source_file
    /<setup>_b<board>m<module>  one group per observation (a module's power stream):
        attrs   setup, board, module, sample_rate_hz, n_detectors, n_samples, t_start_ns, t_end_ns,
                table_identities (JSON list: the tables that produced the power), converter_kinds (JSON
                list), segment_starts (JSON list of sample indices where a new segment starts after a
                step beyond max_gap_s), provenance (paths of the matching /provenance groups), flag_bits
                (JSON name -> bit), counts (JSON: chunks, duplicate_chunks, gaps, gap_samples, seq_gaps,
                overlap_samples, absent_samples, ...)
        tod        float64 (n_det, n_samp)  W; NaN where no usable power      [chunked, compressed]
        flags      uint16  (n_det, n_samp)  core.flags bits (GAP, UNKNOWN_CHANNEL, ...)  [chunked, compressed]
                                            attrs flag_bit<n> = "<name>: <meaning>", flag_bits_json
        time       float64 (n_samp,)        s since the Unix epoch (float64 s, as TOAST and sotodlib keep times)
        time_ns    int64   (n_samp,)        ns since the Unix epoch (exact)
        sigma_p_w  float32 (n_det, n_samp)  W, per-sample power uncertainty from the readout noise, where the
                                            converter gave it (NaN elsewhere); present only then
                                            (noise weight = 1 / sigma_p_w**2)     [chunked, compressed]
        detectors  str     (n_det,)         detector ids b<board>m<module>c<channel>
        channels   int32   (n_det,)

Every dataset carries ``units`` and ``description`` attributes. ``tod`` is
chunked ``(min(n_det, 16), block_samples)``: one detector's timeline or one
time span of all detectors reads a handful of chunks.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mntes_stream import __version__
from mntes_stream.core import flags as fl
from mntes_stream.errors import ConfigError, TransportError
from mntes_stream.feeds.blocks import DEFAULT_BLOCK_SAMPLES, TodBlock
from mntes_stream.feeds.recorded import RecordedPower
from mntes_stream.io.describe import flag_attrs, flags_schema

__all__ = ["FORMAT", "FORMAT_VERSION", "COMPRESSIONS", "ExportSummary", "export_hdf5", "read_hdf5", "observation_names"]

FORMAT = "mntes-stream/power"
FORMAT_VERSION = 2  # 2: table_identities / converter_kinds / segment_starts as JSON lists
COMPRESSIONS = ("gzip", "lzf", "none")
_ROW_CHUNK = 16


@dataclass(frozen=True)
class ExportSummary:
    """What :func:`export_hdf5` wrote.

    ``samples`` counts detector-samples (n_det x n_samp summed over observations);
    ``segment_breaks`` the steps in time beyond ``max_gap_s`` (not filled), over all observations.
    """

    path: str
    observations: tuple
    samples: int
    gap_samples: int
    absent_samples: int
    duplicate_chunks: int
    segment_breaks: int
    file_bytes: int
    seconds: float
    damaged: str = ""  # what of the session could not be read ("" when nothing); listed in the file's damaged_spans

    @property
    def samples_per_s(self) -> float:
        return self.samples / self.seconds if self.seconds > 0 else float("inf")


def _filters(compression: str) -> dict:
    if compression == "gzip":
        # Level 1 + shuffle: most of level 9's ratio on float data at several times the speed.
        return {"compression": "gzip", "compression_opts": 1, "shuffle": True}
    if compression == "lzf":
        return {"compression": "lzf", "shuffle": True}
    if compression == "none":
        return {}
    raise ConfigError(f"compression must be one of {COMPRESSIONS}, got {compression!r}")


def _json(v) -> str:
    return json.dumps(v, sort_keys=True, default=str)


def _create_observation(f, rec: RecordedPower, sid, block_samples: int, filters: dict):
    import h5py

    ix = rec.streams[sid]
    n_det = len(ix.detectors)
    g = f.create_group(sid.name)
    g.attrs.update({"setup": sid.setup, "board": sid.board, "module": sid.module,
                    "sample_rate_hz": float(ix.sample_rate_hz) if ix.sample_rate_hz else float("nan"),
                    "n_detectors": n_det, "flag_bits": _json({n: b for b, n in fl.NAMES.items()})})
    rows = max(1, min(n_det, _ROW_CHUNK))
    cols = int(block_samples)
    tod = g.create_dataset("tod", (n_det, 0), maxshape=(n_det, None), dtype="<f8", chunks=(rows, cols),
                           fillvalue=np.nan, **filters)
    tod.attrs.update({"units": "W", "description": "optical power at the TES (MNTES); NaN where no usable power, see flags"})
    fg = g.create_dataset("flags", (n_det, 0), maxshape=(n_det, None), dtype="<u2", chunks=(rows, cols),
                          fillvalue=fl.GAP, **filters)
    fg.attrs.update({"units": "bitmask", "description": "per-sample mntes_stream.core.flags bits",
                     "bits": _json({n: b for b, n in fl.NAMES.items()}),
                     **flag_attrs()})  # flag_bit3 = "env_out_of_range: ...": meanings without project code
    t = g.create_dataset("time", (0,), maxshape=(None,), dtype="<f8", chunks=(cols,), **filters)
    t.attrs.update({"units": "s", "description": "sample time, seconds since 1970-01-01T00:00:00Z (float64)"})
    tn = g.create_dataset("time_ns", (0,), maxshape=(None,), dtype="<i8", chunks=(cols,), **filters)
    tn.attrs.update({"units": "ns", "description": "sample time, nanoseconds since 1970-01-01T00:00:00Z (exact)"})
    d = g.create_dataset("detectors", data=np.array(ix.detectors, dtype=object), dtype=h5py.string_dtype())
    d.attrs["description"] = "detector id b<board>m<module>c<channel> of each tod row"
    c = g.create_dataset("channels", data=ix.channels.astype("<i4"))
    c.attrs["description"] = "readout channel of each tod row"
    return g


def _sigma_dataset(g, tod, filters: dict):
    """The observation's ``sigma_p_w``, made at its first block that carries one (NaN where none was given)."""
    n_det = tod.shape[0]
    d = g.create_dataset("sigma_p_w", (n_det, tod.shape[1]), maxshape=(n_det, None), dtype="<f4",
                         chunks=tod.chunks, fillvalue=np.nan, **filters)
    d.attrs.update({"units": "W", "description": "per-sample power uncertainty from the readout noise through the "
                    "local responsivity (core.uncertainty); NaN where not given; noise weight = 1 / sigma_p_w**2"})
    return d


def _write_block(ds: dict, b: TodBlock, group=None, filters: dict | None = None) -> None:
    """One block into an observation's datasets (held open: a dataset object freed mid-write by h5py reports
    a failed write, a full disk, only as an ignored error in its deallocation, and HDF5 then goes on)."""
    a, z = b.first_sample, b.first_sample + b.n_samples
    if b.sigma_p_w is not None and "sigma_p_w" not in ds and group is not None:
        ds["sigma_p_w"] = _sigma_dataset(group, ds["tod"], filters or {})
    for name in ("tod", "flags", "sigma_p_w"):
        if name not in ds:
            continue
        ds[name].resize(z, axis=1)
    for name in ("time", "time_ns"):
        ds[name].resize(z, axis=0)
    ds["tod"][:, a:z] = b.p_opt_w
    ds["flags"][:, a:z] = b.flags
    ds["time"][a:z] = b.t_s
    ds["time_ns"][a:z] = b.t_ns
    if b.sigma_p_w is not None and "sigma_p_w" in ds:
        ds["sigma_p_w"][:, a:z] = b.sigma_p_w


def export_hdf5(source, out, *, compression: str = "gzip", block_samples: int = DEFAULT_BLOCK_SAMPLES,
                overwrite: bool = False, progress: bool = False, **selection) -> ExportSummary:
    """Write a recorded session's power to a self-describing HDF5 file.

    Parameters
    ----------
    source : path, directory, or iterable of paths
        The MCAP session.
    out : str or Path
        HDF5 file to create.
    compression : {"gzip", "lzf", "none"}
        gzip (deflate) is readable by every HDF5 build; lzf is faster but h5py-only.
    block_samples : int
        Samples per write and per HDF5 chunk along time.
    overwrite : bool
        Replace an existing ``out`` (default: refuse).
    progress : bool
        tqdm progress bars.
    **selection
        ``setup``, ``detectors``, ``start_ns``, ``end_ns``, ``board``, ``module``,
        ``max_gap_s`` (see :class:`~mntes_stream.feeds.recorded.RecordedPower`).

    Returns
    -------
    ExportSummary
    """
    import h5py

    filters = _filters(compression)
    out = Path(out)
    if out.exists() and not overwrite:
        raise ConfigError(f"{out} exists (use overwrite=True / --overwrite)")
    t_start = time.perf_counter()
    rec = RecordedPower(source, progress=progress, **selection)
    tmp = out.with_name(out.name + ".partial")
    try:
        tmp.unlink(missing_ok=True)  # a previous run's leftover: never a finished file
        disk = _GuardedFile(tmp, out)
        f = h5py.File(disk, "w")
    except OSError as exc:
        raise TransportError(f"cannot create {tmp}: {exc}") from None
    try:
        totals = _write_file(f, rec, block_samples, filters, disk)
        f.close()
        disk.sync()
        disk.check()
        tmp.replace(out)
    except BaseException:
        import contextlib

        with contextlib.suppress(Exception):  # HDF5 never saw an error (see _GuardedFile): closing is safe
            f.close()
        disk.close()
        tmp.unlink(missing_ok=True)
        raise
    disk.close()
    return ExportSummary(str(out), tuple(rec.names), *totals, out.stat().st_size, time.perf_counter() - t_start,
                         damaged=rec.session.damage_line())


class _GuardedFile:
    """The file object HDF5 writes through (h5py's ``fileobj`` driver), keeping write errors from HDF5.

    HDF5 2.0 meeting a full disk swallows some errors in object deallocation,
    goes on, and crashes at close or exit (the export's rc 139). Here a failed
    write is remembered and its bytes kept in memory (reads see them), so
    HDF5 always sees a working file; the export stops after the block in
    progress (:meth:`check`), closes cleanly and removes the partial file.
    Memory after a failure is bounded by one block and HDF5's caches.
    """

    def __init__(self, path: Path, out: Path):
        self.out = out
        self._fd = os.open(path, os.O_RDWR | os.O_CREAT | os.O_EXCL, 0o644)
        self._pos = 0
        self._spill: dict[int, bytes] = {}  # offset -> bytes that could not be written
        self.error: OSError | None = None

    def seek(self, offset: int, whence: int = 0) -> int:
        base = {0: 0, 1: self._pos, 2: self._size()}[whence]
        self._pos = base + offset
        return self._pos

    def tell(self) -> int:
        return self._pos

    def _size(self) -> int:
        return max([os.fstat(self._fd).st_size] + [o + len(b) for o, b in self._spill.items()])

    def write(self, data) -> int:
        data = bytes(data)
        if self.error is None:
            try:
                n = os.pwrite(self._fd, data, self._pos)
                if n < len(data):
                    raise OSError(28, os.strerror(28))  # a short write: the disk is full
                self._pos += n
                return n
            except OSError as exc:
                self.error = exc
        self._spill[self._pos] = data
        self._pos += len(data)
        return len(data)

    def readinto(self, buf) -> int:
        n = len(buf)
        out = bytearray(os.pread(self._fd, n, self._pos).ljust(n, b"\0"))
        for o, b in self._spill.items():
            lo, hi = max(o, self._pos), min(o + len(b), self._pos + n)
            if lo < hi:
                out[lo - self._pos:hi - self._pos] = b[lo - o:hi - o]
        memoryview(buf).cast("B")[:n] = out
        self._pos += n
        return n

    def read(self, n: int = -1) -> bytes:
        buf = bytearray(max(0, self._size() - self._pos) if n is None or n < 0 else n)
        self.readinto(buf)
        return bytes(buf)

    def truncate(self, size: int | None = None) -> int:
        size = self._pos if size is None else size
        if self.error is None:
            os.ftruncate(self._fd, size)
        return size

    def flush(self) -> None:
        pass

    def sync(self) -> None:
        """To the disk before the rename: a finished name never points at data still in memory."""
        if self.error is None:
            try:
                os.fsync(self._fd)
            except OSError as exc:
                self.error = exc

    def check(self) -> None:
        """TransportError (one line) once a write has failed."""
        if self.error is not None:
            raise TransportError(f"cannot write {self.out}: {self.error.strerror or self.error} (nothing written: "
                                 "the partial file is removed)")

    def close(self) -> None:
        if self._fd >= 0:
            os.close(self._fd)
            self._fd = -1
        self._spill.clear()


def _write_file(f, rec: RecordedPower, block_samples: int, filters: dict, disk: _GuardedFile) -> tuple:
    """The whole export into the open file ``f``; ``(samples, gap, absent, duplicates, breaks)``."""
    provenance = rec.provenance()
    f.attrs.update({
        "format": FORMAT, "format_version": FORMAT_VERSION,
        "software_version": f"mntes-stream {__version__}",
        "created_utc": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "source_files": _json([str(p) for p in rec.files]),
        "observations": _json(rec.names),
        "selection": _json(rec.selection),
        "max_gap_s": rec.max_gap_s,
        "recording": _json(rec.recording_metadata()),
        "units": _json({"tod": "W", "time": "s", "time_ns": "ns"}),
        "flags_schema": _json(flags_schema()),  # schemas/flags.v1.json: bit names, meanings, units
    })
    pg = f.create_group("provenance")
    pg.attrs["description"] = "distinct mntes.provenance records of the session (detector parameters, table identity)"
    prov_paths: dict[tuple, list[str]] = {}
    for k, (p, log_ns, path) in enumerate(provenance):
        g = pg.create_group(str(k))
        g.attrs.update({"setup": p.setup, "params_toml": p.params_toml, "table_identity": p.table_identity,
                        "converter_kind": p.converter_kind, "software_version": p.software_version,
                        "t_ns": p.t_ns, "recorded_log_time_ns": log_ns, "source_file": str(path)})
        prov_paths.setdefault((p.setup, p.table_identity), []).append(g.name)
    groups = {sid: _create_observation(f, rec, sid, block_samples, filters) for sid in rec.streams}
    datasets = {sid: {name: g[name] for name in ("tod", "flags", "time", "time_ns")} for sid, g in groups.items()}
    for b in rec.iter_blocks(block_samples):
        _write_block(datasets[b.stream], b, groups[b.stream], filters)
        disk.check()  # stop at the first failed write: what follows would only fill memory
    summary_samples = gap = absent = dups = breaks = 0
    for sid, g in groups.items():
        st, ix = rec.stats[sid], rec.streams[sid]
        n = g["time_ns"].shape[0]
        tn = g["time_ns"]
        g.attrs.update({
            "n_samples": n,
            "t_start_ns": int(tn[0]) if n else 0,
            "t_end_ns": int(tn[-1]) if n else 0,
            "table_identities": _json(st.table_identities),
            "converter_kinds": _json(st.converter_kinds),
            "segment_starts": _json(st.segment_starts),
            "provenance": _json([p for t in st.table_identities for p in prov_paths.get((sid.setup, t), [])]),
            "counts": _json({k: v for k, v in st.as_dict().items() if not isinstance(v, list)}
                            | {"chunks_indexed": len(ix.chunks)}),
        })
        summary_samples += n * len(ix.detectors)
        gap += st.gap_samples
        absent += st.absent_samples
        dups += st.duplicate_chunks
        breaks += len(st.segment_starts)
    _mark_damage(f, rec.session)
    return summary_samples, gap, absent, dups, breaks


def _mark_damage(f, session) -> None:
    """What of the recording could not be read: the file says so, with the spans (the power there is GAP)."""
    f.attrs["damaged"] = session.damage_line()
    f.attrs["damaged_spans_ns"] = _json([[d.start_ns, d.end_ns] for d in session.damage])
    f.attrs["damaged_chunks"] = _json([{"file": d.path, "offset": d.offset, "why": d.why, "start_ns": d.start_ns,
                                        "end_ns": d.end_ns, "messages": d.messages, "topics": dict(d.topics)}
                                       for d in session.damage])


def observation_names(path) -> list[str]:
    """Observation group names of an exported file."""
    import h5py

    with h5py.File(path, "r") as f:
        return json.loads(f.attrs["observations"])


def read_hdf5(path, observation: str | None = None) -> TodBlock | dict[str, TodBlock]:
    """Load exported observations back as :class:`TodBlock` (one, or all by name)."""
    import h5py

    with h5py.File(path, "r") as f:
        if f.attrs.get("format") != FORMAT:
            raise ConfigError(f"{path} is not an mntes-stream power export (format {f.attrs.get('format')!r})")
        if int(f.attrs.get("format_version", 0)) != FORMAT_VERSION:
            raise ConfigError(f"{path}: format_version {f.attrs.get('format_version')} (this reader: {FORMAT_VERSION}); "
                              "export the session again")
        names = json.loads(f.attrs["observations"]) if observation is None else [observation]
        out = {}
        for name in names:
            if name not in f:
                raise ConfigError(f"{path} has no observation {name!r} (has {json.loads(f.attrs['observations'])})")
            g = f[name]
            out[name] = TodBlock(
                str(g.attrs["setup"]), int(g.attrs["board"]), int(g.attrs["module"]),
                tuple(s.decode() if isinstance(s, bytes) else str(s) for s in g["detectors"][()]),
                g["channels"][()], g["time_ns"][()], g["tod"][()], g["flags"][()],
                table_identities=tuple(json.loads(g.attrs["table_identities"])),
                sigma_p_w=g["sigma_p_w"][()] if "sigma_p_w" in g else None,
            )
    return out[observation] if observation is not None else out
