"""Helpers shared by CLI subcommands."""

from __future__ import annotations

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
