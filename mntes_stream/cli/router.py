"""``mntes-stream router`` (the ``[router]`` service) and ``mntes-stream ps`` (who is alive on a setup)."""

from __future__ import annotations

import json
import time

from mntes_stream.cli._common import (
    add_quiet,
    add_settings_args,
    add_zenoh_args,
    arguments,
    service_config,
    settings_from_args,
    setup_logging,
    zenoh_from_args,
    zenoh_layer,
)
from mntes_stream.options import number

_ROUTER = ("setup", "name", "duration_s")
# Counters whose rate ps shows, first found wins: what "rate" means for each kind of service.
_RATE_KEYS = ("samples_converted", "chunks_converted", "messages", "chunks_published", "chunks", "samples")


def run_router(args) -> int:
    from mntes_stream.service.router import RouterService

    setup_logging(not args.quiet)
    cfg = service_config(RouterService, args.config, args.set, settings_from_args(args, _ROUTER), zenoh_layer(args))
    RouterService(cfg).start()
    return 0


def _rates(first: list[dict], second: list[dict]) -> dict[tuple, tuple[str, float]]:
    """Per instance (key, zid): the rate it states (``samples_per_s``), else that of its first counter
    among ``_RATE_KEYS`` between two heartbeats."""
    before = {(b["key"], b.get("zid")): b for b in first}
    out = {}
    for b in second:
        if isinstance(b.get("samples_per_s"), (int, float)):
            out[(b["key"], b.get("zid"))] = ("samples", float(b["samples_per_s"]))
            continue
        a = before.get((b["key"], b.get("zid")))
        if a is None or "t_ns" not in a or "t_ns" not in b or b["t_ns"] <= a["t_ns"]:
            continue
        for k in _RATE_KEYS:
            if isinstance(b.get(k), (int, float)) and isinstance(a.get(k), (int, float)):
                out[(b["key"], b.get("zid"))] = (k, (b[k] - a[k]) / ((b["t_ns"] - a["t_ns"]) * 1e-9))
                break
    return out


def run_ps(args) -> int:
    from mntes_stream.core.lag import who_is_behind
    from mntes_stream.io.presence import list_services
    from mntes_stream.io.transport import ZenohSettings, open_session

    # ps is a client of whatever it is pointed at: it listens on nothing.
    zenoh = zenoh_from_args(args, ZenohSettings(mode="client" if args.connect else None))
    with open_session(zenoh) as session:
        first = list_services(session, args.setup, args.timeout)
        if args.interval > 0 and first:
            time.sleep(args.interval)
            second = list_services(session, args.setup, args.timeout)
        else:
            second = first
    rates = _rates(first, second)
    for b in second:
        if (b["key"], b.get("zid")) in rates:
            b["rate_counter"], b["rate_per_s"] = rates[(b["key"], b.get("zid"))]
    if args.json:
        print(json.dumps({"setup": args.setup, "services": second}, indent=2, default=str))
        return 0
    if not second:
        import sys

        from mntes_stream.cli._common import setup_hint

        print(f"no live services on setup {args.setup!r}")
        hint = setup_hint(zenoh, args.setup, args.timeout)
        if hint:
            print(f"mntes-stream: warning: {hint}", file=sys.stderr)
        return 0
    print(f"{'SERVICE':<11} {'NAME':<16} {'STATE':<9} {'UP':>7} {'RATE':>14} {'LAG':>8} {'LOST':>6}  HOST:PID  OWNS / WARNINGS")
    for b in second:
        rate = f"{b['rate_per_s']:.4g}/s" if "rate_per_s" in b else "-"
        lag = f"{b['latency_p99_ms']:.0f} ms" if isinstance(b.get("latency_p99_ms"), (int, float)) else "-"
        lost = b.get("chunks_lost", "-")
        up = f"{b['uptime_s']:.0f} s" if isinstance(b.get("uptime_s"), (int, float)) else "-"
        behind = who_is_behind(b.get("latency_p99_ms"), b.get("arrival_p99_ms"))
        extra = "; ".join([x for x in (_owns_text(b.get("owns") or {}), _coverage_text(b), _conflict_text(b)) if x]
                          + ([f"behind: {behind}"] if behind else []) + list(b.get("warnings") or []))
        print(f"{b['service']:<11} {b['name']:<16} {b.get('state', '?'):<9} {up:>7} {rate:>14} {lag:>8} {lost!s:>6}  "
              f"{b.get('host', '?')}:{b.get('pid', '?')}  {extra}")
    return 0


