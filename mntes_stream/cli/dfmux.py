"""``mntes-stream dfmux-bridge``: IceBoard packets straight from the boards -> counts and housekeeping on zenoh."""

from __future__ import annotations

from mntes_stream.cli._common import add_quiet, add_zenoh_args, arguments, print_mapping

# The [dfmux-bridge] settings the flags set (their types, ranges and help come from DfMuxBridgeSettings); the
# flags keep the spellings they had before they were derived from the settings.
_BRIDGE = ("board_hosts", "boards", "v2_boards", "interface", "sctp", "setup", "chunk_samples", "duration_s",
           "t_bath_k", "b_field_t", "bias", "hk_every_s", "hk_timeout_s", "hk_stale_s", "params", "board_hk",
           "board_names")
_SPELLED = {"boards": "--board", "v2_boards": "--v2-board", "bias": "--bias", "board_hosts": "--board-host",
            "hk_every_s": "--hk-every", "hk_timeout_s": "--hk-timeout", "hk_stale_s": "--hk-stale",
            "board_hk": "--no-board-hk", "board_names": "--no-board-names"}
_METAVARS = {"boards": "SERIAL", "v2_boards": "IP=SERIAL", "sctp": "HOST", "interface": "ADDR",
             "bias": "BOARD/MODULE=V", "board_hosts": "SERIAL=HOST[:PORT]", "params": "FILE"}


def bridge_config(args):
    """The ``[dfmux-bridge]`` config the command line asks for (``--config``, ``--set``, flags, zenoh flags)."""
    from mntes_stream.cli._common import service_config, settings_from_args, zenoh_layer
    from mntes_stream.dfmux.bridge import DfMuxBridgeService

    return service_config(DfMuxBridgeService, args.config, args.set, {"bridge": settings_from_args(args, _BRIDGE)},
                          zenoh_layer(args))


def run_bridge(args) -> int:
    from mntes_stream.dfmux.bridge import DfMuxBridgeService, ledger_line
    from mntes_stream.service.base import stop_on_signals

    cfg = bridge_config(args)
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


def _bridge_args(p) -> None:
    from mntes_stream.cli._common import add_settings_args
    from mntes_stream.dfmux.bridge import DfMuxBridgeSettings

    p.add_argument("--config", metavar="FILE", help="bridge TOML ([dfmux-bridge], [zenoh]); flags override it")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    add_settings_args(p, DfMuxBridgeSettings, _BRIDGE, {"duration_s": ("--duration",)}, spelled=_SPELLED,
                      repeatable=("boards", "v2_boards", "sctp", "bias", "board_hosts"), metavars=_METAVARS)
    add_quiet(p)
    p.add_argument("--json", action="store_true", help="print the result as one JSON object")
    add_zenoh_args(p)
    p.set_defaults(func=run_bridge)


def register(sub) -> None:
    p = sub.add_parser("dfmux-bridge", help="publish IceBoard (DfMux) packets from the boards on zenoh, no DAQ",
                       description="Receive IceBoard packets with spt3g's own DfMuxCollector and DfMuxBuilder (UDP "
                                   "multicast on an interface, or SCTP to named boards) and publish counts per "
                                   "(board serial, module) and housekeeping as the simulator does, so the converter, "
                                   "recorder and monitor run unchanged. Missing samples go into the ledger; board "
                                   "restarts, late modules and silent boards are reported, never fatal.")
    arguments(p, _bridge_args)
