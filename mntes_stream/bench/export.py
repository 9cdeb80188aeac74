"""``mntes-stream bench export``: recorded power to HDF5, detector-samples per second.

A session of ``--modules`` 128-channel modules at ``--rate-hz`` in
``--chunk-s`` power chunks (real encoded PowerChunk messages: a level plus
white noise, one saturated NaN channel per module) is written with the MCAP writer into
a temporary directory, rotated into several files. Then it is timed:

- ``read``: :class:`~mntes_stream.feeds.recorded.RecordedPower` index pass +
  block iteration (everything but HDF5);
- ``export``: :func:`~mntes_stream.feeds.hdf5.export_hdf5` end to end, once
  per ``--compression``;
- ``--format toast|sotodlib|litebird_sim``: the framework exports of
  :mod:`mntes_stream.feeds.frameworks` end to end (read, build each
  framework's objects, write with its own writer: ``toast.io.save_hdf5``
  uncompressed, ``AxisManager.save`` and ``write_list_of_observations`` with
  gzip), the framework imported before the clock starts. A framework that is
  not installed is reported as such, not timed.

Throughput is detector-samples (n_det x n_samp) per wall-clock second; the
real-time factor is stream seconds exported per wall-clock second.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

HELP = "export throughput: MCAP session -> HDF5 (detector-samples per second)"


def add_arguments(p) -> None:
    p.add_argument("--modules", type=int, default=8, help="128-channel modules (default 8 = 1024 detectors)")
    p.add_argument("--rate-hz", type=float, default=200.0, help="sample rate (Hz; default 200)")
    p.add_argument("--chunk-s", type=float, default=0.1, help="chunk length (s; default 0.1)")
    p.add_argument("--seconds", type=float, default=60.0, help="stream time in the session")
    p.add_argument("--compression", action="append", choices=("gzip", "lzf", "none"),
                   help="HDF5 compression(s) to time (repeatable; default gzip and lzf)")
    p.add_argument("--format", action="append", choices=("hdf5", "toast", "sotodlib", "litebird_sim"),
                   help="export format(s) to time (repeatable; default all four)")
    p.add_argument("--block-samples", type=int, default=8192, help="samples per HDF5 write (default 8192)")
    p.add_argument("--dir", help="where to write (default: a temporary directory, removed afterwards)")


def write_session(directory: Path, modules: int, rate_hz: float, chunk_s: float, seconds: float, seed: int = 0) -> int:
    """A recorded power session in ``directory``; returns the detector-samples in it."""
    from mntes_stream.core import flags as fl
    from mntes_stream.core.ids import detector_id
    from mntes_stream.io import keys
    from mntes_stream.io.mcap import RotatingMcapWriter
    from mntes_stream.io.messages import PowerChunk

    rng = np.random.default_rng(seed)
    n_ch, n_samp = 128, int(round(rate_hz * chunk_s))
    n_chunks = int(round(seconds / chunk_s))
    ch = np.arange(n_ch, dtype=np.int32)
    t0 = 1_700_000_000_000_000_000
    step_ns = int(round(chunk_s * 1e9))
    # Fresh noise in every chunk: repeated payloads would flatter both zstd and gzip.
    level = rng.normal(1e-12, 1e-13, (modules, n_ch, 1))
    flags = np.zeros((n_ch, n_samp), np.uint16)
    flags[-1, :] = fl.SATURATED
    w = RotatingMcapWriter(directory, "bench", rotate_bytes=64 << 20, rotate_s=0)
    try:
        for k in range(n_chunks):
            t_k = t0 + k * step_ns
            for m in range(modules):
                p = level[m] + rng.normal(0, 1e-15, (n_ch, n_samp))
                p[-1, :] = np.nan
                msg = PowerChunk(setup="bench", board=0, module=m, channels=ch,
                                 detector_ids=[detector_id(0, m, c) for c in range(n_ch)], seq=k, t0_ns=t_k,
                                 sample_rate_hz=rate_hz, p_opt_w=p, flags=flags, table_identity="bench",
                                 converter_kind="table", source_t_pub_ns=t_k, t_pub_ns=t_k)
                w.write(keys.power_key("bench", 0, m), msg.to_bytes(), t_k + step_ns + 1000 * m)
            w.tick()
    finally:
        w.close()
    return modules * n_ch * n_chunks * n_samp


def run(args) -> dict:
    from mntes_stream.errors import ConfigError
    from mntes_stream.feeds.hdf5 import export_hdf5
    from mntes_stream.feeds.recorded import RecordedPower

    directory = Path(args.dir) if args.dir else Path(tempfile.mkdtemp(prefix="mntes-bench-export-"))
    compressions = args.compression or ["gzip", "lzf"]
    try:
        session = directory / "session"
        samples = write_session(session, args.modules, args.rate_hz, args.chunk_s, args.seconds)
        mcap_bytes = sum(p.stat().st_size for p in session.glob("*.mcap"))
        t0 = time.perf_counter()
        rec = RecordedPower(session)
        t_index = time.perf_counter() - t0
        got = sum(b.p_opt_w.size for b in rec.iter_blocks(args.block_samples))
        t_read = time.perf_counter() - t0
        if got != samples:
            raise ConfigError(f"read {got} detector-samples, wrote {samples}")
        result = {
            "detectors": args.modules * 128,
            "sample_rate_hz": args.rate_hz,
            "stream_seconds": args.seconds,
            "detector_samples": samples,
            "mcap_files": len(list(session.glob("*.mcap"))),
            "mcap_mb": round(mcap_bytes / 1e6, 1),
            "read_index_s": round(t_index, 2),
            "read_msamples_per_s": round(samples / t_read / 1e6, 2),
        }
        formats = args.format or ["hdf5", "toast", "sotodlib", "litebird_sim"]
        for comp in compressions if "hdf5" in formats else []:
            out = directory / f"export-{comp}.h5"
            s = export_hdf5(session, out, compression=comp, block_samples=args.block_samples, overwrite=True)
            if s.samples != samples:
                raise ConfigError(f"exported {s.samples} detector-samples, wrote {samples}")
            result[f"export_{comp}_msamples_per_s"] = round(s.samples_per_s / 1e6, 2)
            result[f"export_{comp}_realtime_factor"] = round(args.seconds / s.seconds, 1)
            result[f"export_{comp}_file_mb"] = round(s.file_bytes / 1e6, 1)
        for fmt in (f for f in formats if f != "hdf5"):
            result.update(_framework(fmt, session, directory, samples, args.seconds))
        return result
    finally:
        if not args.dir:
            shutil.rmtree(directory, ignore_errors=True)


_IMPORTS = {"toast": "toast", "sotodlib": "sotodlib.core", "litebird_sim": "litebird_sim"}


def _framework(fmt: str, session: Path, directory: Path, samples: int, seconds: float) -> dict:
    """Time one framework export of ``session``; ``{fmt}_...`` figures, or a note if it is not installed."""
    import importlib

    from mntes_stream.errors import ConfigError

    try:
        importlib.import_module(_IMPORTS[fmt])  # import time is not export time
    except ImportError as exc:
        return {f"{fmt}_not_installed": str(exc)}
    from mntes_stream.feeds import frameworks

    export = frameworks.FRAMEWORKS[fmt][1]
    out = directory / f"export-{fmt}"
    s = export(session, out, overwrite=True)
    if s.samples != samples:
        raise ConfigError(f"{fmt}: exported {s.samples} detector-samples, wrote {samples}")
    return {f"{fmt}_msamples_per_s": round(s.samples_per_s / 1e6, 2),
            f"{fmt}_realtime_factor": round(seconds / s.seconds, 1),
            f"{fmt}_file_mb": round(s.file_bytes / 1e6, 1)}
