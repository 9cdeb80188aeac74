"""``mntes-stream record | replay | convert | inspect``: MCAP recording and its uses."""

from __future__ import annotations

import dataclasses
import json
import logging
import warnings

from mntes_stream.cli._common import add_zenoh_args, zenoh_overrides


def _logging(verbose: bool) -> None:
    logging.basicConfig(level=logging.INFO if verbose else logging.WARNING, format="%(asctime)s %(name)s: %(message)s")


# ---------------------------------------------------------------------------- record

_RECORD_FLAGS = {
    "setup": "setup",
    "key_expr": "key_expr",
    "dir": "directory",
    "prefix": "prefix",
    "flush_s": "flush_interval_s",
    "rotate_mb": "rotate_mb",
    "rotate_s": "rotate_s",
    "compression": "compression",
    "chunk_kb": "chunk_size_kb",
    "duration": "duration_s",
}


def run_record(args) -> int:
    from mntes_stream.service.recorder import RecorderConfig, run_recorder

    cfg = RecorderConfig.from_toml(args.config) if args.config else RecorderConfig()
    kw = {field: getattr(args, flag) for flag, field in _RECORD_FLAGS.items() if getattr(args, flag) is not None}
    if args.fsync:
        kw["fsync"] = True
    cfg = dataclasses.replace(cfg, zenoh=zenoh_overrides(args, cfg.zenoh), **kw)
    _logging(not args.quiet)
    stats = run_recorder(cfg)
    out = dataclasses.asdict(stats)
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"recorded {stats.messages} messages ({stats.payload_bytes / 1e6:.1f} MB payload, {stats.invalid} invalid, "
              f"{stats.seq_gaps} sequence gaps) in {stats.duration_s:.1f} s into {len(stats.files)} file(s):")
        for f in stats.files:
            print(f"  {f}")
    return 0


# ---------------------------------------------------------------------------- replay


def run_replay_cmd(args) -> int:
    from mntes_stream.io.mcap_io import Session
    from mntes_stream.service.replay import ReplayConfig, parse_time, run_replay

    cfg = ReplayConfig.from_toml(args.config) if args.config else ReplayConfig()
    kw: dict = {"source": tuple(args.files)}
    if args.afap:
        kw["speed"] = 0.0
    elif args.speed is not None:
        kw["speed"] = args.speed
    if args.all:
        kw["topics"] = ("**",)
    elif args.topics:
        kw["topics"] = tuple(args.topics)
    if args.wait_s is not None:
        kw["wait_subscribers_s"] = args.wait_s
    if args.start is not None or args.end is not None:
        t0 = Session(args.files, warn=False).start_ns
        if args.start is not None:
            kw["start_ns"] = parse_time(args.start, t0)
        if args.end is not None:
            kw["end_ns"] = parse_time(args.end, t0)
    cfg = dataclasses.replace(cfg, zenoh=zenoh_overrides(args, cfg.zenoh), **kw)
    _logging(not args.quiet)
    stats = run_replay(cfg, progress=not args.quiet and not args.json)
    if args.json:
        print(json.dumps(dataclasses.asdict(stats), indent=2))
    else:
        print(f"replayed {stats.messages} messages on {stats.topics} topics: {stats.recorded_span_s:.2f} s of recording "
              f"in {stats.duration_s:.2f} s (at most {stats.behind_max_ms:.1f} ms behind schedule)")
    return 0


# ---------------------------------------------------------------------------- inspect


def run_inspect(args) -> int:
    from mntes_stream.io.mcap_io import Session

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = Session(args.files)
    meta = s.metadata()
    out = {
        "files": [dataclasses.asdict(f) for f in s.files],
        "complete": s.complete,
        "start_ns": s.start_ns,
        "end_ns": s.end_ns,
        "topics": dict(sorted(s.message_counts().items())),
        "metadata": [{"name": m.name, "file": m.path, **({"data": m.data} if args.full else {})} for m in meta],
        "attachments": [{"name": a.name, "media_type": a.media_type, "bytes": len(a.data), "log_time_ns": a.log_time_ns, "file": a.path} for a in s.attachments()],
    }
    if args.json:
        print(json.dumps(out, indent=2))
        return 0
    for f in s.files:
        state = "complete" if f.complete else f"UNFINISHED ({f.problem}); recovered {f.recovered_bytes}/{f.size_bytes} bytes"
        print(f"{f.path}: {f.messages} messages, {f.chunks} chunks, {state}")
    if s.start_ns is not None:
        print(f"span: {(s.end_ns - s.start_ns) / 1e9:.3f} s of receive time")
    print("topics:")
    for t, n in out["topics"].items():
        print(f"  {n:>9d}  {t}")
    print("metadata: " + ", ".join(sorted({m.name for m in meta})))
    print(f"attachments: {len(out['attachments'])}")
    return 0


