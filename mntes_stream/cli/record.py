"""``mntes-stream record | replay | convert | inspect``: MCAP recording and its uses."""

from __future__ import annotations

import dataclasses
import json
import warnings

from mntes_stream.cli._common import (
    add_json,
    add_overwrite,
    add_quiet,
    add_settings_args,
    add_zenoh_args,
    arguments,
    service_config,
    settings_from_args,
    setup_logging,
    zenoh_layer,
)

# ---------------------------------------------------------------------------- record

_RECORD = ("setup", "key_expr", "directory", "prefix", "flush_interval_s", "rotate_mb", "rotate_s", "compression",
           "chunk_size_kb", "fsync", "duration_s", "queue_messages")
_RECORD_ALIASES = {"directory": ("--out", "--dir"), "flush_interval_s": ("--flush-s",), "chunk_size_kb": ("--chunk-kb",),
                   "duration_s": ("--duration",)}


def run_record(args) -> int:
    from mntes_stream.service.recorder import RecorderService, cost_line, final_line

    cfg = service_config(RecorderService, args.config, args.set, settings_from_args(args, _RECORD), zenoh_layer(args))
    setup_logging(not args.quiet)
    out = RecorderService(cfg).start()
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        print(f"recorded {out['messages']} messages ({out['payload_bytes'] / 1e6:.1f} MB payload, {out['invalid']} invalid, "
              f"{out['seq_gaps']} sequence gaps) in {out['duration_s']:.1f} s into {len(out['files'])} file(s):")
        for f in out["files"]:
            print(f"  {f}")
        print(cost_line(out))
        for name, line in sorted((out.get("converters") or {}).items()):
            print(f"converter {name} (its last recorded status): {line}")
        print(final_line(out))  # the ledger, in one line, last
    return 0


# ---------------------------------------------------------------------------- replay


def replay_config(args):
    """The replay's config: ``--config``, ``--set``, then the flags given (``--afap``, ``--all`` as their settings)."""
    from mntes_stream.service.replay import ReplayService

    kw: dict = {"source": tuple(args.files)} if args.files else {}
    kw.update(settings_from_args(args, _REPLAY))
    if args.afap:
        kw["speed"] = 0.0
    if args.all:
        kw["topics"] = ("**",)
    return service_config(ReplayService, args.config, args.set, kw, zenoh_layer(args))


def run_replay_cmd(args) -> int:
    from mntes_stream.errors import ConfigError
    from mntes_stream.io.mcap import Session
    from mntes_stream.service.replay import parse_time, run_replay

    cfg = replay_config(args)
    if not cfg.source:
        raise ConfigError("nothing to replay: give recordings (files or directories) or a config with source")
    if args.start is not None or args.end is not None:
        t0 = Session(list(cfg.source), warn=False).start_ns
        times = {}
        if args.start is not None:
            times["start_ns"] = parse_time(args.start, t0)
        if args.end is not None:
            times["end_ns"] = parse_time(args.end, t0)
        cfg = dataclasses.replace(cfg, **times)
    setup_logging(not args.quiet)
    from mntes_stream.cli.ocs import recording_with_hk

    with recording_with_hk(args, list(cfg.source)) as source:  # --hk: bath temperature from OCS HK files
        cfg = dataclasses.replace(cfg, source=tuple(str(s) for s in source))
        stats = run_replay(cfg, progress=not args.quiet and not args.json)
    if args.json:
        print(json.dumps(dataclasses.asdict(stats), indent=2))
    else:
        print(f"replayed {stats.messages} messages on {stats.topics} topics: {stats.recorded_span_s:.2f} s of recording "
              f"in {stats.duration_s:.2f} s (at most {stats.behind_max_ms:.1f} ms behind schedule)")
        print(f"ledger: counts {stats.ledger_line}")  # the last line: every recorded chunk of every stream
    return 0


# ---------------------------------------------------------------------------- inspect


