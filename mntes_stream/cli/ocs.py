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
    """The :class:`~mntes_stream.ocs.hk.OcsFields` of ``--hk`` / ``--t-bath-field``, or None without ``--hk``."""
    from mntes_stream.errors import ConfigError
    from mntes_stream.ocs.hk import OcsFields

    hk, field = getattr(args, "hk", None), getattr(args, "t_bath_field", None)
    if not hk:
        if field:
            raise ConfigError("--t-bath-field names a field of --hk FILE|DIR: give --hk too")
        return None
    if not field:
        raise ConfigError("--hk needs --t-bath-field FULL.FIELD.NAME (e.g. observatory.LS372.feeds.temperatures."
                          "Channel_06_T)")
    return OcsFields(t_bath_field=field)


def hk_messages_of(args, setup: str, start_ns=None, end_ns=None) -> list | None:
    """``(t_ns, key, payload)`` housekeeping messages from ``--hk`` (None without it)."""
    fields = hk_fields(args)
    if fields is None:
        return None
    from mntes_stream.ocs.hk import hk_from_files

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
