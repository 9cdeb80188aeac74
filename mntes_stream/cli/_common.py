"""Helpers shared by CLI subcommands."""

from __future__ import annotations

import dataclasses

from mntes_stream.core.params import DetectorParams, table1_params
from mntes_stream.errors import ConfigError


def add_params_args(parser) -> None:
    parser.add_argument("--params", metavar="FILE", help="detector parameter file (TOML); default: the paper's Table 1 detector")
    parser.add_argument("--detector", metavar="ID", help="detector id in --params (default: the first)")


def params_from_args(args) -> DetectorParams:
    if not args.params:
        if args.detector:
            raise ConfigError("--detector needs --params")
        return table1_params()
    from mntes_stream.io.paramfile import load_params

    detectors = load_params(args.params)
    if args.detector is None:
        return next(iter(detectors.values()))
    try:
        return detectors[args.detector]
    except KeyError:
        raise ConfigError(f"detector {args.detector!r} not in {args.params}") from None


def add_zenoh_args(p) -> None:
    """``--connect/--listen/--mode/--zenoh-config``, overriding a config's [zenoh] table."""
    g = p.add_argument_group("zenoh (override the config file's [zenoh] table)")
    g.add_argument("--connect", action="append", metavar="ENDPOINT", help="e.g. tcp/127.0.0.1:7447 (repeatable)")
    g.add_argument("--listen", action="append", metavar="ENDPOINT", help="e.g. tcp/0.0.0.0:7447 (repeatable)")
    g.add_argument("--mode", choices=("peer", "client", "router"))
    g.add_argument("--zenoh-config", metavar="FILE", help="zenoh JSON5 config file")


def zenoh_overrides(args, z):
    """``z`` (a ``transport.ZenohSettings``) with the command line's zenoh options applied."""
    kw = {}
    if args.connect:
        kw["connect"] = tuple(args.connect)
    if args.listen:
        kw["listen"] = tuple(args.listen)
    if args.mode:
        kw["mode"] = args.mode
    if args.zenoh_config:
        kw["config_file"] = args.zenoh_config
    return dataclasses.replace(z, **kw)


def print_mapping(d: dict, as_json: bool, width: int = 24) -> None:
    """A command's result: one JSON object, or one right-aligned ``key: value`` per line (None skipped)."""
    import json

    if as_json:
        print(json.dumps(d, indent=2, default=str))
        return
    for key, value in d.items():
        if value is not None:
            print(f"{key:>{width}s}: {value}")
