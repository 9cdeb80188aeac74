"""``mntes-stream serve --config FILE`` (one service) and ``mntes-stream config check|show|template``.

``serve`` runs the service whose main table the config has (the registry,
``service/registry.py``, lists them; so does ``serve --help``) in this
process, until it ends or SIGINT/SIGTERM.
"""

from __future__ import annotations

import json
import logging
import sys
import threading

from mntes_stream.cli._common import add_quiet, add_zenoh_args, arguments, description, setup_logging, zenoh_layer
from mntes_stream.options import number


def _heartbeats(svc, every_s: float, done: threading.Event) -> None:
    """Log the service's heartbeat every ``every_s`` until ``done``."""
    log = logging.getLogger(f"mntes_stream.{svc.name}")
    while not done.wait(every_s):
        st = svc.status()
        counters = ", ".join(f"{k} {v}" for k, v in st.items() if k not in ("service", "name", "state", "since_beat_s")
                             and isinstance(v, (int, float)) and not isinstance(v, bool) and k != "uptime_s")
        # While a client waits for its router its state is the reason ("waiting for router ...").
        state = st.get("waiting_for") or st["state"] if st["state"] == "waiting" else st["state"]
        log.info("%s %s: %s, up %.0f s%s", st["service"], st["name"], state, st["uptime_s"],
                 f"; {counters}" if counters else "")


def run_serve(args) -> int:
    import dataclasses

    from mntes_stream.errors import ConfigError
    from mntes_stream.service.config import load_service_config, with_zenoh

    setup_logging(not args.quiet)
    service, config = load_service_config(args.config, args.set)
    config = with_zenoh(config, zenoh_layer(args))
    if args.duration is not None:
        if not hasattr(config, "duration_s"):
            raise ConfigError(f"--duration does not apply to the {service.name} service")
        config = dataclasses.replace(config, duration_s=args.duration)
    part = {k: v for k, v in (("shard", args.shard), ("boards", _numbers(args.boards, "--boards")),
                              ("modules", _numbers(args.modules, "--modules")), ("standby", args.standby or None))
            if v is not None}
    for key in part:
        if not hasattr(config, key):
            raise ConfigError(f"--{key} does not apply to the {service.name} service")
    if part:  # a converter's (or recorder's) part of the focal plane, as [converter] shard/boards/modules say
        config = dataclasses.replace(config, **part)
    svc = service(config)
    done = threading.Event()
    if args.heartbeat_s > 0:
        threading.Thread(target=_heartbeats, args=(svc, args.heartbeat_s, done), daemon=True).start()
    try:
        result = svc.start()
    finally:
        done.set()
    if args.json:
        print(json.dumps(result, indent=2, default=str))
    if isinstance(result, dict) and result.get("ledger_line"):  # the last line: what happened to every chunk
        label = " ".join(x for x in (service.name, getattr(config, "name", "")) if x)
        # ... and what a recording lacks (the recorder's ledger_note: counts recorded without power)
        print(f"{label}: {result['ledger_line']}{result.get('ledger_note') or ''}",
              file=sys.stderr if args.json else sys.stdout)
    return 0


def run_config(args) -> int:
    from mntes_stream.errors import ConfigError
    from mntes_stream.service.config import check_paths, render, show_file

    if args.set and args.action != "show":
        raise ConfigError(f"--set applies to config show, not config {args.action}")
    if args.action == "check":  # exit code 2 when any file is bad, as every command's bad input
        failed = 0
        for _path, line, ok in check_paths(args.files):
            if ok:
                print(line)
            else:
                print(f"mntes-stream: error: {line}", file=sys.stderr)
                failed += 1
        return 2 if failed else 0
    if args.action == "show":
        if len(args.files) != 1:
            raise ConfigError("config show takes one file")
        print(show_file(args.files[0], args.set))
        return 0
    from mntes_stream.service.registry import service_class

    for name in args.files:  # template: the defaults of the named services
        service = service_class(name)
        print(f"# {service.name}: {service.summary}. Every value below is the default.")
        print(render(_defaults(service), service.name))
    return 0


def _defaults(service):
    """The service's config with every default (a placeholder where one is required)."""
    from mntes_stream.errors import ConfigError

    try:
        return service.Config()
    except ConfigError:  # e.g. the converter needs params or tables
        return service.config_from_document({service.name: {"params": "params.toml"}})


def _numbers(text: str | None, flag: str) -> tuple[int, ...] | None:
    """``"0,3"`` -> ``(0, 3)``; None stays None."""
    if text is None:
        return None
    from mntes_stream.errors import ConfigError

    try:
        return tuple(int(x) for x in text.split(",") if x.strip())
    except ValueError:
        raise ConfigError(f"{flag} {text!r}: expected numbers separated by commas, e.g. 0,3") from None


def _description() -> str:
    from mntes_stream.service.registry import SERVICES  # every service's class, for its summary: the help alone

    listed = "; ".join(f"[{name}] {cls.summary}" for name, cls in SERVICES.items())
    return ("Run the service a config describes until it ends or SIGINT/SIGTERM, which stop "
            f"it cleanly. The config's main table names the service: {listed}. "
            "`mntes-stream config template SERVICE` prints a service's settings.")


def _serve_args(p) -> None:
    description(p, _description)
    p.add_argument("--config", required=True, metavar="FILE", help="e.g. services/converter.toml")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help="override a setting, e.g. converter.kind=exact (repeatable; VALUE in TOML)")
    p.add_argument("--duration", type=number(float, "s", ge=0), metavar="S", help="stop after S seconds (overrides duration_s)")
    p.add_argument("--shard", metavar="I/N", help="converter or recorder: own bucket I of N of the streams (shard)")
    p.add_argument("--boards", metavar="B,B", help="converter: own these boards only (boards)")
    p.add_argument("--modules", metavar="M,M", help="converter: ... and these modules (modules)")
    p.add_argument("--standby", action="store_true", help="converter: run as a hot standby (standby = true)")
    p.add_argument("--heartbeat-s", type=number(float, "s", ge=0), default=10.0, metavar="S",
                   help="log the service's heartbeat this often (0: never; default 10)")
    p.add_argument("--json", action="store_true", help="print the final statistics as JSON")
    add_quiet(p)
    add_zenoh_args(p)
    p.set_defaults(func=run_serve)


def _config_args(p) -> None:
    from mntes_stream.service.registry import SERVICES

    p.add_argument("action", choices=("check", "show", "template"), help="what to do")
    p.add_argument("files", nargs="+", metavar="FILE|DIR|SERVICE",
                   help="check: config files or directories; show: one file; template: service names "
                        f"({', '.join(SERVICES)})")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE",
                   help="show: override a setting before showing (repeatable)")
    p.set_defaults(func=run_config)


def register(sub) -> None:
    p = sub.add_parser("serve", help="run one service from its config file (services/*.toml)")
    arguments(p, _serve_args)

    p = sub.add_parser("config", help="check or show config files (services, parameters, zenoh JSON5)",
                       description="check: validate files and directories (service configs, detector parameter "
                                   "files, zenoh JSON5; in a directory its *.toml and *.json5 files, other files "
                                   "named are skipped with a note; exit code 2 when any is bad); "
                                   "show: print the effective config with every default; "
                                   "template: print a service's defaults (e.g. `config template recorder`).")
    arguments(p, _config_args)
