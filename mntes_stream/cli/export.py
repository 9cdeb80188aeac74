"""``mntes-stream export SESSION --out FILE``: recorded power to HDF5 for mapmakers."""

from __future__ import annotations

import re
from datetime import UTC, datetime

from mntes_stream.cli._common import add_quiet, print_mapping
from mntes_stream.errors import ConfigError
from mntes_stream.options import number

_ISO = re.compile(r"^\d{4}-\d{2}-\d{2}[T ]")


def parse_time_ns(text: str) -> int:
    """``--start``/``--end``: integer ns since the epoch, or an ISO 8601 time (UTC unless it says otherwise)."""
    text = text.strip()
    if re.fullmatch(r"-?\d+", text):
        return int(text)
    if _ISO.match(text):
        try:
            dt = datetime.fromisoformat(text.replace("Z", "+00:00"))
        except ValueError as exc:
            raise ConfigError(f"cannot read time {text!r}: {exc}") from None
        if dt.tzinfo is None:
            dt = dt.replace(tzinfo=UTC)
        delta = dt - datetime(1970, 1, 1, tzinfo=UTC)
        return (delta.days * 86_400 + delta.seconds) * 1_000_000_000 + delta.microseconds * 1_000
    raise ConfigError(f"time {text!r}: give integer ns since the epoch or ISO 8601 (2025-01-31T12:00:00Z)")


def _detectors(values) -> list[str] | None:
    if not values:
        return None
    return [d for v in values for d in (s.strip() for s in v.split(",")) if d]


# --format -> (module, export function, extra) of the mapmaking frameworks (mntes_stream.feeds.frameworks).
_FRAMEWORKS = {
    "toast": ("toast", "export_toast", "toast"),
    "sotodlib": ("sotodlib.core", "export_sotodlib", "sotodlib"),
    "litebird_sim": ("litebird_sim", "export_litebird", "litebird"),
}


def _framework_export(fmt: str, args, selection: dict):
    from mntes_stream.errors import import_extra

    module, func, extra = _FRAMEWORKS[fmt]
    # Before any session is read: toast/so3g must be loaded before spt3g in a process (else a segfault).
    import_extra(module, extra)
    import mntes_stream.feeds.frameworks as fw

    compression = args.compression or "gzip"
    kwargs = {} if fmt == "toast" else {"compression": None if compression == "none" else compression}
    if args.focal_plane:
        kwargs["positions"] = fw.read_positions(args.focal_plane)
    return getattr(fw, func)(args.session, args.out, overwrite=args.overwrite, **kwargs, **selection)


def run_export(args) -> int:
    from pathlib import Path

    from mntes_stream.cli.g3 import g3_sessions_as_mcap

    # Said here in a shell's words (the feeds, a Python API, name their overwrite=True), and before any G3 run
    # is converted for nothing.
    if Path(args.out).exists() and not args.overwrite:
        raise ConfigError(f"{args.out} exists (--overwrite replaces it)")
    with g3_sessions_as_mcap(args):  # a G3 run (SPT-3G) is converted to a temporary recording first
        return _run_export(args)


