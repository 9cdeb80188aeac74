"""``mntes-stream params --from RUN.g3 --params BOLO.toml --out PARAMS.toml``: a G3 run's converter parameters.

``--from-board SERIAL[=HOST[:PORT]]`` (repeatable) instead of ``--from``:
the names and amps per count of IceBoards read over tuber now, as
``dfmux-bridge`` reads them (``dfmux.boardhk``), for a lab without a DAQ.

A DAQ's parameter list names bolometers; the converter, ``g3-bridge
--params`` and the recorder's provenance name detectors by id, and the gain
of each detector is the DfMux's amps per count in force. This command reads
the run's Wiring and first Housekeeping frame and writes the file they take
as it is (no Python needed; ``g3.files.write_converter_params``).
"""

from __future__ import annotations

from mntes_stream.cli._common import add_json, add_overwrite, add_quiet, claim_out, print_mapping


def run_boards(args) -> int:
    from mntes_stream.cli.g3 import quiet_spt3g
    from mntes_stream.dfmux.boardhk import board_params, parse_hosts, read_once
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3.power import load_g3_params
    from mntes_stream.io.paramfile import dump_params

    hosts = {}
    for b in args.from_board:  # SERIAL alone: where spt3g reaches it, iceboard<serial>.local:80
        hosts.update(parse_hosts([b]) if "=" in b or not b.strip().isdigit() else
                     {int(b): (f"iceboard{int(b):04d}.local", 80)})
    claim_out(args.out, args.overwrite, inputs=[args.params])
    quiet_spt3g()
    readings = [read_once(s, h, p) for s, (h, p) in hosts.items()]
    pdict, missing = board_params(load_g3_params(args.params), readings)
    if not pdict:
        raise ConfigError("no channel of the boards has parameters: keyed by the boards' mapped names or detector id?")
    where = ", ".join(f"board {s} ({h}:{p})" for s, (h, p) in hosts.items())
    dump_params(list(pdict.values()), args.out, metadata={
        "source": f"mntes-stream params: {args.params} for {where} (keyed by detector id, gain from the boards' "
                  "housekeeping)", "names": {d: n for r in readings for n, d in zip(r.wiring.names,
                                                                                     r.wiring.detector_ids) if n != d}})
    if not args.quiet or args.json:
        print_mapping({"params": args.out, "detectors": len(pdict), "boards": sorted(hosts), "from": args.params,
                       "without_parameters": len(missing)}, args.json)
    return 0


def run(args) -> int:
    from mntes_stream.cli.g3 import g3_input_config, quiet_spt3g
    from mntes_stream.errors import ConfigError
    from mntes_stream.g3.files import expand_inputs, is_g3, write_converter_params

    if bool(args.source) == bool(args.from_board):
        raise ConfigError("params: give --from RUN.g3 or --from-board SERIAL[=HOST[:PORT]], one of them")
    if args.from_board:
        return run_boards(args)
    if not is_g3(args.source):
        raise ConfigError(f"--from {args.source}: expected a G3 run (RUN.g3, .g3.gz, ...)")
    files = expand_inputs(args.source)
    claim_out(args.out, args.overwrite, inputs=[*files, args.params])
    quiet_spt3g()
    n = write_converter_params(files, args.params, args.out, g3_input_config(args))
    if args.quiet and not args.json:  # -q: no detail, the last line only
        print(f"wrote {args.out}: {n} detectors")
    else:
        print_mapping({"params": args.out, "detectors": n, "run": files[0], "from": args.params}, args.json)
    return 0


def register(sub) -> None:
    from mntes_stream.cli.g3 import add_g3_input_args

    p = sub.add_parser("params", help="the converter's parameter file for a G3 run or IceBoards (detector ids, their gain)",
                       description="Write the detector parameters of PARAMS (keyed by bolometer name or detector id) "
                                   "for the bolometers wired in a G3 run, keyed by detector id, each gain the DfMux "
                                   "amps per count of the run's first housekeeping: the file `serve` (converter), "
                                   "`g3-bridge --params` and `convert` take as it is. Bolometers without parameters "
                                   "are skipped with one warning.")
    p.add_argument("--from", dest="source", metavar="RUN.g3",
                   help="the G3 run (its Wiring and first DfMux Housekeeping frame are read)")
    p.add_argument("--from-board", action="append", default=[], metavar="SERIAL[=HOST[:PORT]]",
                   help="instead of --from: read this IceBoard's housekeeping now over tuber (its mapped channel "
                        "names, amps per count; default host iceboard<serial>.local:80); repeatable")
    p.add_argument("--params", required=True, metavar="FILE",
                   help="detector parameters (TOML) keyed by bolometer name or detector id, e.g. the "
                        "RUN.bolometer-params.toml `simulate --format g3` writes")
    p.add_argument("--out", required=True, metavar="PARAMS.toml", help="the parameter file to write")
    add_g3_input_args(p)
    add_overwrite(p, "replace an existing --out file")
    add_json(p)
    add_quiet(p)
    p.set_defaults(func=run)