def run_inspect(args) -> int:
    """Exit 2 when anything is called DAMAGED (an unreadable chunk or record, messages lost)."""
    import sys

    from mntes_stream.io.mcap import Session
    from mntes_stream.io.mcap.recovery import being_written

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        s = Session(args.files)
    meta = s.metadata()
    out = {
        "sessions": [{"session": sid, "files": [str(p) for p in ps]} for sid, ps in s.sessions],
        "session": s.session,
        "being_written": [f.path for f in s.files if not f.complete and being_written(f.path)],
        "files": [dataclasses.asdict(f) for f in s.files],
        "complete": s.complete,
        "start_ns": s.start_ns,
        "end_ns": s.end_ns,
        "topics": dict(sorted(s.message_counts().items())),
        "metadata": [{"name": m.name, "file": m.path, **({"data": m.data} if args.full else {})} for m in meta],
        "attachments": [{"name": a.name, "media_type": a.media_type, "bytes": len(a.data), "log_time_ns": a.log_time_ns, "file": a.path} for a in s.attachments()],
        "damaged": [dataclasses.asdict(d) for d in s.damage],
    }
    checks = None
    if args.verify:
        from mntes_stream.io.mcap.repair import verify_file

        checks = {c.path: c for c in (verify_file(f.path) for f in s.files)}
        out["verified"] = [dataclasses.asdict(c) | {"ok": c.ok, "lost_messages": c.lost_messages} for c in checks.values()]
        out["complete"] = all(c.ok and c.complete for c in checks.values())
        damaged = [p for p, c in checks.items() if not c.ok]
    else:
        damaged = sorted({d.path for d in s.damage}
                         | {f.path for f in s.files if f.unlabelled_messages or f.damaged_records})
    out["damaged_files"] = damaged
    ledger = _ledger_of(s)
    out["ledger"] = ledger.as_dict()
    if args.json:
        print(json.dumps(out, indent=2))
    else:
        if len(s.sessions) > 1:  # two runs into one folder: never one observation with a hole between them
            print(f"{len(s.sessions)} recording sessions here; this is the newest, {s.session} (give another's "
                  "files to read it):")
            for sid, ps in s.sessions:
                print(f"  session {sid or 'unnamed (written before sessions were named)'}: {len(ps)} file(s), "
                      f"{' '.join(str(p) for p in ps)}")
        _print_inspect(s, out, meta, checks)
        print("\n".join(ledger.lines()))
    if damaged:
        what = "; ".join(f"{p}: {checks[p].summary()}" if checks else p for p in damaged)
        print(f"mntes-stream: error: {len(damaged)} of {len(s.files)} file(s) DAMAGED ({what})", file=sys.stderr)
        return 2
    return 0


def _ledger_of(session):
    """The recording's ledger (io/mcap/ledger.py): its mntes.ledger metadata, else recomputed from the messages."""
    from mntes_stream.io.mcap.ledger import recording_ledger

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # damage is said once, above
        return recording_ledger(session)


def _print_inspect(s, out, meta, checks) -> None:
    for f in s.files:
        if f.complete:
            state = "complete"
        elif f.path in out["being_written"]:  # its writer holds it open: a live recording, not a dead one
            state = f"being written (its recorder runs): read up to its last flush, {f.recovered_bytes} bytes"
        else:
            state = f"UNFINISHED ({f.problem}); recovered {f.recovered_bytes}/{f.size_bytes} bytes"
        c = checks[f.path] if checks else None
        damage = c.damage if c is not None else [d for d in s.damage if d.path == f.path]
        if c is not None and not c.ok:
            state += f"; DAMAGED: {c.summary()}"
        elif c is not None:
            state += ", every chunk verified"
        elif damage or f.damaged_records:
            state += (f"; DAMAGED: {len(damage)} chunk(s) unreadable, {len(f.damaged_records)} damaged record(s) "
                      f"(inspect --verify reads every chunk)")
        print(f"{f.path}: {f.messages} messages, {f.chunks} chunks, {state}")
        for d in damage:
            print(f"  damaged chunk at {d.describe(with_path=False)}")
        if c is None:
            for off, why in f.damaged_records:
                print(f"  damaged record at byte {off}: {why}")
        if c is not None:
            for off, why in c.damaged_chunks:
                if not any(d.offset == off for d in c.damage):
                    print(f"  damaged record at byte {off}: {why}")
            if c.reconstructed_channels:
                print(f"  channels rebuilt from their payloads (record lost): {', '.join(c.reconstructed_channels)}")
    for m in meta:
        if m.name == "mntes.damaged":  # written by recover/convert: this file is whole, its source was not
            print(f"{m.path}: made from a damaged source: {m.data.get('messages_lost', '?')} messages lost in "
                  f"{m.data.get('chunks', '?')} chunk(s) (metadata mntes.damaged)")
    if s.start_ns is not None:
        print(f"span: {(s.end_ns - s.start_ns) / 1e9:.3f} s of receive time")
    print("topics:")
    for t, n in out["topics"].items():
        print(f"  {n:>9d}  {t}")
    print("metadata: " + ", ".join(sorted({m.name for m in meta})))
    print(f"attachments: {len(out['attachments'])}")