def _run_export(args) -> int:
    from mntes_stream.feeds.hdf5 import export_hdf5

    fmt = getattr(args, "format", "hdf5")
    if fmt == "hdf5" and getattr(args, "focal_plane", None):
        raise ConfigError("--focal-plane is for --format toast, sotodlib or litebird_sim (hdf5 carries no focal plane)")
    if fmt != "hdf5" and getattr(args, "block_samples", None) is not None:
        raise ConfigError(f"--block-samples is for --format hdf5 (the {fmt} writer chunks its own files)")
    if fmt == "toast" and getattr(args, "compression", None) is not None:
        raise ConfigError("--compression is not for --format toast (toast.io.save_hdf5 writes uncompressed)")
    selection = {
        "setup": args.setup,
        "detectors": _detectors(args.detectors),
        "start_ns": None if args.start is None else parse_time_ns(args.start),
        "end_ns": None if args.end is None else parse_time_ns(args.end),
        "board": args.board,
        "module": args.module,
    }
    if args.max_gap_s is not None:
        selection["max_gap_s"] = args.max_gap_s
    if fmt != "hdf5":
        summary = _framework_export(fmt, args, selection)
    else:
        summary = export_hdf5(args.session, args.out, compression=args.compression or "gzip",
                              block_samples=args.block_samples or 8192,
                              overwrite=args.overwrite, progress=not (args.json or args.quiet), **selection)
    result = {
        "format": fmt,
        "path": summary.path,
        "observations": list(summary.observations),
        "detector_samples": summary.samples,
        "gap_samples": summary.gap_samples,
        "absent_detector_samples": summary.absent_samples,
        "duplicate_chunks": summary.duplicate_chunks,
        "segment_breaks": summary.segment_breaks,
        "file_bytes": summary.file_bytes,
        "seconds": round(summary.seconds, 3),
        "samples_per_s": round(summary.samples_per_s),
    }
    damaged = getattr(summary, "damaged", "")
    if damaged:  # said on stderr and in the summary; the file lists the spans (attribute damaged_spans_ns)
        import sys

        print(f"mntes-stream: warning: input DAMAGED: {damaged}", file=sys.stderr)
        result["damaged"] = damaged
    print_mapping(result, args.json)
    return 0


def register(sub) -> None:
    p = sub.add_parser("export", help="export recorded power to HDF5 (one group per module: tod, time, flags, detectors) "
                       "or to TOAST / sotodlib / litebird_sim files")
    p.add_argument("session", nargs="+", help="MCAP file(s) or a directory of rotated files, or a G3 run "
                                              "(RUN.g3, either layout; needs --g3-params)")
    p.add_argument("--g3-params", metavar="FILE", help="G3 input: detector parameters (keyed by bolometer name "
                                                       "or detector id) to convert it with")
    p.add_argument("--out", required=True,
                   help="HDF5 file to write (hdf5, sotodlib); a directory of one .h5 per observation (toast, litebird_sim)")
    p.add_argument("--format", default="hdf5", choices=("hdf5", *_FRAMEWORKS),
                   help="hdf5 (default): this package's layout; toast: toast.io.save_hdf5 (uncompressed), one file per "
                   "observation; sotodlib: AxisManager.save, one group per observation; litebird_sim: "
                   "write_list_of_observations (float64), one file per observation. A module's power is split into "
                   "observations at segment breaks")
    p.add_argument("--focal-plane", metavar="FILE",
                   help="detector positions for the framework formats, covering every exported detector: CSV with "
                   "header detector,xi_rad,eta_rad,gamma_rad, or a G3 file with Wiring and BolometerProperties "
                   "(xi = x_offset, eta = y_offset, gamma = pol_angle; default: a documented boresight placeholder)")
    p.add_argument("--start", help="first sample time: integer ns since the epoch or ISO 8601 (UTC)")
    p.add_argument("--end", help="end (exclusive) sample time, same forms as --start")
    p.add_argument("--detectors", action="append", metavar="IDS", help="comma-separated detector ids (repeatable)")
    p.add_argument("--setup", help="only this setup's streams")
    p.add_argument("--board", type=number(int, ge=0), help="only this board")
    p.add_argument("--module", type=number(int, ge=0), help="only this module")
    p.add_argument("--compression", choices=("gzip", "lzf", "none"),
                   help="hdf5, sotodlib, litebird_sim: gzip (default) is readable everywhere; lzf is faster but "
                        "h5py-only")
    p.add_argument("--block-samples", type=number(int, ge=1), help="hdf5: samples per write and per HDF5 chunk (default 8192)")
    p.add_argument("--max-gap-s", type=number(float, "s", ge=0), metavar="S",
                   help="a longer step in time is a segment break (counted, listed in the group's segment_starts), "
                   "not a hole filled with NaN + GAP (default: feeds.blocks.DEFAULT_MAX_GAP_S, one hour)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing --out file")
    p.add_argument("--json", action="store_true", help="print the summary as JSON (no progress bars)")
    add_quiet(p)
    p.set_defaults(func=run_export)