def _owns_text(owns: dict) -> str:
    """A converter's part of the focal plane on one line: shard, streams, and what it holds back or shares."""
    short = {k: v for k, v in owns.items() if k in ("shard", "boards", "modules", "streams", "publishing")}
    text = " ".join(f"{k}={v}" for k, v in short.items() if v not in ("*", "0/1"))
    if owns.get("held"):
        text += f" held={len(owns['held'])} ({owns.get('role', '?')})"
    if owns.get("conflict"):
        text += " CONFLICT with " + ",".join(sorted({n for s in owns.get("claimed_also_by", ()) for n in
                                                       s.partition(":")[2].split(",") if n}))
    return text


def _conflict_text(b: dict) -> str:
    """Streams two or more publishers send side by side (a converter's or recorder's ``conflicts``)."""
    c = b.get("conflicts") or {}
    return ("CONFLICT publishers " + ",".join(f"{s}:{n}" for s, n in sorted(c.items()))) if c else ""


def _coverage_text(b: dict) -> str:
    """What a recorder says of the streams it sees: counts without power, power gaps, counts recorded without
    power (the open holes, with their numbers)."""
    out = []
    if b.get("unconverted"):
        out.append("unconverted=" + ",".join(b["unconverted"]))
    if b.get("power_gaps"):
        out.append("power_gaps=" + ",".join(f"{s}:{n}" for s, n in sorted(b["power_gaps"].items())))
    if b.get("unpowered"):  # counts recorded without power, below the newest power: a hole while it is open
        seqs = b.get("unpowered_seqs") or {}
        out.append("unpowered=" + ",".join(f"{s}:{n}" + (f"({seqs[s]})" if s in seqs else "")
                                           for s, n in sorted(b["unpowered"].items())))
    return " ".join(out)


def _router_args(p) -> None:
    from mntes_stream.service.router import RouterConfig  # the router service's module: `router` alone needs it

    p.add_argument("--config", metavar="FILE", help="a [router] config (services/router.toml); flags override it")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    add_settings_args(p, RouterConfig, _ROUTER, {"duration_s": ("--duration",)})
    add_quiet(p)
    add_zenoh_args(p)
    p.set_defaults(func=run_router)


def register(sub) -> None:
    p = sub.add_parser("router", help="run a zenoh router (the hub services connect to as clients)",
                       description="A zenoh session in router mode, as zenoh's own zenohd: listens on "
                                   "tcp/127.0.0.1:7447 unless -l says otherwise, joins other routers named with -e. "
                                   "Recipes: services/README.md. The [router] service of `serve`, with flags.")
    arguments(p, _router_args)

    p = sub.add_parser("ps", help="list the live services of a setup (liveliness tokens and heartbeats)",
                       description="Every running service holds a zenoh liveliness token "
                                   "mntes/<setup>/alive/<service>/<name> and answers its heartbeat there. "
                                   "ps lists them from any host on the zenoh network: state, uptime, rate, lag, "
                                   "lost, what each owns, and its warnings (e.g. a dead connect endpoint).")
    p.add_argument("--setup", default="lab", help="setup name (default lab)")
    p.add_argument("--interval", type=number(float, "s", ge=0), default=0.5, metavar="S",
                   help="ask twice, S apart, to show rates (0: once, no rates; default 0.5)")
    p.add_argument("--timeout", type=number(float, "s", gt=0), default=1.0, metavar="S", help="how long to wait for answers (default 1)")
    p.add_argument("--json", action="store_true", help="one JSON document")
    add_zenoh_args(p)
    p.set_defaults(func=run_ps)