def run_recover(args) -> int:
    import sys

    from mntes_stream.cli._common import claim_out
    from mntes_stream.io.mcap.repair import DAMAGE_METADATA, recover_file

    claim_out(args.output, args.overwrite, inputs=[args.input])
    c = recover_file(args.input, args.output)
    if args.json:
        print(json.dumps(dataclasses.asdict(c) | {"ok": c.ok, "lost_messages": c.lost_messages}, indent=2))
        return 0
    for d in c.damage:
        print(f"  damaged chunk at {d.describe(with_path=False)}", file=sys.stderr)
    for off, why in c.damaged_chunks:
        if not any(d.offset == off for d in c.damage):
            print(f"  damaged record at byte {off}: {why}", file=sys.stderr)
    if c.reconstructed_channels:
        print(f"  channels rebuilt from their payloads (record lost): {', '.join(c.reconstructed_channels)}",
              file=sys.stderr)
    source = "finished" if c.complete else "unfinished"
    if c.ok:
        print(f"{args.output}: {c.readable_messages} messages from {c.path} ({c.chunks} chunks, every chunk read, "
              f"source {source})")
    else:
        print(f"{args.output}: {c.readable_messages} messages from {c.path} ({c.chunks} chunks, source {source}); "
              f"DAMAGED: {c.summary()} (listed above; marked in its {DAMAGE_METADATA} metadata)")
    return 0


# ---------------------------------------------------------------------------- convert


def run_convert(args) -> int:
    from mntes_stream.cli._common import claim_out
    from mntes_stream.cli.g3 import refuse_inapplicable
    from mntes_stream.pipeline.offline import convert_recording

    refuse_inapplicable(args, _g3_name(args.input), _g3_name(args.output))
    claim_out(args.output, args.overwrite, inputs=[args.input])

    import tomllib

    from mntes_stream.service.converter import ConverterConfig, ConverterService

    pipeline = None
    kind = args.kind
    # LOW_RESPONSIVITY (and sigma_P) as that converter, or one with the defaults, publishes them.
    conf = service_config(ConverterService, args.config, (), {}, None) if args.config else None
    if conf is not None:
        pipeline = conf.pipeline
        uncertainty, sigma_p, low = conf.uncertainty_used, conf.sigma_p, conf.low_responsivity
        with open(args.config, "rb") as f:  # a kind the file sets is applied (the default is the recorded one)
            if kind is None and "kind" in tomllib.load(f).get("converter", {}):
                kind = conf.kind
    else:  # the converter's defaults (its dataclass fields'; a config needs parameters to exist)
        from mntes_stream.core.uncertainty import UncertaintySettings

        sigma_p, low = ConverterConfig.sigma_p, ConverterConfig.low_responsivity
        uncertainty = UncertaintySettings() if low != "off" or sigma_p else None
    if _g3_name(args.input) or _g3_name(args.output):  # SPT-3G G3 in or out (mntes_stream.g3)
        from mntes_stream.cli.g3 import run_g3_convert

        return run_g3_convert(args, pipeline)
    if kind is not None and args.tables:
        from mntes_stream.errors import ConfigError

        raise ConfigError("--tables sets the converter kind: give --kind (or a config's kind) or --tables, not both")
    from mntes_stream.cli.ocs import recording_with_hk

    with recording_with_hk(args, args.input) as source:  # --hk: bath temperature from OCS HK files
        stats = convert_recording(source, args.output, tables=args.tables, params=args.params,
                                  pipeline_config=pipeline, progress=not args.quiet, uncertainty=uncertainty,
                                  sigma_p=sigma_p, only_fused=low == "auto", kind=kind)
    if stats.damaged:  # on stderr too: a convert in a script must not pass over it
        import sys

        print(f"mntes-stream: warning: {args.input}: input DAMAGED: {stats.damaged}", file=sys.stderr)
    if args.json:
        print(json.dumps(dataclasses.asdict(stats), indent=2))
    else:
        print(stats.summary())
    return 0


def _g3_name(path) -> bool:
    return any(str(path).lower().endswith(s) for s in (".g3", ".g3.gz", ".g3.zst", ".g3.bz2"))


def _record_args(p) -> None:
    from mntes_stream.service.recorder import RecorderConfig  # the recorder's module: `record` alone needs it

    p.add_argument("--config", metavar="FILE", help="recorder TOML (services/recorder.toml); flags override it")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    add_settings_args(p, RecorderConfig, _RECORD, _RECORD_ALIASES, title="recorder (override the config file)")
    add_json(p, "print the final statistics as JSON")
    add_quiet(p)
    add_zenoh_args(p)
    p.set_defaults(func=run_record)


# The [replay] settings the flags set (types, ranges and help from ReplayConfig).
_REPLAY = ("speed", "topics", "wait_subscribers_s")


