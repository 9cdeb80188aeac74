"""``mntes-stream transcode IN OUT --foxglove``: a recording with Foxglove-readable json channels added."""

from __future__ import annotations

from mntes_stream.options import number


def run(args) -> int:
    from mntes_stream.cli._common import claim_out
    from mntes_stream.foxglove.transcode import transcode
    from mntes_stream.foxglove.translate import FoxgloveView

    claim_out(args.output, args.overwrite, inputs=[args.input])
    view = FoxgloveView(args.detectors or (), args.per_module, args.max_rate_hz)
    st = transcode(args.input, args.output, foxglove=args.foxglove, view=view, compression=args.compression)
    damaged = getattr(st, "damaged", "")
    if damaged:
        import sys

        print(f"mntes-stream: warning: {args.input}: input DAMAGED: {damaged}", file=sys.stderr)
    print(f"{args.output}: {st.messages} messages copied, {st.json_messages} json messages added"
          f" ({st.undecodable} undecodable), {st.metadata} metadata records, {st.attachments} attachments,"
          f" {st.seconds:.1f} s" + (f"; input DAMAGED: {damaged} (marked in its mntes.damaged metadata)"
                                     if damaged else ""))
    return 0


def register(sub) -> None:
    p = sub.add_parser(
        "transcode",
        help="rewrite a recording, adding json channels the Foxglove app reads (--foxglove)",
        description="Copy every message of a recording (a file or a directory of rotated files) verbatim into one "
        "MCAP file, with its metadata and attachments and the flag/unit records; with --foxglove, also json "
        "channels with JSON Schemas: /mntes/<setup>/power/<board>/<module> (p_opt_pw.<detector id> in pW), "
        "/mntes/<setup>/flag_rates/<service>, /mntes/<setup>/hk/<sensor>, /mntes/<setup>/status/<service>.",
    )
    p.add_argument("input", metavar="IN", help="recording: an .mcap file or a directory")
    p.add_argument("output", metavar="OUT", help="the .mcap file to create")
    p.add_argument("--foxglove", action="store_true", help="add the json channels")
    p.add_argument("--detectors", nargs="+", metavar="ID", help="detector ids to show (default: first per module)")
    p.add_argument("--per-module", type=number(int, ge=0), default=4, metavar="N",
                   help="detectors per module when --detectors is not given (0: all; default 4)")
    p.add_argument("--max-rate-hz", type=number(float, "Hz", ge=0), default=0.0, metavar="HZ",
                   help="power samples per second and module at most (default 0: every sample)")
    p.add_argument("--compression", choices=("zstd", "lz4", "none"), default="zstd",
                   help="MCAP chunk compression of OUT (default zstd)")
    p.add_argument("--overwrite", action="store_true", help="replace an existing OUT file")
    p.set_defaults(func=run)
