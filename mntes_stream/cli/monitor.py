"""``mntes-stream monitor``: the quick-look page (or a terminal table) of a running setup (``[monitor]`` service)."""

from __future__ import annotations

import argparse
import math

from mntes_stream.cli._common import (
    add_zenoh_args,
    arguments,
    service_config,
    settings_from_args,
    setup_logging,
    zenoh_layer,
)

_SERVICE = ("setup", "bind", "allowed_hosts", "port", "update_s", "text", "duration_s", "params")
_VIEW = ("history_s", "long_history_s", "memory_mb", "silent_s", "hk_stale_s", "leakage_detectors",
         "leakage_window_s", "leakage_every_s")


def _f_hwp(text: str):
    if text == "auto":
        return "auto"
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"f_HWP: not a number or 'auto': {text!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise argparse.ArgumentTypeError(f"f_HWP must be > 0 Hz, got {text}")
    return value


def monitor_config(args):
    """The ``[monitor]`` config the command line asks for (``--config``, ``--set``, flags, zenoh flags)."""
    from mntes_stream.monitor.service import MonitorService

    view = settings_from_args(args, _VIEW)
    if args.f_hwp is not None:
        view["f_hwp_hz"] = None if args.f_hwp == "auto" else args.f_hwp
    return service_config(MonitorService, args.config, args.set, {**settings_from_args(args, _SERVICE), "view": view},
                          zenoh_layer(args))


def run_monitor(args) -> int:
    from mntes_stream.errors import import_extra
    from mntes_stream.monitor.service import MonitorService

    setup_logging(args.verbose)
    cfg = monitor_config(args)
    if not cfg.text:
        import_extra("aiohttp", "monitor")  # the page's server; checked before anything starts
        import_extra("plotly", "monitor")
    from mntes_stream.cli._common import setup_hint

    hint = setup_hint(cfg.zenoh, cfg.setup)  # a misspelt setup would wait forever, silently
    if hint:
        import sys

        print(f"mntes-stream: warning: {hint}", file=sys.stderr)
    MonitorService(cfg).start()
    return 0


def _monitor_args(p) -> None:
    from mntes_stream.cli._common import add_settings_args
    from mntes_stream.monitor.aggregate import MonitorConfig  # the monitor's modules: `monitor` alone needs them
    from mntes_stream.monitor.service import MonitorServiceConfig

    p.add_argument("--config", metavar="FILE", help="a [monitor] config (services/monitor.toml); flags override it")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    add_settings_args(p, MonitorServiceConfig, _SERVICE, {"duration_s": ("--duration",)})
    add_settings_args(p, MonitorConfig, _VIEW)
    p.add_argument("--f-hwp", type=_f_hwp, default=None, metavar="HZ|auto",
                   help="HWP frequency whose 1f/2f/4f are marked (default 0.77 Hz, LFT); 'auto' estimates it")
    p.add_argument("-v", "--verbose", action="store_true", help="log at INFO (default: warnings only)")
    add_zenoh_args(p)
    p.set_defaults(func=run_monitor)


def register(sub) -> None:
    p = sub.add_parser(
        "monitor",
        help="quick-look web page (or --text table) of power, housekeeping and service health",
        description="Subscribe to mntes/<setup>/{power,hk,status} and serve a live page on 127.0.0.1 "
        "(time streams over 30 s to 1 h, spectrum with HWP harmonics, focal-plane view by state, power, flag "
        "rate, noise or HWP leakage, the linear conversion's live 2f -> 4f nonlinearity against MNTES per "
        "detector (from the counts of --leakage-detectors detectors), housekeeping, service health, a badge "
        "that turns red when data stop). "
        "Works the same on a live converter and on `mntes-stream replay`. The [monitor] service of "
        "`serve`, with flags.",
    )
    arguments(p, _monitor_args)