def _replay_args(p) -> None:
    from mntes_stream.service.replay import ReplayConfig  # the replay's module: `replay` alone needs it

    p.add_argument("files", nargs="*", metavar="FILE.mcap",
                   help="recording(s), a directory of rotated files or the folder `up` writes (default: the config's source)")
    p.add_argument("--config", metavar="FILE", help="replay TOML (services/replay.toml)")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    speed = p.add_mutually_exclusive_group()
    add_settings_args(speed, ReplayConfig, ("speed",), metavars={"speed": "X"})
    speed.add_argument("--afap", action="store_true", help="as fast as possible (same as --speed 0)")
    # The times as a person gives them (seconds from the start, or ISO-8601); the settings hold ns since the epoch.
    p.add_argument("--start", help="seconds after the first message, or an ISO-8601 time")
    p.add_argument("--end", help="seconds after the first message, or an ISO-8601 time")
    sel = p.add_mutually_exclusive_group()
    sel.add_argument("--all", action="store_true", help="replay every topic (power, status, provenance too)")
    add_settings_args(sel, ReplayConfig, ("topics",), metavars={"topics": "KEYEXPR"})
    add_settings_args(p, ReplayConfig, ("wait_subscribers_s",), spelled={"wait_subscribers_s": "--wait-s"})
    from mntes_stream.cli.ocs import add_hk_args

    add_hk_args(p)
    add_json(p, "print the statistics as one JSON document")
    add_quiet(p)
    add_zenoh_args(p)


def register(sub) -> None:
    p = sub.add_parser("record", help="record mntes/<setup>/** from zenoh into rotated MCAP files",
                       description="Record every message of a setup into MCAP until SIGINT/SIGTERM (or --duration).")
    arguments(p, _record_args)

    p = sub.add_parser("replay", help="re-publish a recorded session onto zenoh",
                       description="Re-publish recorded messages (default: counts and housekeeping) in log-time order, "
                                   "payloads unchanged, with BLOCK congestion control.")
    arguments(p, _replay_args)
    p.set_defaults(func=run_replay_cmd)

    p = sub.add_parser("convert", help="re-convert a recorded session offline (same code path as the live service)",
                       description="Feed the recorded counts and housekeeping of IN through the converter pipeline and "
                                   "write inputs plus new power and status to OUT. Parameters and tables default to "
                                   "the provenance stored in IN.")
    p.add_argument("input", metavar="IN.mcap", help="recording (file or directory of rotated files), or a G3 run "
                                                    "(RUN.g3, raw Timepoints or collated Scans; a quoted glob for several)")
    p.add_argument("output", metavar="OUT.mcap", help="the converted recording to write (OUT.g3: SPT-3G Scan frames)")
    p.add_argument("--tables", metavar="FILE", help="response tables to use instead of the recorded ones")
    p.add_argument("--params", metavar="FILE", help="detector parameter TOML to use instead of the recorded one")
    p.add_argument("--config", metavar="FILE", help="converter TOML whose [alignment]/[status] settings (and [converter] sigma_p with [uncertainty]) to use "
                                                    "(default: the pipeline defaults for the recorded setup)")
    add_overwrite(p, "replace an existing OUT file")
    add_json(p, "print the statistics as one JSON document")
    add_quiet(p)
    from mntes_stream.cli.g3 import add_g3_convert_args

    add_g3_convert_args(p)
    from mntes_stream.cli.ocs import add_hk_args

    add_hk_args(p)
    p.set_defaults(func=run_convert)

    p = sub.add_parser("inspect", help="summarise MCAP recordings (topics, counts, completeness, metadata)")
    p.add_argument("files", nargs="+", metavar="FILE.mcap", help="recordings: files or directories of rotated files")
    p.add_argument("--full", action="store_true", help="include metadata values")
    p.add_argument("--verify", action="store_true",
                   help="read every chunk and check its CRC (a summary alone can call a damaged file complete)")
    add_json(p, "print the summary as one JSON document")
    p.set_defaults(func=run_inspect)
    p = sub.add_parser("recover", help="rewrite a recording whose writer was killed into a finished MCAP file",
                       description="Copy every readable record of IN (a file whose writer died: no index, no footer) "
                                   "into OUT with summary, index and footer, so any MCAP reader opens it.")
    p.add_argument("input", metavar="IN.mcap", help="the recording whose writer died")
    p.add_argument("output", metavar="OUT.mcap", help="the finished MCAP file to write")
    add_overwrite(p, "replace an existing OUT file")
    add_json(p, "print the check as one JSON document")
    p.set_defaults(func=run_recover)
