"""``mntes-stream ocs-bridge`` and the ``--hk`` / ``--t-bath-field`` options of convert, replay and g3-bridge."""

from __future__ import annotations

import contextlib
import tempfile
from pathlib import Path


def add_hk_args(p) -> None:
    """Bath temperature from OCS HK G3 files (the aggregator's), aligned by time."""
    g = p.add_argument_group("housekeeping from OCS", "bath temperature from OCS HK G3 files (the aggregator's), "
                                                      "in place of the input's own, aligned by time")
    g.add_argument("--hk", metavar="FILE|DIR", help="OCS HK G3 file, or a directory of them (searched below)")
    g.add_argument("--t-bath-field", metavar="FULL.FIELD.NAME",
                   help="the bath thermometer's field: feed address + field, e.g. "
                        "observatory.LS372.feeds.temperatures.Channel_06_T (unit K)")


def hk_fields(args):
    """The :class:`~mntes_stream.g3.ocs_hk.OcsFields` of ``--hk`` / ``--t-bath-field``, or None without ``--hk``."""
    from mntes_stream.errors import ConfigError

    hk, field = getattr(args, "hk", None), getattr(args, "t_bath_field", None)
    if not hk:
        if field:
            raise ConfigError("--t-bath-field names a field of --hk FILE|DIR: give --hk too")
        return None
    from mntes_stream.g3.ocs_hk import OcsFields  # with --hk only: its module imports numpy and the messages

    if not field:
        raise ConfigError("--hk needs --t-bath-field FULL.FIELD.NAME (e.g. observatory.LS372.feeds.temperatures."
                          "Channel_06_T)")
    return OcsFields(t_bath_field=field)


def hk_messages_of(args, setup: str, start_ns=None, end_ns=None) -> list | None:
    """``(t_ns, key, payload)`` housekeeping messages from ``--hk`` (None without it)."""
    fields = hk_fields(args)
    if fields is None:
        return None
    from mntes_stream.g3.ocs_hk import hk_from_files

    return hk_from_files(args.hk, fields, setup, start_ns, end_ns)


@contextlib.contextmanager
def recording_with_hk(args, source):
    """``convert``/``replay`` of an MCAP recording with ``--hk``: the recording's files plus one more
    holding the OCS readings (a recording that has its own bath temperature is refused: two thermometers
    would mix)."""
    if not getattr(args, "hk", None):
        hk_fields(args)  # --t-bath-field alone is an error
        yield source
        return
    from mntes_stream.errors import ConfigError
    from mntes_stream.io import keys
    from mntes_stream.io.mcap import McapFileWriter, Session, writer_description
    from mntes_stream.io.mcap.session import session_files

    files = session_files(source)
    session = Session(files, warn=False)
    counts = session.message_counts()
    setups = {keys.parse_key(t)["setup"] for t in counts if keys.kind_of(t) == "counts"}
    if len(setups) != 1:
        raise ConfigError(f"--hk: the recording's counts must be of one setup (found {sorted(setups)})")
    setup = setups.pop()
    own = counts.get(keys.hk_key(setup, "t_bath"), 0)
    if own:
        raise ConfigError(f"--hk: the recording has its own t_bath ({own} messages on {keys.hk_key(setup, 't_bath')}); "
                          "two thermometers would mix")
    msgs = hk_messages_of(args, setup, session.start_ns, session.end_ns)
    with tempfile.TemporaryDirectory(prefix="mntes-hk-") as tmp:
        side = Path(tmp) / "ocs-hk.mcap"
        with McapFileWriter(side, metadata={"mntes.recording": writer_description(
                mode="OCS housekeeping", input=str(args.hk), field=args.t_bath_field)}) as w:
            for t_ns, key, payload in msgs:
                w.write(key, payload, t_ns)
        yield [*files, side]


# The [ocs-bridge] settings the flags set (types, ranges, help from ocs.bridge.OcsBridgeSettings).
_BRIDGE = ("router", "realm", "t_bath_field", "b_field_field", "setup", "stale_s", "duration_s")


def bridge_config(args):
    """The ocs-bridge config from ``--config``/``--set``, the command line (which wins) and the zenoh flags."""
    from mntes_stream.cli._common import service_config, settings_from_args, zenoh_layer
    from mntes_stream.ocs.bridge import OcsBridgeService

    return service_config(OcsBridgeService, args.config, args.set, {"bridge": settings_from_args(args, _BRIDGE)},
                          zenoh_layer(args))


def run_bridge(args) -> int:
    from mntes_stream.cli._common import print_mapping
    from mntes_stream.ocs.bridge import OcsBridgeService, bridge_line
    from mntes_stream.service.base import stop_on_signals

    cfg = bridge_config(args)
    svc = OcsBridgeService(cfg)
    svc.owns()  # a config without any field is a one-line error before anything starts
    with stop_on_signals() as stop:
        result = svc.start(stop=stop)
    print_mapping(result, args.json)
    if not args.json:
        print(bridge_line(result))
    return 0


def _bridge_args(p) -> None:
    from mntes_stream.cli._common import add_json, add_settings_args, add_zenoh_args
    from mntes_stream.ocs.bridge import OcsBridgeSettings

    p.add_argument("--config", metavar="FILE", help="bridge TOML ([ocs-bridge], [zenoh]); flags override it")
    p.add_argument("--set", action="append", default=[], metavar="TABLE.KEY=VALUE", help="override a config value")
    add_settings_args(p, OcsBridgeSettings, _BRIDGE, {"duration_s": ("--duration",)},
                      metavars={"router": "ws://HOST:PORT/ws", "t_bath_field": "FULL.FIELD.NAME",
                                "b_field_field": "FULL.FIELD.NAME", "stale_s": "S", "duration_s": "S"})
    add_json(p, "print the final statistics as one JSON document")
    add_zenoh_args(p)
    p.set_defaults(func=run_bridge)


def register(sub) -> None:
    from mntes_stream.cli._common import arguments

    p = sub.add_parser("ocs-bridge", help="publish OCS housekeeping (bath temperature, field) from a crossbar router "
                                          "on zenoh",
                       description="Subscribe to the OCS feeds (WAMP topics through a crossbar router) of the fields "
                                   "named, and publish their readings as t_bath / b_field housekeeping messages with "
                                   "their own times, as the simulator does: the converter's staleness rules apply. "
                                   "Needs the ocs extra (autobahn).")
    arguments(p, _bridge_args)
