"""``mntes-stream foxglove``: serve a setup to the Foxglove app (``[foxglove]`` service)."""

from __future__ import annotations

from mntes_stream.cli._common import (
    add_zenoh_args,
    arguments,
    service_config,
    settings_from_args,
    setup_logging,
    zenoh_layer,
)

_SERVICE = ("setup", "bind", "port", "detectors", "per_module", "max_rate_hz", "duration_s")


def run_foxglove(args) -> int:
    from mntes_stream.service.foxglove import FoxgloveService, require_foxglove

    setup_logging(args.verbose)
    require_foxglove()  # checked before anything starts
    cfg = service_config(FoxgloveService, args.config, args.set, settings_from_args(args, _SERVICE), zenoh_layer(args))
    FoxgloveService(cfg).start()
    return 0


def _foxglove_args(p) -> None:
    from mntes_stream.cli._common import add_settings_args
    from mntes_stream.service.foxglove import FoxgloveConfig  # the service's module: `foxglove` alone needs it

    p.add_argument("--config", metavar="FILE", help="a [foxglove] config (services/foxglove.toml); flags override it")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    add_settings_args(p, FoxgloveConfig, _SERVICE, {"duration_s": ("--duration",)})
    p.add_argument("-v", "--verbose", action="store_true", help="log at INFO (default: warnings only)")
    add_zenoh_args(p)
    p.set_defaults(func=run_foxglove)


def register(sub) -> None:
    p = sub.add_parser(
        "foxglove",
        help="serve a setup live to the Foxglove app (Foxglove WebSocket protocol)",
        description="Subscribe to mntes/<setup>/{power,hk,status} and serve json channels (power of selected "
        "detectors per module, flag rates by name, housekeeping, converter status) on ws://127.0.0.1:8765 "
        "(open it in Foxglove: Open connection > Foxglove WebSocket). The [foxglove] service of `serve`, with flags.",
    )
    arguments(p, _foxglove_args)
