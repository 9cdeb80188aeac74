"""``mntes-stream monitor``: the quick-look page (or a terminal table) of a running setup."""

from __future__ import annotations

import argparse
import math
import sys
import time


def _in_range(cast, lo: float, hi: float, what: str):
    """An argparse ``type`` accepting ``cast(text)`` within [lo, hi]."""

    def parse(text: str):
        try:
            value = cast(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{what}: not a number: {text!r}") from None
        if not (math.isfinite(value) and lo <= value <= hi):
            raise argparse.ArgumentTypeError(f"{what} must be in [{lo:g}, {hi:g}], got {text}")
        return value

    return parse


_positive_hz = _in_range(float, 1e-3, 1e3, "f_HWP (Hz)")


def _f_hwp(text: str):
    return None if text == "auto" else _positive_hz(text)


def _settings(args):
    from mntes_stream.cli._common import zenoh_from_args
    from mntes_stream.monitor.aggregate import MonitorConfig

    config = MonitorConfig(history_s=args.history_s, f_hwp_hz=args.f_hwp, silent_s=args.silent_s, hk_stale_s=args.hk_stale_s)
    return config, zenoh_from_args(args)


def _run_text(sub, args) -> int:
    from mntes_stream.monitor.text import render_text

    clear = sys.stdout.isatty()
    t_end = time.monotonic() + args.duration if args.duration > 0 else None
    period = max(args.update_s, 0.1)
    time.sleep(min(period, 1.0))  # let a first interval of data arrive
    while True:
        with sub.lock:
            tick = sub.aggregator.tick(time.time_ns())
            screen = render_text(sub.aggregator, tick)
        print(("\x1b[H\x1b[2J" if clear else "") + screen + ("" if clear else "\n"), flush=True)
        if t_end is not None and time.monotonic() >= t_end:
            return 0
        time.sleep(period if t_end is None else max(min(period, t_end - time.monotonic()), 0.0))


def run_monitor(args) -> int:
    from mntes_stream.cli._common import setup_logging
    from mntes_stream.errors import import_extra
    from mntes_stream.monitor.subscriber import MonitorSubscriber

    setup_logging(args.verbose)
    config, zenoh = _settings(args)
    if not args.text:
        import_extra("aiohttp", "monitor")  # the page's server; checked before anything starts
        import_extra("plotly", "monitor")
    with MonitorSubscriber(args.setup, zenoh, config) as sub:
        try:
            if args.text:
                return _run_text(sub, args)
            from mntes_stream.monitor.server import serve

            def ready(host, port):
                shown = f"[{host}]" if ":" in host else host
                print(f"mntes-stream monitor: serving http://{shown}:{port}/ (setup {args.setup})", flush=True)

            serve(sub, args.bind, args.port, args.update_s, args.duration, ready)
        except KeyboardInterrupt:
            pass
    return 0


def register(sub) -> None:
    from mntes_stream.cli._common import add_zenoh_args
    from mntes_stream.io import keys

    p = sub.add_parser(
        "monitor",
        help="quick-look web page (or --text table) of power, housekeeping and service health",
        description="Subscribe to mntes/<setup>/{power,hk,status} and serve a live page on 127.0.0.1 "
        "(time streams, spectrum with HWP harmonics, channel-state grid, housekeeping, service health). "
        "Works the same on a live converter and on `mntes-stream replay`.",
    )
    p.add_argument("--setup", default=keys.DEFAULT_SETUP, help=f"setup name (default: {keys.DEFAULT_SETUP})")
    p.add_argument("--bind", default="127.0.0.1",
                   help="address to listen on (default 127.0.0.1; anything else exposes the page beyond this machine)")
    p.add_argument("--port", type=_in_range(int, 0, 65535, "port (0: any free port)"), default=8050, help="HTTP port (default 8050; 0 picks a free one)")
    p.add_argument("--text", action="store_true", help="print a live terminal table instead of serving the page")
    p.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: until Ctrl-C)")
    p.add_argument("--update-s", type=_in_range(float, 0.05, 60, "update period (s)"), default=0.5, help="update period of the page / table (s, default 0.5)")
    p.add_argument("--f-hwp", type=_f_hwp, default=0.77, metavar="HZ|auto",
                   help="HWP frequency whose 1f/2f/4f are marked (default 0.77 Hz, LFT); 'auto' estimates it")
    p.add_argument("--history-s", type=float, default=30.0, help="power history kept and plotted (s, default 30)")
    p.add_argument("--silent-s", type=float, default=3.0, help="a module without data this long is silent (s)")
    p.add_argument("--hk-stale-s", type=float, default=2.0, help="housekeeping not received this long is stale (s)")
    p.add_argument("-v", "--verbose", action="store_true")
    add_zenoh_args(p)
    p.set_defaults(func=run_monitor)
