"""Command-line options shared by ``cli/`` and ``bench/``: zenoh's own flags, hidden deprecated aliases and
numbers checked against their range.

They live here, below both, because ``bench/`` is run by ``cli/bench.py``
and must not import ``cli/`` back (tests/test_layering.py); ``cli._common``
names them for the commands. docs/cli.md has the grammar.
"""

from __future__ import annotations

__all__ = ["add_zenoh_args", "deprecated_alias", "number", "zenoh_layer"]


def add_zenoh_args(p) -> None:
    """zenoh's own flags, as its example programs and router take them."""
    g = p.add_argument_group(
        "zenoh", "as zenoh's own programs take them; they override the config's [zenoh] table, which overrides "
                 "the zenoh config file (-c, else [zenoh] config_file, else $ZENOH_CONFIG), which overrides the "
                 "defaults (peer, listen on loopback only, scouting off)")
    g.add_argument("-c", "--zenoh-config", metavar="FILE", help="zenoh JSON5 config file")
    g.add_argument("-m", "--mode", choices=("peer", "client", "router"), help="zenoh mode")
    g.add_argument("-e", "--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("-l", "--listen", action="append", metavar="ENDPOINT", help="e.g. tcp/0.0.0.0:7447 (repeatable)")
    g.add_argument("--cfg", action="append", default=[], metavar="KEY:VALUE",
                   help="any zenoh config change, VALUE in JSON5, e.g. scouting/gossip/enabled:true (repeatable)")
    g.add_argument("--no-multicast-scouting", action="store_true", help="multicast scouting off (the default here)")


def zenoh_layer(args):
    """The command line's zenoh flags as a ``ZenohSettings`` layer (only what was given)."""
    from mntes_stream.io.transport import ZenohSettings

    return ZenohSettings(
        config_file=args.zenoh_config,
        mode=args.mode,
        connect=tuple(args.connect) if args.connect else None,
        listen=tuple(args.listen) if args.listen else None,
        multicast_scouting=False if args.no_multicast_scouting else None,
        cfg=tuple(args.cfg),
    )


def deprecated_alias(p, old: str, new: str, **kwargs) -> None:
    """A hidden ``old`` flag doing what ``new`` does, with one line on stderr naming ``new``."""
    import argparse
    import sys

    base = kwargs.pop("action", "store")

    class _Deprecated(argparse.Action):
        def __call__(self, parser, namespace, values, option_string=None):
            print(f"mntes-stream: warning: {option_string} is deprecated; use {new}", file=sys.stderr)
            if base == "store_true":
                setattr(namespace, self.dest, True)
            elif base == "append":
                setattr(namespace, self.dest, [*(getattr(namespace, self.dest, None) or []), values])
            else:
                setattr(namespace, self.dest, values)

    if base == "store_true":
        kwargs["nargs"] = 0
    p.add_argument(old, action=_Deprecated, help=argparse.SUPPRESS, **kwargs)


def number(kind: type = float, unit: str = "", *, ge: float | None = None, gt: float | None = None,
           le: float | None = None, lt: float | None = None, allow_inf: bool = False):
    """An argparse ``type``: ``kind`` (int or float) parsed from the text, finite, within the bounds.

    Out of range or not a number, argparse says one line naming the flag and
    the range in the words of a config file's error (``core.settings``):

    >>> import argparse
    >>> p = argparse.ArgumentParser(prog="up", exit_on_error=False)
    >>> _ = p.add_argument("--duration", type=number(float, "s", ge=0))
    >>> p.parse_args(["--duration", "-1"])
    Traceback (most recent call last):
    ...
    argparse.ArgumentError: argument --duration: expected a number (s) >= 0, got '-1'
    """
    import argparse
    import math
    import operator

    def parse(text: str):
        from mntes_stream.core.settings import Setting, expected  # when a value is given: no start-up cost

        s = Setting(unit=unit, ge=ge, gt=gt, le=le, lt=lt)
        try:
            value = kind(text)
        except ValueError:
            value = None
        ok = value is not None and (math.isfinite(value) or (allow_inf and value == math.inf)) and all(
            bound is None or test(value, bound) for bound, test in ((ge, operator.ge), (gt, operator.gt),
                                                                     (le, operator.le), (lt, operator.lt)))
        if not ok:
            raise argparse.ArgumentTypeError(f"expected {expected(kind, s)}{' or inf' if allow_inf else ''}, "
                                             f"got {text!r}")
        return value

    parse.__name__ = kind.__name__  # argparse's fallback words, should anything else go wrong
    return parse