# ---------------------------------------------------------------------------- convert


def run_convert(args) -> int:
    from mntes_stream.service.offline import convert_recording

    pipeline = None
    if args.config:
        from mntes_stream.service.converter import ConverterConfig

        pipeline = ConverterConfig.from_toml(args.config).pipeline
    stats = convert_recording(args.input, args.output, tables=args.tables, params=args.params, pipeline_config=pipeline,
                              progress=not args.quiet)
    if args.json:
        print(json.dumps(dataclasses.asdict(stats), indent=2))
    else:
        print(stats.summary())
    return 0


def register(sub) -> None:
    p = sub.add_parser("record", help="record mntes/<setup>/** from zenoh into rotated MCAP files",
                       description="Record every message of a setup into MCAP until SIGINT/SIGTERM (or --duration).")
    p.add_argument("--config", metavar="FILE", help="recorder TOML (services/recorder.toml); flags override it")
    p.add_argument("--setup", help="setup name (records mntes/<setup>/**)")
    p.add_argument("--key-expr", help="record this key expression instead")
    p.add_argument("--dir", help="output directory")
    p.add_argument("--prefix", help="file prefix: <dir>/<prefix>-<seq>.mcap")
    p.add_argument("--flush-s", type=float, help="flush cadence = the crash-loss bound (s)")
    p.add_argument("--rotate-mb", type=float, help="new file after this many MB (0: never)")
    p.add_argument("--rotate-s", type=float, help="new file after this many seconds (0: never)")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"))
    p.add_argument("--chunk-kb", type=int, help="chunk size (uncompressed kB)")
    p.add_argument("--fsync", action="store_true", help="fsync at every flush (power-loss safe)")
    p.add_argument("--duration", type=float, help="stop after this many seconds")
    p.add_argument("--json", action="store_true", help="print the final statistics as JSON")
    p.add_argument("-q", "--quiet", action="store_true")
    add_zenoh_args(p)
    p.set_defaults(func=run_record)

    p = sub.add_parser("replay", help="re-publish a recorded session onto zenoh",
                       description="Re-publish recorded messages (default: counts and housekeeping) in log-time order, "
                                   "payloads unchanged, with BLOCK congestion control.")
    p.add_argument("files", nargs="+", metavar="FILE.mcap", help="recording(s) or a directory of rotated files")
    p.add_argument("--config", metavar="FILE", help="replay TOML (services/replay.toml)")
    speed = p.add_mutually_exclusive_group()
    speed.add_argument("--speed", type=float, help="multiple of real time (1: real time; 0: as fast as possible)")
    speed.add_argument("--afap", action="store_true", help="as fast as possible (same as --speed 0)")
    p.add_argument("--start", help="seconds after the first message, or an ISO-8601 time")
    p.add_argument("--end", help="seconds after the first message, or an ISO-8601 time")
    sel = p.add_mutually_exclusive_group()
    sel.add_argument("--all", action="store_true", help="replay every topic (power, status, provenance too)")
    sel.add_argument("--topics", nargs="+", metavar="KEYEXPR", help="topics or patterns such as mntes/lab/counts/**")
    p.add_argument("--wait-s", type=float, help="wait this long for subscribers before starting")
    p.add_argument("--json", action="store_true")
    p.add_argument("-q", "--quiet", action="store_true")
    add_zenoh_args(p)
    p.set_defaults(func=run_replay_cmd)

    p = sub.add_parser("convert", help="re-convert a recorded session offline (same code path as the live service)",
                       description="Feed the recorded counts and housekeeping of IN through the converter pipeline and "
                                   "write inputs plus new power and status to OUT. Parameters and tables default to "
                                   "the provenance stored in IN.")
    p.add_argument("input", metavar="IN.mcap", help="recording (file or directory of rotated files)")
    p.add_argument("output", metavar="OUT.mcap")
    p.add_argument("--tables", metavar="FILE", help="response tables to use instead of the recorded ones")
    p.add_argument("--params", metavar="FILE", help="detector parameter TOML to use instead of the recorded one")
    p.add_argument("--config", metavar="FILE", help="converter TOML whose [alignment]/[status] settings to use "
                                                    "(default: the pipeline defaults for the recorded setup)")
    p.add_argument("--json", action="store_true")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=run_convert)

    p = sub.add_parser("inspect", help="summarise MCAP recordings (topics, counts, completeness, metadata)")
    p.add_argument("files", nargs="+", metavar="FILE.mcap")
    p.add_argument("--full", action="store_true", help="include metadata values")
    p.add_argument("--json", action="store_true")
    p.set_defaults(func=run_inspect)
