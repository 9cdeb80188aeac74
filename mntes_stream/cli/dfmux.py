"""``mntes-stream dfmux-bridge``: IceBoard packets straight from the boards -> counts and housekeeping on zenoh."""

from __future__ import annotations

from mntes_stream.cli._common import add_quiet, add_zenoh_args, print_mapping
from mntes_stream.options import number

_FLAGS = {"setup": "setup", "interface": "interface", "boards": "board", "v2_boards": "v2_board", "sctp": "sctp",
          "chunk_samples": "chunk_samples", "duration_s": "duration", "t_bath_k": "t_bath_k",
          "b_field_t": "b_field_t", "bias": "bias", "board_hosts": "board_host", "hk_every_s": "hk_every",
          "hk_timeout_s": "hk_timeout", "hk_stale_s": "hk_stale", "board_hk": "board_hk",
          "board_names": "board_names", "params": "params"}


def run_bridge(args) -> int:
    import dataclasses

    from mntes_stream.cli._common import service_config, zenoh_layer
    from mntes_stream.dfmux.bridge import DfMuxBridgeService, ledger_line
    from mntes_stream.errors import ConfigError
    from mntes_stream.service.base import stop_on_signals

    cfg = service_config(DfMuxBridgeService, args.config, args.set, {}, zenoh_layer(args))
    flags = {k: (tuple(v) if isinstance(v, list) else v) for k, a in _FLAGS.items()
             if (v := getattr(args, a, None)) is not None}
    try:
        cfg = dataclasses.replace(cfg, bridge=dataclasses.replace(cfg.bridge, **flags))
    except ConfigError as exc:
        raise ConfigError(f"command line: {exc}") from None
    with stop_on_signals() as stop:
        result = DfMuxBridgeService(cfg).start(stop=stop)
    if args.json:
        print_mapping(result, True)
        return 0
    if not args.quiet:
        print(f"dfmux-bridge: G3 read with {result.get('spt3g', '?')}")
        for text in result.get("events", []):
            print(f"  {text}")
    print(ledger_line(result))  # the last line: what was published, never received, lost
    return 0


def register(sub) -> None:
    p = sub.add_parser("dfmux-bridge", help="publish IceBoard (DfMux) packets from the boards on zenoh, no DAQ",
                       description="Receive IceBoard packets with spt3g's own DfMuxCollector and DfMuxBuilder (UDP "
                                   "multicast on an interface, or SCTP to named boards) and publish counts per "
                                   "(board serial, module) and housekeeping as the simulator does, so the converter, "
                                   "recorder and monitor run unchanged. Missing samples go into the ledger; board "
                                   "restarts, late modules and silent boards are reported, never fatal.")
    p.add_argument("--config", metavar="FILE", help="bridge TOML ([dfmux-bridge], [zenoh]); flags override it")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    p.add_argument("--board", action="append", type=number(int, ge=0), metavar="SERIAL",
                   help="a V3/V4 board's serial (repeatable; every named board must send)")
    p.add_argument("--v2-board", action="append", metavar="IP=SERIAL",
                   help="a V2 board, which sends no serial: its IP address and serial (repeatable)")
    p.add_argument("--interface", metavar="ADDR", help="address of the interface the multicast arrives on")
    p.add_argument("--sctp", action="append", metavar="HOST",
                   help="read this board by SCTP instead of UDP multicast (repeatable; needs kernel SCTP)")
    p.add_argument("--setup", help="setup name in the keys (default lab)")
    p.add_argument("--chunk-samples", type=number(int, ge=1), help="samples per counts chunk per module (default 16, ~0.1 s)")
    p.add_argument("--duration", type=number(float, "s", ge=0), metavar="S", help="stop after this long (default: until Ctrl-C)")
    p.add_argument("--t-bath-k", type=number(float, "K", gt=0), metavar="K", help="bath temperature to publish (default: none)")
    p.add_argument("--b-field-t", type=number(float, "T"), metavar="T", help="magnetic field to publish (default 0)")
    p.add_argument("--bias", action="append", metavar="BOARD/MODULE=V",
                   help="bias table entry, RMS volts; * for any board or module (repeatable); a fallback: a module's "
                        "bias comes from its board's housekeeping once read")
    p.add_argument("--board-host", action="append", metavar="SERIAL=HOST[:PORT]",
                   help="where that board's tuber answers, if not at iceboard<serial>.local:80 (repeatable)")
    p.add_argument("--hk-every", type=number(float, "s", gt=0), metavar="S", help="read each board's housekeeping this often "
                   "(default 10 s)")
    p.add_argument("--hk-timeout", type=number(float, "s", gt=0), metavar="S", help="a board's tuber reply must come within this "
                   "(default 5 s)")
    p.add_argument("--hk-stale", type=number(float, "s", gt=0), metavar="S", help="a board's last good housekeeping holds this long, "
                   "then its samples are flagged HK_STALE (default 60 s)")
    p.add_argument("--params", metavar="FILE", help="detector parameters (keyed by detector id or the boards' "
                   "names): the boards' R_normal, R_frac achieved and loop gain are checked against them")
    p.add_argument("--no-board-hk", dest="board_hk", action="store_false", default=None,
                   help="do not read the boards' housekeeping (bias from --bias only)")
    p.add_argument("--no-board-names", dest="board_names", action="store_false", default=None,
                   help="detector ids b<serial>m<module>c<channel> even where the boards store mapped names")
    add_quiet(p)
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    add_zenoh_args(p)
    p.set_defaults(func=run_bridge)
